from pathlib import Path

import pytest

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data beside the repo; tests needing it skip only when the folder is absent."""
    if not DATA.is_dir():
        pytest.skip(f"real-data folder {DATA} not present")
    return DATA

import compileall
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"


def pytest_configure(config: pytest.Config) -> None:
    """Compile the repository's modules once: the integration tests start several hundred service
    processes, and where PYTHONDONTWRITEBYTECODE is set (this machine) each would compile every module
    it imports again (0.1 s or more of CPU per process). Python reads a .pyc only while it matches its
    source, so this changes what runs in no way."""
    for folder in ("quick_stream", "services", "tests"):
        compileall.compile_dir(str(REPO / folder), quiet=1)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data beside the repo; tests needing it skip only when the folder is absent."""
    if not DATA.is_dir():
        pytest.skip(f"real-data folder {DATA} not present")
    return DATA

"""The dead-code scan: vulture finds nothing unused in the product, the services or the tests.

Names only a library or ``__dict__`` uses are listed, with their reason, in
tests/tools/vulture_whitelist.py; anything else the scan finds is to be deleted.
"""
from __future__ import annotations

import subprocess
import sys

import pytest

from tests.tools import REPO

pytest.importorskip("vulture")  # the `test` extra installs it

SCAN = ["quick_stream", "services", "tests", "tests/tools/vulture_whitelist.py", "--min-confidence", "60"]

# Found in modules another change is rewriting (the services' loop: stream/runtime.py and
# core/render_stage.py); they go with that rewrite. Not a place for new entries.
PENDING = {
    ("quick_stream/core/render_stage.py", "unbatched"),
    ("quick_stream/stream/runtime.py", "received"),
    ("quick_stream/stream/runtime.py", "wake"),
}


def _pending(line: str) -> bool:
    path = line.split(":", 1)[0]
    return any(path == p and f"'{name}'" in line for p, name in PENDING)


def test_nothing_is_unused():
    r = subprocess.run([sys.executable, "-m", "vulture", *SCAN], cwd=REPO, capture_output=True, text=True)
    assert r.returncode in (0, 3), r.stderr  # 3: vulture found something
    found = [ln for ln in r.stdout.splitlines() if ln.strip() and not _pending(ln)]
    assert found == [], "\n".join(found)

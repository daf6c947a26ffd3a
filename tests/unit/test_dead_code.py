"""The dead-code scan: vulture finds nothing unused in the product, the services or the tests.

Names only a library or ``__dict__`` uses are listed, with their reason, in
tests/tools/vulture_whitelist.py; anything else the scan finds is to be deleted.
"""
from __future__ import annotations

import subprocess
import sys

from tests.tools import REPO


SCAN = ["quick_stream", "services", "tests", "tests/tools/vulture_whitelist.py", "--min-confidence", "60"]


def test_nothing_is_unused():
    r = subprocess.run([sys.executable, "-m", "vulture", *SCAN], cwd=REPO, capture_output=True, text=True)
    assert r.returncode in (0, 3), r.stderr  # 3: vulture found something
    found = [ln for ln in r.stdout.splitlines() if ln.strip()]
    assert found == [], "\n".join(found)

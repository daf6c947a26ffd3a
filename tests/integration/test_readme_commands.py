"""The README's commands run as a newcomer copies them (the ``quick-stream ...`` part of each shell line;
the venv and ``pip install`` around them are what CI's own run does, and ``pytest`` is this suite)."""
from __future__ import annotations

import re
import shlex
import subprocess
import sys

from tests.tools import REPO
from tests.unit.test_doc_commands import shown_commands


def test_the_readmes_commands_run_as_written(tmp_path):
    commands = shown_commands((REPO / "README.md").read_text())
    assert commands == ["quick-stream up"]  # the main job on the embedded default; a new one gets run here too
    for command in commands:
        argv = shlex.split(command)
        r = subprocess.run([sys.executable, "-m", "quick_stream", *argv[1:]], cwd=tmp_path, capture_output=True,
                           text=True, timeout=600)
        assert r.returncode == 0, r.stdout + r.stderr
        # all 300 when the machine keeps up; a loaded one sheds at the capture, as the line then says
        done = re.search(r"stabilized (\d+) of 300 frames: (\d+) shed at the capture", r.stdout + r.stderr)
        assert done and int(done[1]) + int(done[2]) == 300 and int(done[1]) > 0, r.stdout + r.stderr
        assert (tmp_path / "out" / "stabilized.avi").stat().st_size > 0
        assert (tmp_path / "out" / "recording.mcap").stat().st_size > 0

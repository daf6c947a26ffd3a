"""The services die with ``quick-stream up`` (quick_stream/stream/launcher.py, ``PARENT_DEATH``).

``up`` starts every child in its own session, so nothing but the parent-death signal ties them
to it: a SIGKILLed ``up`` (no chance to stop them) must not leave a router and five services
running. Each child gets SIGTERM when ``up`` dies and stops as on Ctrl-C.
"""
from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

from tests.helpers import UP, sent, wait_for_status

GONE_WITHIN_S = 60.0  # generous: a clean stop takes a second or two; the test waits on the event


def gone(pid: int) -> bool:
    """No such process any more, or a zombie (exited; its new parent has not reaped it yet)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return True
    return any(line.startswith("State:") and "Z" in line.split()[1] for line in status.splitlines())


def parent_of(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])


def test_every_child_stops_when_up_is_sigkilled(tmp_path):
    p = subprocess.Popen([*UP, "--out", str(tmp_path), "--source", "synthetic:frames=100000,width=160,height=120",
                          "--duration", "3600"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    pids: dict[str, int] = {}
    try:
        # every service up: the capture sends only once the others' liveliness tokens are there
        st = wait_for_status(tmp_path / "logs" / "status.json",
                             lambda s: all(v["running"] and v["pid"] for v in s["services"].values()) and sent(s) >= 1,
                             timeout=120)
        pids = {name: v["pid"] for name, v in st["services"].items()}
        assert set(pids) == {"router", "recorder", "flow", "motion", "render", "capture"}
        assert all(parent_of(pid) == p.pid and not gone(pid) for pid in pids.values()), pids
        assert all(os.getsid(pid) == pid for pid in pids.values())  # each in a session of its own
        os.kill(p.pid, signal.SIGKILL)
        p.wait(timeout=30)
        deadline = time.monotonic() + GONE_WITHIN_S
        while (running := {n for n, pid in pids.items() if not gone(pid)}) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not running, f"still running {GONE_WITHIN_S:g} s after up was killed: {sorted(running)}"
    finally:
        if p.poll() is None:
            p.kill()
        for pid in pids.values():  # the test failed: leave nothing behind
            if not gone(pid):
                os.kill(pid, signal.SIGKILL)

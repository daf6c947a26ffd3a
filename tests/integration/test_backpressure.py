"""A deliberately slowed render stage: nothing upstream grows, frames are dropped early and counted
(by the live capture, which sheds what the pipeline cannot take; with shedding off, by render, which
drops the oldest frames it holds), and memory stays bounded. The slow render is the test tool
tests/tools/slow_render.py: the real render service with every frame slowed."""
from __future__ import annotations

from pathlib import Path

from tests.helpers import pipeline, recorded, wait_for_log
from tests.tools import repo_env

FRAMES = 100  # 6.7 s at 15 frames/s: the slowed render takes ~8, so the capture sheds within seconds


def peak_rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmHWM")


def test_a_slow_render_makes_the_live_capture_shed_and_nothing_downstream_drops(tmp_path):
    """The capture sends only what the pipeline takes (shedding, counted), so render drops nothing
    and every frame sent comes out. (Without the capture's shedding, --shed off or a publisher that
    is not ours, the flow stage sheds for every stage: tests/integration/test_flood.py.)"""
    # 120 ms more per frame: at most ~8 frames/s against 15 coming in (15, not 30: flow keeps twice its
    # pace in hand, so a second suite beside this one does not make flow drop frames of its own, which
    # is not what this test is about)
    capture = ["--source", f"synthetic:frames={FRAMES},width=320,height=240", "--fps", "15"]
    sup, _ = pipeline(tmp_path, capture=capture, render=["--slow-ms", "120"], render_module="tests.tools.slow_render",
                      env=repo_env())
    peaks = {}
    try:
        wait_for_log(sup, tmp_path / "logs" / "render.log", "end of stream")
        peaks = {n: peak_rss_mb(sup.pid(n)) for n in ("flow", "motion", "render", "recorder")}
    finally:
        codes = sup.stop()
    assert all(c == 0 for c in codes.values()), codes
    stats, by_type = recorded(tmp_path / "rec.mcap")
    out = len(by_type.get("stabilized", []))
    r, f, c = stats["render"], stats["flow"], stats["capture"]
    assert c["shed"] > 0 and c["sent"] + c["shed"] == FRAMES  # dropped at the source, counted
    assert r["dropped"] == 0 and r["missing"] == 0 and out == c["sent"]  # every frame sent comes out
    assert f.get("inbox0_dropped", 0) == 0  # upstream did not have to drop anything
    assert peaks["render"] < 450 and peaks["flow"] < 300 and peaks["motion"] < 300, peaks

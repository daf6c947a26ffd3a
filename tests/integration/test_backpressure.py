"""A deliberately slowed render stage: nothing upstream grows, frames are dropped early and counted
(by the live capture, which sheds what the pipeline cannot take; with shedding off, by render, which
drops the oldest frames it holds), and memory stays bounded. The slow render is the test tool
tests/tools/slow_render.py: the real render service with every frame slowed."""
from __future__ import annotations

import time
from pathlib import Path

from quick_stream.io.recording import read_messages
from quick_stream.stream.launcher import ServiceSpec, Supervisor, free_port
from quick_stream.stream.wire import decode
from tests.helpers import start_router
from tests.tools import repo_env

FRAMES = 150


def peak_rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmHWM")


def test_a_slow_render_makes_the_live_capture_shed_and_nothing_downstream_drops(tmp_path):
    """The capture sends only what the pipeline takes (shedding, counted), so render drops nothing
    and every frame sent comes out. (Without shedding, --shed off or a publisher that is not ours,
    render drops the oldest frames it holds beyond --max-frames and counts them: the render stage's
    bound, tests/unit/test_stages.py.)"""
    ep = f"tcp/127.0.0.1:{free_port()}"
    z = ["-e", ep, "--no-multicast-scouting"]
    specs = [ServiceSpec("router", ["-m", "quick_stream", "router", "-l", ep, "--no-multicast-scouting"]),
             ServiceSpec("recorder", ["-m", "quick_stream.services.recorder", *z,
                                      "--output", str(tmp_path / "rec.mcap")]),
             ServiceSpec("flow", ["-m", "quick_stream.services.flow", *z]),
             ServiceSpec("motion", ["-m", "quick_stream.services.motion", *z]),
             # 120 ms more per frame: at most ~8 frames/s against 15 coming in (15, not 30: flow keeps
             # twice its pace in hand, so a second suite beside this one does not make flow drop frames
             # of its own, which is not what this test is about)
             ServiceSpec("render", ["-m", "tests.tools.slow_render", *z, "--slow-ms", "120"]),
             ServiceSpec("capture", ["-m", "quick_stream.services.capture", *z, "--source",
                                     f"synthetic:frames={FRAMES},width=320,height=240", "--fps", "15",
                                     "--wait-for", "recorder,flow,motion,render"], may_finish=True)]
    sup = Supervisor(specs, tmp_path / "logs", max_restarts=0, env=repo_env())
    start_router(sup, ep)
    for s in specs[1:]:
        sup.start(s.name)
    log = tmp_path / "logs" / "render.log"
    peaks = {}
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            time.sleep(0.5)
            sup.poll()
            if log.exists() and "end of stream" in log.read_text():
                break
        else:
            raise AssertionError(log.read_text()[-800:])
        peaks = {n: peak_rss_mb(sup.pid(n)) for n in ("flow", "motion", "render", "recorder")}
    finally:
        codes = sup.stop()
    assert all(c == 0 for c in codes.values()), codes
    stats = {}
    out = 0
    for topic, _, data in read_messages(tmp_path / "rec.mcap"):
        if not topic.startswith("quick/"):
            continue  # Foxglove channels
        m = decode(data)
        if m.type == "stats":
            stats[m.obj.service] = m.obj.values
        elif m.type == "stabilized":
            out += 1
    r, f, c = stats["render"], stats["flow"], stats["capture"]
    assert c["shed"] > 0 and c["sent"] + c["shed"] == FRAMES  # dropped at the source, counted
    assert r["dropped"] == 0 and r["missing"] == 0 and out == c["sent"]  # every frame sent comes out
    assert f.get("inbox0_dropped", 0) == 0  # upstream did not have to drop anything
    assert peaks["render"] < 450 and peaks["flow"] < 300 and peaks["motion"] < 300, peaks

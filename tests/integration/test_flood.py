"""A publisher that is not our capture floods the frame key far faster than the pipeline takes frames
(docs/architecture.md, Overload; docs/reliability.md): the flow stage decides once which frames are
shed, names them, and every stage follows. No work is spent on a frame another stage dropped:
every frame flow and motion processed comes out, nothing else does, and render flags no orphan.
Before, flow's queue and render's buffer shed different frames (render decoded and held every frame,
dropped frames flow had taken and rendered flow's shed frames as flagged orphans). Counts only, no clocks.
"""
from __future__ import annotations

import subprocess
import sys

from quick_stream.io.recording import read_messages
from quick_stream.stream.wire import WireError, decode
from tests.helpers import pipeline, recorded, wait_for_log
from tests.tools import repo_env

FPS, SECONDS = 240, 2  # 480 frames of 320x240 from a foreign publisher, against a render slowed to ~20 frames/s
# The publisher waits for a congested link (zenoh's default drops for it): every stage gets every
# frame, so the account is exact. (A frame lost on flow's link alone is one flow never saw, not one
# it shed: render renders it uncorrected and flagged, as any frame skipped upstream.)


def test_a_foreign_flood_is_shed_once_by_flow_and_every_stage_follows(tmp_path):
    sup, ep = pipeline(tmp_path, render=["--slow-ms", "50"], render_module="tests.tools.slow_render", env=repo_env())
    try:
        pub = subprocess.run([sys.executable, "-m", "tests.tools.flood", "publish", ep, "--fps", str(FPS),
                              "--seconds", str(SECONDS), "--size", "320x240", "--loop", "90",
                              "--wait-for", "recorder,flow,motion,render", "--block"],
                             capture_output=True, text=True, timeout=300, env=repo_env())
        assert pub.returncode == 0, pub.stderr[-3000:]
        wait_for_log(sup, tmp_path / "logs" / "render.log", "end of stream", timeout=300)
    finally:
        codes = sup.stop()
    assert all(c == 0 for c in codes.values()), codes
    stats, _ = recorded(tmp_path / "rec.mcap")
    f, r = stats["flow"], stats["render"]
    flows, corrected, out, flagged, named = [], set(), set(), set(), []
    for topic, _, data in read_messages(tmp_path / "rec.mcap"):
        try:
            m = decode(data)
        except WireError:
            continue
        stage = topic.rsplit("/", 1)[-1]
        if m.type == "flow":
            flows.append((m.seq, m.obj.seq_next))
            named += m.shed
        elif m.type == "end" and stage == "flow":
            named += getattr(m.obj, "shed", ())
        elif m.type == "correction":
            corrected.add(m.seq)
        elif m.type == "stabilized":
            out.add(m.seq)
            if m.obj.flags:
                flagged.add(m.seq)
    # render spent nothing on frames flow shed and dropped nothing flow had taken
    assert (r["orphans"], r["missing"], r["dropped"], r["flagged"]) == (0, 0, 0, 0), r
    assert not flagged and out == corrected  # every frame processed upstream came out, and nothing else
    assert not out & set(named)
    # the flood was shed, once, at flow, every frame shed named once; render let go what it had of them
    assert f["shed"] == len(named) == len(set(named)) > 0.5 * FPS * SECONDS
    assert 0 < r["shed_upstream"] <= f["shed"]
    assert len(out) >= len(flows) > 0 and f.get("inbox0_dropped", 0) == 0

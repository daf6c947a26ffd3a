"""A slow foreign subscriber costs the pipeline nothing (docs/deployment.md, "Delivery guarantees per key").

A viewer that is not part of the pipeline joins the router as a zenoh *peer* (it listens, so gossip
gives it direct links to the services, flow's included), subscribes to every key of the stream
through a bounded ``FifoChannel`` and then stops reading: zenoh's receive path for it waits, its
links back up. Before, flow's lossless (``CongestionControl.BLOCK``) publisher then waited for that
link for zenoh's ``wait_before_close`` (5 s) until the link was closed: flow's inbox overflowed
(36-45 frames dropped at 15 frames/s), the path restarted there (those frames flagged) and the
output paused ~6 s (``python -m tests.tools.slow_viewer``, docs/reliability.md). Now the pipeline's
lossless publishers drop for a congested link only, and the healthy receivers recover what their
own link missed from the publishers' caches: every frame sent comes out, none flagged, nothing
dropped or lost anywhere in the pipeline. Counts only, no clocks.
"""
from __future__ import annotations

import json
import subprocess
import sys

from tests.helpers import pipeline, recorded, wait_for_log
from tests.tools import repo_env

FRAMES = 105  # 7 s at 15 frames/s: the viewer's links back up within the first second, and the
# publishers' old 5 s wait for a congested link (wait_before_close) would fall inside it


def test_slow_peer_viewer_costs_the_pipeline_nothing(tmp_path):
    capture = ["--source", f"synthetic:frames={FRAMES},width=320,height=240", "--fps", "15"]
    sup, ep = pipeline(tmp_path, capture=capture)
    # a foreign peer reading a FifoChannel(4) of quick/@v1/cam0/** one sample per 1000 s: it stops reading
    viewer = subprocess.Popen([sys.executable, "-m", "tests.tools.slow_viewer", "viewer", ep, "peer",
                               "quick/@v1/cam0/**", "fifo", "1000"], stdout=subprocess.PIPE, text=True, env=repo_env())
    try:
        wait_for_log(sup, tmp_path / "logs" / "render.log", "end of stream")
    finally:
        viewer.terminate()
        text, _ = viewer.communicate(timeout=30)
        codes = sup.stop()
    assert all(c == 0 for c in codes.values()), codes
    seen = json.loads(text.strip().splitlines()[-1])
    assert seen["viewer_received"] >= 1 and seen["viewer_direct_peers"] >= 1  # it was there, as a peer
    stats, by_type = recorded(tmp_path / "rec.mcap")
    c, f, m, r = stats["capture"], stats["flow"], stats["motion"], stats["render"]
    assert c["sent"] + c["shed"] == FRAMES
    assert f["inbox0_dropped"] == 0  # flow kept up: its publisher never held it
    assert m["inbox0_lost"] == 0 and r["inbox0_lost"] == 0 and r["inbox1_lost"] == 0
    assert r["missing"] == 0
    assert len(by_type["stabilized"]) == c["sent"]  # every frame sent came out
    if c["shed"] == 0:  # a machine too busy for 15 frames/s sheds some, and a gap flags frames: not the viewer's doing
        assert r["flagged"] == 0 and r["orphans"] == 0

"""A capture renumbered mid-stream, through the running services (docs/reliability.md, "Renumbered
stream"): frames 0..39, then the camera's next frames numbered from 0 again, as a hand-started
capture that did not ask the stream's cursor publishes them, into router + recorder + flow +
motion + render. The output goes on: the old numbering to its end, then, after the 15 frames in a
row that confirm the new numbering, the new one (the path restarts at its first frame, handed over
without a jump: corrected, named a restart), each stage counting one renumbering. Before, every frame after 39 was refused as out of
order and the stream halted for good.
"""
from __future__ import annotations

import argparse
import threading
import time
from pathlib import Path

import pytest

from tests.helpers import pipeline, recorded, wait_for_log

from quick_stream.core.continuity import ContinuityParams, RENUMBERED
from quick_stream.io.sources import open_source
from quick_stream.stream import keys
from quick_stream.stream.runtime import ServiceRuntime
from quick_stream.stream.transport import add_zenoh_args, config_from_args
from quick_stream.stream.wire import EndOfStream, encode_end, encode_frame
from quick_stream.stream.wire.codec import peek

OLD, NEW = 40, 45
FIRST = ContinuityParams().resync - 1  # the new numbering's first frame taken (0..13 are refused)
# paced by the pipeline, as `capture --pace fast` is: at most AHEAD frames sent and not yet through the
# motion stage (flow's queue, 30, never overflows, and flow's admission, which sheds for a foreign
# publisher that runs ahead of the motion stage, never sheds) and WINDOW not yet stabilized (the
# planner's window and a release)
AHEAD, WINDOW = 10, 45


def inject(ep: str) -> None:
    """Publish the stream, each frame stamped with its publication time, paced by flow's and render's output."""
    frames = list(open_source(f"synthetic:frames={OLD + NEW},width=160,height=120"))
    p = argparse.ArgumentParser()
    add_zenoh_args(p)
    conf = config_from_args(p.parse_args(["-e", ep, "--no-multicast-scouting"]))
    out = threading.Condition()
    got = {"motion": 0, "stabilized": 0}

    def came(sample) -> None:
        mtype = peek(sample.payload.to_bytes())[0]
        if mtype in got:
            with out:
                got[mtype] += 1
                out.notify_all()

    with ServiceRuntime("injector", "cam0", conf, install_signals=False) as rt:
        rt.subscribe(keys.key("cam0", "motion"), came)
        rt.subscribe(keys.key("cam0", "stabilized"), came)
        pub = rt.publisher("frame", lossless=True)
        missing = rt.wait_for(["recorder", "flow", "motion", "render"], 60)
        assert not missing, missing
        owed = {"motion": 0, "stabilized": 0}  # what the frames sent so far make (the refused ones: nothing)
        for i, f in enumerate(frames):
            seq = i if i < OLD else i - OLD
            pub.put(encode_frame(f.with_(seq=seq), "cam0", color="raw", pub_ns=time.time_ns()))
            refused = OLD <= i < OLD + FIRST
            owed["motion"] += 0 < i and not refused
            owed["stabilized"] += not refused
            with out:
                assert out.wait_for(lambda: got["motion"] >= owed["motion"] - AHEAD
                                    and got["stabilized"] >= owed["stabilized"] - WINDOW, 60), (got, owed)
        # as the capture does before its end: every service that receives frames has the last one
        # (their cursors follow the new numbering)
        assert not rt.lagging("frame", NEW - 1, 60)
        pub.put(encode_end(EndOfStream(NEW - 1, "test stream end"), "cam0"))


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> tuple[dict, dict]:
    tmp: Path = tmp_path_factory.mktemp("resync")
    sup, ep = pipeline(tmp)
    try:
        inject(ep)
        wait_for_log(sup, tmp / "logs" / "render.log", "end of stream")
        restarts = {n: c.restarts for n, c in sup.children.items()}
    finally:
        codes = sup.stop()
    assert all(c == 0 for c in codes.values()), codes
    assert not any(restarts.values()), restarts
    return recorded(tmp / "rec.mcap")


def test_a_capture_renumbered_mid_stream_keeps_the_output_going(run):
    stats, by_type = run
    out = [(m.seq, bool(m.obj.flags)) for m in by_type["stabilized"]]
    assert [s for s, _ in out] == list(range(OLD)) + list(range(FIRST, NEW))  # in order, each once
    assert not any(flagged for _, flagged in out)
    restarts = [m for m in by_type["correction"] if m.obj.motion == "restart"]  # the break: the path restarts
    assert [m.seq for m in restarts] == [FIRST] and RENUMBERED in restarts[0].obj.reason
    f, m, r, rec = stats["flow"], stats["motion"], stats["render"], stats["recorder"]
    assert (f["renumberings"], f["out_of_order_frames"], f["refused_frames"], f["shed"]) == (1, FIRST, FIRST, 0)
    assert (m["renumberings"], m["refused_flows"]) == (1, 0)
    assert (r["renumberings"], r["refused_frames"], r["orphans"], r["missing"]) == (1, FIRST, 0, 0)
    assert f["internal_errors"] == m["internal_errors"] == r["internal_errors"] == 0
    # the recorder's account followed the new numbering of frame, flow, motion, correction and
    # stabilized: nothing counted missing, late or twice
    assert rec["renumberings"] == 5 and rec["unreceived"] == rec["late"] == rec["duplicates"] == 0, rec

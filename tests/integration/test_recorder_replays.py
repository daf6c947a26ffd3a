"""A restarted publisher sends again what its predecessor had sent (issue 30, row 8): a restarted
motion service resumes after the newest correction, so the motions its predecessor had published
past it go out a second time, byte for byte. The recorder logged a false renumbering (15 seqs in a
row behind the newest) and stored each of them twice. Now they are recognised as replays on
arrival: stored once, counted (``replays``), and the account of the stage goes on (no renumbering).

Through a router and the recorder service: one publisher session sends motions 0..39 and closes (the
killed motion service), a second one sends 20..44 (its successor: 20..39 again, the same bytes,
then new ones), and one message with a seq already recorded and other bytes (a conflict: kept).
"""
from __future__ import annotations

import argparse
import threading
from pathlib import Path

import numpy as np

from tests.helpers import pipeline_specs, recorded, start_pipeline

from quick_stream.core.motion import MotionEstimate
from quick_stream.stream import keys
from quick_stream.stream.launcher import free_port
from quick_stream.stream.runtime import ServiceRuntime
from quick_stream.stream.transport import add_zenoh_args, config_from_args
from quick_stream.stream.wire import decode, encode_motion

FIRST, REPLAY_FROM, LAST = 40, 20, 45  # the predecessor's motions 0..39; its successor's 20..44


def motion(seq: int, tx: float = 0.01) -> bytes:
    m = np.eye(4)
    m[:3, 3] = (tx * seq, 0.0, 0.02)
    return encode_motion(MotionEstimate(seq, seq + 1, "se3", "exact", m, np.zeros(6), True, "", 100, 1.0, 0.1,
                                        None), "cam0")


def publish(ep: str, seqs: range, extra: list[bytes] = ()) -> dict:
    """As a motion service: ``seqs`` on the motion key, then ``extra``; waits until the recorder has the
    last of ``seqs`` and returns the recorder's first stats after that which count the ``extra`` (each
    a ledger duplicate: a seq it had)."""
    p = argparse.ArgumentParser()
    add_zenoh_args(p)
    conf = config_from_args(p.parse_args(["-e", ep, "--no-multicast-scouting"]))
    got: dict = {}
    seen = threading.Event()
    with ServiceRuntime("motion", "cam0", conf, install_signals=False) as rt:
        armed = threading.Event()

        def stats(sample) -> None:
            m = decode(sample.payload.to_bytes())
            if armed.is_set() and m.obj.service == "recorder" and m.obj.values.get("duplicates", 0) >= len(extra):
                got.update(m.obj.values)
                seen.set()

        rt.subscribe(keys.key("cam0", "stats"), stats)
        pub = rt.publisher("motion", lossless=True)
        assert not rt.wait_for(["recorder"], 60)
        for s in seqs:
            pub.put(motion(s))
        for data in extra:
            pub.put(data)
        assert not rt.lagging("motion", seqs[-1], 60, required=frozenset({"recorder"}))
        armed.set()
        assert seen.wait(60), "no stats from the recorder"
    return got


def test_a_restarted_publishers_replay_is_stored_once_and_is_no_renumbering(tmp_path: Path):
    ep = f"tcp/127.0.0.1:{free_port()}"
    sup = start_pipeline(pipeline_specs(tmp_path, ep, stages=False), tmp_path, ep)
    try:
        publish(ep, range(FIRST))  # the motion service, killed after motion 39
        conflict = motion(LAST - 1, tx=0.5)  # the successor's own motion 44 sent again, other bytes
        stats = publish(ep, range(REPLAY_FROM, LAST), [conflict])
    finally:
        codes = sup.stop()
    assert all(c == 0 for c in codes.values()), codes
    replays = FIRST - REPLAY_FROM
    assert stats["replays"] == replays and stats["seq_conflicts"] == 1, stats
    assert stats["renumberings"] == 0 and stats["duplicates"] == 1 and stats["unreceived"] == 0, stats
    _, by_type = recorded(tmp_path / "rec.mcap")
    seqs = [m.seq for m in by_type["motion"]]
    assert sorted(seqs) == sorted([*range(LAST), LAST - 1]), seqs  # each once; the conflict kept beside the first
    log = (tmp_path / "logs" / "recorder.log").read_text()
    assert "numbering restarts" not in log, log
    assert f"cam0/motion: motion seq {REPLAY_FROM} arrived again, byte for byte" in log, log
    assert f"cam0/motion: motion seq {LAST - 1} arrived again with different bytes" in log, log

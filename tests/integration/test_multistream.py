"""Two cameras on one deployment (docs/deployment.md, "Several cameras"): two streams, one router,
one recorder, side by side.

Each stream has its own capture, flow, motion and render (one process per stream per stage);
both run side by side, each paced by its own pipeline; each stream's output equals its own single-stream result
bit for bit (nothing of one leaks into the other), and one recorder keeps both.
"""
from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np
from tests.helpers import capture_spec, offline_images, pipeline_specs, stage_specs, start_pipeline

from quick_stream.stream.launcher import free_port
from quick_stream.io.recording import read_messages
from quick_stream.stream.wire import decode

SPECS = {"cam0": "synthetic:frames=90,width=320,height=240,seed=1",
         "cam1": "synthetic:frames=90,width=320,height=240,seed=2"}


def test_two_streams_side_by_side_at_full_rate(tmp_path: Path):
    ep = f"tcp/127.0.0.1:{free_port()}"
    specs = pipeline_specs(tmp_path, ep, recorder=["--all-streams"], stages=False)  # router, recorder
    z = ["-e", ep, "--no-multicast-scouting"]
    for cam in SPECS:
        specs += stage_specs(z, cam, render=["--png", str(tmp_path / cam), "--color", "raw"])
    for cam, spec in SPECS.items():
        specs.append(capture_spec(z, ["--stream", cam, "--source", spec, "--color", "raw", "--pace", "fast",
                                      "--wait-timeout", "60"], ["flow", "motion", "render"], f"capture-{cam}"))
    sup = start_pipeline(specs, tmp_path, ep)
    deadline = time.monotonic() + 120
    logs = {cam: tmp_path / "logs" / f"render-{cam}.log" for cam in SPECS}
    try:
        while time.monotonic() < deadline:
            time.sleep(0.5)
            sup.poll()
            rec_log = tmp_path / "logs" / "recorder.log"
            if (all(p.exists() and "end of stream" in p.read_text() for p in logs.values()) and rec_log.exists()
                    and all(f"recorded the end of quick/@v1/{cam}/stabilized" in rec_log.read_text() for cam in SPECS)):
                break  # every render finished and the recording holds each stream's end
        else:
            raise AssertionError({p.name: p.read_text()[-600:] for p in (tmp_path / "logs").glob("*.log")})
    finally:
        codes = sup.stop()
    assert all(c == 0 for c in codes.values()), codes
    for cam, spec in SPECS.items():
        ref = offline_images(spec)
        got = {int(p.stem): cv2.imread(str(p)) for p in (tmp_path / cam).glob("*.png")}
        assert sorted(got) == sorted(ref) == list(range(90))
        assert [s for s in ref if not np.array_equal(got[s], ref[s])] == [], cam
        text = logs[cam].read_text()
        assert "0 flagged, 0 orphans, 0 missing" in text, text[-400:]
        # the other stream's frames are not this one's: its capture starts a new stream at 0
        assert "under way" not in (tmp_path / "logs" / f"capture-{cam}.log").read_text()
    # both streams recorded whole, side by side. Each capture is paced by its pipeline (--pace fast):
    # at 30 fps live, a second suite beside this one starved the stages and a frame dropped in flow's
    # queue changed cam1's path (frames 30-89). The rate two streams keep live is a benchmark number:
    # `quick-stream bench pipeline --streams 2`.
    for cam in SPECS:  # read_messages: the wire messages as received (their JPEGs were stored apart)
        msgs = [decode(d) for _, _, d in read_messages(tmp_path / "rec.mcap", topics=[f"quick/@v1/{cam}/frame"])]
        stabilized = list(read_messages(tmp_path / "rec.mcap", topics=[f"quick/@v1/{cam}/stabilized"]))
        assert len([m for m in msgs if m.type == "frame"]) == 90 and len(stabilized) == 91  # 90 frames (+ end)

"""``quick-stream rerun``: each stage re-run from a recording reproduces what was logged.

The recording is made without Zenoh: the stages run in-process and exactly what
each service would publish is logged (frames raw/zstd, flows, motions and
release-numbered corrections, raw stabilized frames, ``end`` markers). The flow
stage skips frame 33 as if its inbox had dropped it, so the flow 32 -> 34 must be
recomputed from exactly the frames it names and frame 33 is rendered as an orphan.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import pytest

from quick_stream.cli import main
from quick_stream.stream import keys
from quick_stream.io.stabilizer_flags import add_stabilizer_args, stabilizer_params
from quick_stream.io.recording import Recorder, read_messages
from quick_stream.quality.rerun import RerunError, rerun_stage
from quick_stream.io.sources import open_source
from quick_stream.core.render_stage import RenderStage
from quick_stream.core.sceneflow import lift_pairs
from quick_stream.core.flow_stage import FlowStage
from quick_stream.core.stages import MotionStage
from quick_stream.stream.wire import (EndOfStream, StabilizedImage, decode, encode_correction, encode_end, encode_flow,
                                      encode_frame, encode_motion, encode_stabilized)

SPEC = "synthetic:frames=70,width=320,height=240"
STREAM = "cam0"
SKIPPED = 33  # dropped by the flow "service"


def topic(stage: str) -> str:
    return keys.key(STREAM, stage)


def default_params():
    p = argparse.ArgumentParser()
    add_stabilizer_args(p)
    return stabilizer_params(p.parse_args([]))


class Log:
    """A Recorder with increasing log times (the order the services would publish in)."""

    def __init__(self, path: Path) -> None:
        self.rec, self.t = Recorder(path), 1_000

    def put(self, stage: str, data: bytes) -> None:
        self.t += 1
        self.rec.write(topic(stage), data, log_time_ns=self.t)


def make_recording(path: Path) -> dict[str, int]:
    """Run the stages as the services do, logging every message they would publish."""
    cv2.setNumThreads(1)
    params = default_params()
    flow, motion = FlowStage(params.flow), MotionStage(params.motion, params.planner, params.warp)
    render = RenderStage(params.warp, params.framing)
    log, release, counts = Log(path), 0, {"stabilized": 0, "orphans": 0}

    def publish_batches(batches, closed_by=None) -> None:
        nonlocal release
        for b in batches:
            msgs = [encode_correction(c, STREAM, tag=(release, i, len(b), closed_by)) for i, c in enumerate(b)]
            release += 1
            for m in msgs:
                log.put("correction", m)
            for sf in render.iter_release([decode(m).obj for m in msgs]):
                log.put("stabilized", encode_stabilized(StabilizedImage(sf.seq, sf.timestamp_ns, sf.image, sf.zoom,
                                                                        sf.flags), STREAM, color="raw",
                                                        src_pub_ns=123, ready_pub_ns=456))
                counts["stabilized"] += 1

    last = -1
    for f in open_source(SPEC):
        data = encode_frame(f, STREAM, color="raw", depth="zstd", pub_ns=f.seq)
        log.put("frame", data)
        frame = decode(data).obj
        render.add_frame(frame.seq, frame)
        last = frame.seq
        if frame.seq == SKIPPED:
            continue
        for result in flow.push(frame):
            fdata = encode_flow(result, STREAM)
            log.put("flow", fdata)
            motions, batches = motion.push(decode(fdata).obj)
            for m in motions:
                log.put("motion", encode_motion(m, STREAM))
            publish_batches(batches, result.seq_next)
    end = encode_end(EndOfStream(last, "source exhausted"), STREAM)
    log.put("frame", end)
    log.put("flow", end)
    publish_batches(motion.finish())
    log.put("correction", end)
    for sf in render.flush():
        log.put("stabilized", encode_stabilized(StabilizedImage(sf.seq, sf.timestamp_ns, sf.image, sf.zoom, sf.flags),
                                                STREAM, color="raw"))
        counts["stabilized"] += 1
    log.put("stabilized", end)
    log.rec.close()
    counts["orphans"] = render.orphans
    return counts


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> tuple[Path, dict[str, int]]:
    path = tmp_path_factory.mktemp("rerun") / "recording.mcap"
    return path, make_recording(path)


def test_every_stage_reproduces_its_logged_outputs(recording):
    path, counts = recording
    assert counts == {"stabilized": 70, "orphans": 1}  # frame 33 rendered uncorrected
    logged = {t: 0 for t in ("flow", "motion", "correction")}
    for t, _, data in read_messages(path):
        if decode(data).type != "end" and keys.parse(t)[1] in logged:
            logged[keys.parse(t)[1]] += 1
    assert logged["flow"] == 68  # 69 frames through flow: 68 pairs, one of them 32 -> 34
    for stage in ("flow", "motion", "render"):
        r = rerun_stage(path, stage, None, default_params())
        assert r.ok, (stage, [str(m) for m in r.mismatches[:5]])
        assert r.stream == STREAM and r.logged == r.identical > 0
    r = rerun_stage(path, "motion", STREAM, default_params())
    assert {t.topic: t.logged for t in r.outputs} == {topic("motion"): logged["motion"],
                                                      topic("correction"): logged["correction"] + 1}  # + end
    r = rerun_stage(path, "render", STREAM, default_params())
    assert r.outputs[0].logged == 70 and any("1 orphans" in n for n in r.notes)


def test_a_tampered_flow_is_reported_and_the_cli_fails(recording, tmp_path, capsys):
    path, _ = recording
    bad = tmp_path / "tampered.mcap"
    target = None
    with Recorder(bad) as rec:
        for t, log_time, data in read_messages(path):
            msg = decode(data)
            if msg.type == "flow" and msg.seq == 20:
                fl = msg.obj  # one point's flow off by one fixed-point step (2^-10 px), lifted again
                depth_next = fl.points[:, 2] + fl.displacements[:, 2]
                fl.pixels_next[0, 0] += 2.0 ** -10
                fl.points, fl.displacements = lift_pairs(fl.pixels, fl.points[:, 2], fl.pixels_next, depth_next,
                                                         fl.intrinsics, fl.intrinsics_next)
                data, target = encode_flow(fl, STREAM), msg.seq
                assert decode(data).version == 2  # still the compact layout
            rec.write(t, data, log_time_ns=log_time)
    assert target == 20
    r = rerun_stage(bad, "flow", None, default_params())
    assert not r.ok and r.identical == r.logged - 1
    assert [(m.topic, m.seq, m.fields) for m in r.mismatches] == [(topic("flow"), 20, ("offset.data",))]
    assert main(["rerun", "flow", str(bad)]) == 1
    out = capsys.readouterr().out
    assert "seq 20: offset.data" in out and "DIFFERENT: 1 of 68" in out


def test_usage_errors(recording, tmp_path, capsys):
    path, _ = recording
    flows_only = tmp_path / "flows.mcap"
    with Recorder(flows_only) as rec:
        for t, log_time, data in read_messages(path, topics=[topic("flow")]):
            rec.write(t, data, log_time_ns=log_time)
    assert main(["rerun", "render", str(flows_only)]) == 2
    err = capsys.readouterr().err
    assert str(flows_only) in err and topic("frame") in err
    with pytest.raises(RerunError, match="no 'motion' messages"):  # inputs but no outputs to compare
        rerun_stage(flows_only, "motion")
    assert main(["rerun", "flow", str(tmp_path / "nope.mcap")]) == 2
    assert "no such file" in capsys.readouterr().err
    two = tmp_path / "two.mcap"
    with Recorder(two) as rec:
        rec.write(keys.key("a", "frame"), b"x")
        rec.write(keys.key("b", "frame"), b"x")
    assert main(["rerun", "flow", str(two)]) == 2
    assert "several streams (a, b)" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(["rerun", "capture", str(path)])
    assert e.value.code == 2
    assert main(["rerun", "motion", str(path), "--keyframe-interval", "1"]) == 2  # bad settings


def test_different_settings_do_not_reproduce(recording):
    path, _ = recording
    p = argparse.ArgumentParser()
    add_stabilizer_args(p)
    r = rerun_stage(path, "motion", None, stabilizer_params(p.parse_args(["--smoothness", "5"])))
    assert not r.ok and any(m.topic == topic("correction") for m in r.mismatches)
    assert all(m.seq is not None for m in r.mismatches)

"""The whole stabilizer in-process and `quick-stream stabilize`: determinism, fallbacks, outputs."""
import json

import cv2
import numpy as np
import pytest

from tests.helpers import stabilize

from quick_stream.cli import main
from quick_stream.core.frame import BadFrame
from quick_stream.core.render import FramingParams
from quick_stream.core.stabilizer import StabilizerParams
from quick_stream.io.sources.synthetic import SyntheticSource


def test_same_input_and_settings_give_bit_identical_frames():
    src = SyntheticSource(width=320, height=240, frames=40, seed=4)
    params = lambda: StabilizerParams(framing=FramingParams(mode="auto"))  # noqa: E731
    _, a = stabilize(src, params())
    _, b = stabilize(SyntheticSource(width=320, height=240, frames=40, seed=4), params())
    assert [f.seq for f in a] == list(range(40))
    for x, y in zip(a, b):
        assert np.array_equal(x.image, y.image)
        assert np.array_equal(x.correction.matrix, y.correction.matrix)
    assert any(not np.array_equal(f.image, g.color) for f, g in zip(a, src))  # it did change the frames


def test_the_number_of_opencv_threads_does_not_change_a_bit():
    """`stabilize` uses every core for OpenCV by default; the services run one thread each: both must
    give the same frames."""
    src = lambda: SyntheticSource(width=320, height=240, frames=40, seed=6)  # noqa: E731
    params = lambda: StabilizerParams(framing=FramingParams(mode="auto"))  # noqa: E731
    threads = cv2.getNumThreads()
    try:
        cv2.setNumThreads(1)
        _, a = stabilize(src(), params())
        cv2.setNumThreads(2)
        _, b = stabilize(src(), params())
    finally:
        cv2.setNumThreads(threads)
    assert len(a) == len(b) == 40
    for x, y in zip(a, b):
        assert np.array_equal(x.image, y.image), x.seq
        assert np.array_equal(x.correction.matrix, y.correction.matrix), x.seq


def test_auto_framing_keeps_borders_out():
    src = SyntheticSource(width=320, height=240, frames=45, seed=1)
    _, out = stabilize(src, StabilizerParams(framing=FramingParams(mode="auto")))
    for f in out:
        assert f.zoom >= 1.0
        # no black border: every edge pixel row/column carries scene texture
        edges = np.concatenate([f.image[0], f.image[-1], f.image[:, 0], f.image[:, -1]])
        assert np.mean(edges.max(axis=1) == 0) < 0.01, f.seq


@pytest.mark.parametrize("bridge,reach", [(3, 2), (3, 0), (0, 0)])
def test_textureless_frame_falls_back_visibly(bridge, reach):
    """A black frame leaves two flows with nothing in them (docs/method.md 2.4): reached over (the flow from
    the frame before it to the frame after it, split across it), or with no reach bridged at constant
    velocity, or with no bridge either, a restart at each; corrected and named, not flagged, not snapped back."""
    frames = list(SyntheticSource(width=320, height=240, frames=50, seed=2))
    frames[20] = frames[20].with_(color=np.zeros_like(frames[20].color))  # black frame: no flow
    frames[30] = BadFrame(30, frames[30].timestamp_ns, "synthetic", "unreadable")
    params = StabilizerParams()
    params.motion.bridge_frames = bridge
    params.flow.reach_over = reach
    st, out = stabilize(frames, params)
    seqs = [f.seq for f in out]
    assert seqs == [s for s in range(50) if s != 30]
    by_seq = {f.seq: f for f in out}
    kind = "fit" if reach else "bridge" if bridge else "restart"
    for s in (20, 21):
        c = by_seq[s].correction
        assert c.valid and c.motion == kind and (reach or "contrast" in c.reason), (c.motion, c.reason)
        assert not np.array_equal(c.matrix, np.eye(4))  # corrected, not left as it came
    assert st.bad_frames == [{"seq": 30, "origin": "synthetic", "error": "unreadable"}]
    assert not any(f.flags for f in out)
    assert {f.correction.motion for f in out if f.seq not in (20, 21)} <= {"fit", "start"}
    assert st.motion.bridge.bridges == (2 if bridge and not reach else 0)
    assert st.flow.reached_over == (1 if reach else 0)


def test_stabilize_command_writes_video_report_and_plot(tmp_path, capsys):
    out = tmp_path / "out"
    rc = main(["stabilize", "--source", "synthetic:width=320,height=240,frames=70", "--output",
               str(out / "s.mp4"), "--report", str(out / "r.json"), "--plot", str(out / "p.png"),
               "--png", str(out / "png"), "--quiet"])
    assert rc == 0
    text = capsys.readouterr().out
    assert "frames/s" in text and "shake" in text and "residual jitter" in text
    report = json.loads((out / "r.json").read_text())
    assert report["frames_out"] == 70 and len(report["frames"]) == 70
    assert {"flow", "motion", "path", "warp", "render"} <= set(report["timing_ms"])
    assert report["segments"] and all(s["converged"] for s in report["segments"])
    assert np.asarray(report["frames"][10]["correction"]).shape == (4, 4)
    m = report["metrics"]
    assert not m["failed"] and m["cropping"] > 0.8 and m["distortion"] > 0.9
    assert m["jitter_px"] < m["input_jitter_px"]
    s = report["shake"]
    assert s["stabilized"]["rot_deg"] < 0.3 * s["input"]["rot_deg"]
    cap = cv2.VideoCapture(str(out / "s.mp4"))
    n = 0
    while cap.read()[0]:
        n += 1
    assert n == 70
    assert cv2.imread(str(out / "p.png")) is not None
    assert len(list((out / "png").glob("*.png"))) == 70


def test_stabilize_rejects_bad_settings(capsys):
    assert main(["stabilize", "--source", "synthetic", "--keyframe-interval", "1", "--quiet"]) == 2
    assert "interval" in capsys.readouterr().err
    assert main(["stabilize", "--source", "synthetic", "--path-weights", "1,2", "--quiet"]) == 2
    assert "6 positive numbers" in capsys.readouterr().err


def test_path_weights_reach_the_solver(tmp_path, capsys):
    args = ["stabilize", "--source", "synthetic:width=160,height=120,frames=35", "--output", "", "--plot", "",
            "--no-metrics", "--quiet", "--path", "ep"]  # W weighs the EP path's targets (the smooth path's are exact)
    reports = []
    for w in ("1,1,1,1,1,1", "1,1,1,50,50,50"):
        rep = tmp_path / f"r{len(reports)}.json"
        assert main(args + ["--path-weights", w, "--report", str(rep)]) == 0
        reports.append(json.loads(rep.read_text()))
    a = np.array([f["correction"] for f in reports[0]["frames"]])
    b = np.array([f["correction"] for f in reports[1]["frames"]])
    assert np.abs(a - b).max() > 1e-8  # weights act at second order here; the report keeps 1e-9

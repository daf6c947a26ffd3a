"""A frame whose flow starves is reached over: the flow to the next frame starts from the frame before
it, and the motion is split across it (docs/method.md 2.4; quick_stream/core/flow_stage.py FlowStage,
quick_stream/core/motion/chain.py split_over)."""
from __future__ import annotations

import numpy as np
import pytest

from quick_stream.core.lie import get_group
from quick_stream.core.motion import MotionParams
from quick_stream.core.motion.chain import split_over
from quick_stream.core.sceneflow import SceneFlowParams
from quick_stream.core.flow_stage import FlowDriver, FlowStage
from quick_stream.core.stages import MotionStage
from quick_stream.io.sources.synthetic import SyntheticSource
from quick_stream.stream.wire import WireError, decode, encode_flow


@pytest.fixture(scope="module")
def frames():
    return list(SyntheticSource(width=160, height=120, frames=24, seed=3, shake=2.0))


def blank(f):
    """The frame with its colour one flat grey (no contrast: no flow into or out of it)."""
    return f.with_(color=np.full_like(f.color, 128))


def spans(flows):
    return [(f.seq, f.seq_next, f.over) for f in flows]


def run_flow(frames, params=None):
    st, out = FlowStage(params), []
    for f in frames:
        out += st.push(f)
    return st, out + st.finish()


def test_a_blank_frame_is_reached_over_and_without_the_reach_both_its_flows_starve(frames):
    clip = frames[:10]
    clip[4] = blank(clip[4])
    st, flows = run_flow(clip)
    assert spans(flows) == [(0, 1, ()), (1, 2, ()), (2, 3, ()), (3, 5, (4,)),
                            *[(s, s + 1, ()) for s in range(5, 9)]]
    assert all(len(f) >= 50 and not f.problem for f in flows) and st.reached_over == 1
    _, flows = run_flow(clip, SceneFlowParams(reach_over=0))
    assert spans(flows) == [(s, s + 1, ()) for s in range(9)]
    assert [f.seq for f in flows if len(f) == 0 and "contrast" in f.problem] == [3, 4]


def test_the_reach_is_bounded_and_never_starts_from_a_starved_frame(frames):
    """Three blank frames in a row, two reached over at most: the flow across them is let go starved (the
    motion stage bridges or restarts), and the next one, out of a blank frame, is not reached from."""
    clip = frames[:10]
    for i in (4, 5, 6):
        clip[i] = blank(clip[i])
    st, flows = run_flow(clip)
    assert spans(flows) == [(0, 1, ()), (1, 2, ()), (2, 3, ()), (3, 6, (4, 5)), (6, 7, ()), (7, 8, ()), (8, 9, ())]
    assert [len(f) for f in flows[3:5]] == [0, 0] and st.reached_over == 2


def test_a_stream_ending_on_a_frame_being_reached_over_gives_its_held_flow_at_the_end(frames):
    clip = frames[:6]
    clip[5] = blank(clip[5])
    d = FlowDriver()
    flows = [f for fr in clip for f in d.push(fr)]
    assert spans(flows) == [(s, s + 1, ()) for s in range(4)]
    held = d.finish()
    assert spans(held) == [(4, 5, ())] and len(held[0]) == 0 and d.stats()["empty_flows"] == 1
    assert d.finish() == []


def test_split_over_composes_to_the_motion_and_shares_its_covariance():
    from quick_stream.core.motion import MotionEstimate

    g = get_group("se3")
    twist = np.array([0.01, -0.02, 0.005, 0.03, -0.01, 0.02])
    cov = np.diag(np.arange(1, 7) * 1e-6)
    m = MotionEstimate(10, 13, "se3", "exact", g.exp(twist), twist, True, "", covariance=cov, kind="rotation")
    parts = split_over(m, (11, 12))
    assert [(p.seq, p.seq_next, p.kind) for p in parts] == [(10, 11, "rotation"), (11, 12, "rotation"),
                                                           (12, 13, "rotation")]
    np.testing.assert_allclose(parts[0].matrix @ parts[1].matrix @ parts[2].matrix, m.matrix, atol=1e-12)
    np.testing.assert_allclose(sum(p.covariance for p in parts), cov, rtol=1e-12)
    assert all("reached over" in p.reason for p in parts)
    bad = split_over(MotionEstimate(10, 12, "se3", "exact", np.eye(4), np.zeros(6), False, "no flow"), (11,))
    assert [(p.seq, p.seq_next, p.valid) for p in bad] == [(10, 11, False), (11, 12, False)]
    assert split_over(m, ()) == [m]


def poses_from(motions):
    T = [np.eye(4)]
    for m in motions:
        T.append(T[-1] @ m.matrix)
    return T


def rotation_deg(R) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def path_of(clip, reach):
    """Every motion and correction of ``clip`` through the flow and motion stages."""
    _, flows = run_flow(clip, SceneFlowParams(reach_over=reach))
    motion = MotionStage(MotionParams(translation_prior_mm=0.2))
    motions, released = [], [motion.start(0)]
    for f in flows:
        m, r = motion.push(f)
        motions += m
        released += r
    return motions, released + motion.finish()


@pytest.mark.parametrize("reach", [2, 0])
def test_the_path_through_a_blank_frame_keeps_the_camera_s_orientation(frames, reach):
    """Every frame gets a motion; reached over, the orientation after the blank frame stays within a
    fiftieth of a degree of what the same estimator gives with the frame intact, where the
    constant-velocity bridge (no reach) is off by the shake's turn."""
    clip = frames[:16]
    intact, _ = path_of(clip, reach)
    clip[8] = blank(clip[8])
    motions, released = path_of(clip, reach)
    assert [(m.seq, m.seq_next) for m in motions] == [(s, s + 1) for s in range(15)]
    assert all(m.valid for m in motions)
    assert sorted(c.seq for r in released for c in r) == list(range(16))
    assert all(c.valid and c.motion in ("start", "fit", "bridge") for r in released for c in r)
    est, ref = poses_from(motions), poses_from(intact)
    off = [rotation_deg(ref[s][:3, :3].T @ est[s][:3, :3]) for s in range(16)]
    assert max(off[:8]) < 1e-5  # the same flows up to the blank frame (arccos rounding)
    if reach:
        assert {m.kind for m in motions} == {"fit"}
        assert all("reached over" in m.reason for m in motions[7:9])
        assert max(off[9:]) < 0.02
    else:
        assert [m.kind for m in motions[7:9]] == ["bridge", "bridge"]
        assert max(off[9:]) > 0.5


def test_a_flow_s_over_travels_on_the_wire_and_a_malformed_one_is_refused(frames):
    clip = frames[:7]
    clip[4] = blank(clip[4])
    _, flows = run_flow(clip)
    span = next(f for f in flows if f.over)
    back = decode(encode_flow(span, "cam")).obj
    assert (back.seq, back.seq_next, back.over) == (3, 5, (4,))
    np.testing.assert_array_equal(back.pixels_next, span.pixels_next)
    import dataclasses

    import msgpack

    assert "over" not in msgpack.unpackb(encode_flow(flows[0], "cam"), raw=False)  # left out when empty
    assert decode(encode_flow(flows[0], "cam")).obj.over == ()

    for over in ((5,), (3,), (4, 4), (6,)):
        with pytest.raises(WireError) as e:
            encode_flow(dataclasses.replace(span, over=over), "cam")
        assert e.value.field == "over"
    raw = msgpack.unpackb(encode_flow(span, "cam"), raw=False)
    raw["over"] = [4, 4]
    with pytest.raises(WireError) as e:
        decode(msgpack.packb(raw, use_bin_type=True))
    assert e.value.field == "over" and "strictly between 3 and 5" in str(e.value)


def test_the_stabilizer_renders_every_frame_of_a_stream_with_a_blank_frame_corrected(frames):
    from tests.helpers import stabilize

    clip = frames[:20]
    clip[9] = blank(clip[9])
    st, out = stabilize(clip)
    assert [sf.seq for sf in out] == list(range(20)) and st.flow.reached_over == 1
    assert not any(sf.flags for sf in out) and all(sf.correction.valid for sf in out)
    assert [sf.correction.motion for sf in out[9:11]] == ["fit", "fit"]

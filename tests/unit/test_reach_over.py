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


class CountedFlow:
    """A scene flow whose pair counts are set per (seq, seq_next) (default 500): the flow stage's schedule
    alone, without images."""

    def __init__(self, pairs: dict[tuple[int, int], int], params: SceneFlowParams | None = None,
                 loose: frozenset = frozenset()) -> None:
        self.params = params or SceneFlowParams()
        self.pairs, self.loose = pairs, loose
        self.calls: list[tuple[int, int]] = []

    def compute(self, f0, f1):
        from quick_stream.core.sceneflow import SceneFlowResult

        self.calls.append((f0.seq, f1.seq))
        n = self.pairs.get((f0.seq, f1.seq), 500)
        z3, z2 = np.zeros((n, 3)), np.zeros((n, 2))
        counts = {"kept": n, **({"loose": 1} if (f0.seq, f1.seq) in self.loose else {})}
        return SceneFlowResult(f0.seq, f1.seq, z3, z3, np.ones(n), z2, z2, f0.intrinsics, f1.intrinsics, counts)


def counted_run(frames, pairs, upto=None, params=None, loose=frozenset()):
    st = FlowStage()
    st.flow = CountedFlow(pairs, params, loose)
    out, st.said = [], []
    for fr in frames[:upto]:
        out.append([(f.seq, f.seq_next, f.over, len(f)) for f in st.push(fr)])
        st.said.append(st.notes)
    return st, out


def test_a_smeared_frame_after_a_weak_flow_is_reached_back_over(frames):
    """docs/method.md 2.4: the flow into frame 4 is weak (30 pairs) and the one out of it starves: frame 4 is
    the smeared one, so the flow from frame 3 to 5 is taken in place of both; the weak flow waits one frame."""
    st, out = counted_run(frames, {(3, 4): 30, (4, 5): 3, (3, 5): 400}, upto=8)
    assert out[4] == [] and out[5] == [(3, 5, (4,), 400)]
    assert [s for o in out for s in o] == [(0, 1, (), 500), (1, 2, (), 500), (2, 3, (), 500), (3, 5, (4,), 400),
                                           (5, 6, (), 500), (6, 7, (), 500)]
    assert st.reached_over == 1 and any("reached back over" in n for n in st.said[5])


def test_a_weak_flow_goes_on_when_its_frame_holds(frames):
    """Weak but followed by a good flow: both go out, in order, one frame late; a weak flow whose successor
    starves and whose frame the reach back does not beat goes out as it is, and the frame after it is
    reached over as before."""
    _, out = counted_run(frames, {(3, 4): 30}, upto=7)
    assert out[4] == [] and out[5] == [(3, 4, (), 30), (4, 5, (), 500)]
    st, out = counted_run(frames, {(3, 4): 30, (4, 5): 3, (3, 5): 20}, upto=8)
    assert out[5] == [(3, 4, (), 30)] and out[6] == [(4, 6, (5,), 500)]
    assert st.reached_over == 1 and (3, 5) in st.flow.calls


def test_a_stream_ending_on_a_weak_flow_gives_it_at_the_end(frames):
    st, out = counted_run(frames, {(4, 5): 30}, upto=6)
    assert out[5] == []
    assert [(f.seq, f.seq_next, len(f)) for f in st.finish()] == [(4, 5, 30)] and st.finish() == []


def test_the_reach_back_is_off_at_zero_and_bounded_by_the_reach(frames):
    _, out = counted_run(frames, {(3, 4): 30, (4, 5): 3, (3, 5): 400}, upto=7, params=SceneFlowParams(reach_back_pairs=0))
    assert out[4] == [(3, 4, (), 30)] and out[5] == [] and out[6] == [(4, 6, (5,), 500)]
    # a weak flow that already reaches over reach_over - 1 frames is not held: a reach back would pass the bound
    st, out = counted_run(frames, {(3, 4): 2, (3, 5): 2, (3, 6): 30, (6, 7): 2, (3, 7): 400}, upto=9)
    assert [s[:3] for o in out for s in o][3:5] == [(3, 6, (4, 5)), (6, 8, (7,))]


def test_a_flow_lifted_loose_is_held_as_a_weak_one_and_counted(frames):
    """Lifted loose (docs/method.md (1c)) its frame is smeared whatever its pair count: held, and reached back
    over when the flow out of it starves; the stage counts the loose flows it passes on."""
    st, out = counted_run(frames, {(4, 5): 3}, upto=7, loose=frozenset({(3, 4)}))
    assert out[4] == [] and out[5] == [(3, 5, (4,), 500)] and st.loose == 0 and st.reached_over == 1
    # loose both: the one over the frame is taken when it holds more pairs (and, loose, is held in turn)
    st, out = counted_run(frames, {(4, 5): 3, (3, 5): 900}, upto=7, loose=frozenset({(3, 4), (3, 5)}))
    assert out[4] == out[5] == [] and out[6] == [(3, 5, (4,), 900), (5, 6, (), 500)] and st.loose == 1
    st, out = counted_run(frames, {(4, 5): 3, (3, 5): 400}, upto=7, loose=frozenset({(3, 4), (3, 5)}))
    assert out[5] == [(3, 4, (), 500)] and st.loose == 1
    st, out = counted_run(frames, {}, upto=6, loose=frozenset({(2, 3)}))
    assert out[3] == [] and out[4] == [(2, 3, (), 500), (3, 4, (), 500)] and st.loose == 1

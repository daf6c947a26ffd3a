"""The pipeline stages the services drive: gaps, orphans, order and bounds (quick_stream/core/stages.py, render_stage.py)."""
from __future__ import annotations

import numpy as np
import pytest

from quick_stream.bench.variants import parse_settings
from quick_stream.core.path.planner import Correction
from quick_stream.core.render_stage import RenderStage
from quick_stream.core.flow_stage import FlowStage
from quick_stream.core.stages import MotionStage
from quick_stream.io.sources import open_source
from tests.helpers import flows_of, stabilize


@pytest.fixture(scope="module")
def frames():
    return list(open_source("synthetic:frames=40,width=160,height=120"))


def test_flow_stage_refuses_frames_out_of_order(frames):
    st = FlowStage()
    assert st.push(frames[3]) == []
    assert [f.seq_next for f in st.push(frames[4])] == [4]
    with pytest.raises(ValueError, match="not after"):
        st.push(frames[2])


def run_with_gap(frames, skip: range, restart: bool):
    """Flow/motion/render over the frames, the flow stage never seeing ``skip``: dropped from its
    queue (it then pairs across them) or, with ``restart``, lost with a killed flow service."""
    flow, motion, render = FlowStage(), MotionStage(), RenderStage()
    out = []
    for f in frames:
        render.add_frame(f.seq, f)
        if f.seq in skip:
            continue
        if restart and f.seq == skip.stop:
            flow = FlowStage()  # the restarted service starts over
        fls = flow.push(f)
        batches = [] if motion.started or not flow.began else [motion.start(f.seq)]
        for fl in fls:
            batches += motion.push(fl)[1]
        for b in batches:
            out += list(render.iter_release(b))
    for b in motion.finish():
        out += list(render.iter_release(b))
    out += render.flush()
    return motion, render, out


def test_a_restart_gap_restarts_the_path_and_every_frame_comes_out_in_order_flagged(frames):
    motion, render, out = run_with_gap(frames, range(12, 17), restart=True)
    assert [sf.seq for sf in out] == list(range(40))
    flagged = [sf.seq for sf in out if sf.flags]
    # the gap: frames no flow ever saw, so no correction reaches them
    assert flagged == list(range(12, 17))
    assert all("skipped upstream" in out[s].flags[0] for s in range(12, 17))
    # the restarted flow's first frame: the path restarts there (5 frames: beyond the bridge), corrected
    assert out[17].correction.motion == "restart" and "restarted" in out[17].correction.reason
    assert motion.gaps == 1 and render.orphans == 5 and render.missing == 0


def test_frames_dropped_before_flow_come_out_in_order_flagged(frames):
    motion, render, out = run_with_gap(frames, range(12, 16), restart=False)  # 4 missing: max_missing
    assert [sf.seq for sf in out] == list(range(40))
    assert [sf.seq for sf in out if sf.flags] == list(range(12, 16))  # the path spans them
    assert motion.gaps == 0 and render.orphans == 4


def test_more_frames_dropped_than_flow_bridges_restart_the_path(frames):
    motion, render, out = run_with_gap(frames, range(12, 17), restart=False)  # 5 missing
    assert [sf.seq for sf in out] == list(range(40))
    assert [sf.seq for sf in out if sf.flags] == list(range(12, 17))
    assert out[17].correction.motion == "restart"
    assert "5 frames missing between frame 11 and 17" in out[17].correction.reason
    assert motion.gaps == 0 and render.orphans == 5


@pytest.mark.parametrize("fps,breaks", [(120, 0), (30, 3)])
def test_frames_shed_at_the_capture_of_a_fast_camera_are_bridged_by_time(fps, breaks):
    """A 120 fps camera whose capture sends every 8th frame (the pipeline takes 15 frames/s): 7
    frames missing between two sent ones span 67 ms, which flow bridges; the same gaps at 30 fps
    (267 ms) break the path, which restarts at each (corrected, no frame flagged). Render only ever
    sees the frames sent."""
    sent = list(open_source(f"synthetic:frames=25,width=160,height=120,fps={fps}"))[::8]
    flow, motion, render = FlowStage(), MotionStage(), RenderStage()
    out, batches = [], [motion.start(sent[0].seq)]
    for f in sent:
        render.add_frame(f.seq, f)
        for fl in flow.push(f):
            batches += motion.push(fl)[1]
    batches += motion.finish()
    for b in batches:
        out += list(render.iter_release(b))
    out += render.flush()
    assert [sf.seq for sf in out] == [0, 8, 16, 24]
    assert flow.check.counts["missing_frames"] == 21 and flow.check.counts["breaks"] == breaks
    assert not any(sf.flags for sf in out) and render.orphans == 0
    assert sum(sf.correction.motion == "restart" for sf in out) == breaks


def test_motion_stage_refuses_staleflows_of(frames):
    flow, motion = FlowStage(), MotionStage()
    flow.push(frames[0])
    [f01] = flow.push(frames[1])
    motion.push(f01)
    with pytest.raises(ValueError, match="stale or duplicate"):
        motion.push(f01)


def test_render_stage_bounds_what_it_holds(frames):
    r = RenderStage(max_frames=5)
    for f in frames[:8]:
        r.add_frame(f.seq, f)
    assert r.hold.buffered == 5 and r.hold.dropped == 3
    out = list(r.iter_release([Correction(0, np.eye(4), 0, True)]))  # frame 0 was dropped: counted missing, the rest waits
    assert out == [] and r.missing == 1 and r.hold.buffered == 5


def test_render_stage_bounds_the_bytes_it_holds(frames):
    """Frames held as their messages (loaders, ``size`` bytes each) up to ``max_bytes``; the oldest
    beyond are dropped and counted."""
    r = RenderStage(max_bytes=3000)
    for f in frames[:8]:
        assert r.add_frame(f.seq, lambda f=f: f, size=1000)
    assert r.hold.buffered == 3 and r.hold.dropped == 5 and r.hold.held_bytes == 3000
    assert [sf.seq for sf in r.iter_release([Correction(5, np.eye(4), 0, True)])] == [5]
    assert r.hold.held_bytes == 2000


def test_frames_shed_by_flow_are_bridged_named_on_the_next_correction_and_not_counted_missing(frames):
    """Flow shed frames 1-2 and 5 (its admission) and never saw frame 4: the pair 0 -> 3 is bridged as
    any 2 missing frames would be, counted as shed, not missing; motion puts the shed frames on the
    correction of the frame each flow ends at, and no other correction names any."""
    from quick_stream.core.stages import MotionDriver

    flow, motion = FlowStage(), MotionDriver()
    flow.push(frames[0])
    named = {}
    for seq, shed in ((3, (1, 2)), (6, (5,)), (7, ())):
        [fl] = flow.push(frames[seq], shed=shed)
        assert fl.problem == ""
        for c, _ in motion.push(fl, shed)[1]:
            named[c.seq] = c.shed
    for c, _ in motion.finish():
        named[c.seq] = c.shed
    assert named == {0: (), 3: (1, 2), 6: (5,), 7: ()}
    assert flow.check.counts["missing_frames"] == 1 and flow.check.counts["seq_gaps"] == 1  # frame 4 alone


def test_the_render_stage_times_every_frame_once_per_step(frames):
    """One warp, framing and render sample per frame, so each mean is ms per frame (the border fill's
    zoom estimate counts in framing, the warp inputs made on a frame's arrival in warp)."""
    st, out = stabilize(frames, parse_settings([]).params)
    n = {k: len(v) for k, v in st.timer.samples.items()}
    assert n["warp"] == n["framing"] == n["render"] == len(out) == len(frames)


def test_render_stage_reports_a_frame_that_cannot_be_loaded(frames):
    r = RenderStage()

    def broken():
        raise ValueError("truncated JPEG")

    r.add_frame(0, broken)
    assert list(r.iter_release([Correction(0, np.eye(4), 0, True)])) == []
    assert r.hold.bad == [{"seq": 0, "error": "ValueError: truncated JPEG"}]


def test_release_groups_hand_over_releases_whose_sender_died():
    import numpy as np

    from quick_stream.core.path.planner import Correction
    from quick_stream.core.release import ReleaseGroups

    def c(seq):
        return Correction(seq, np.eye(4), 0, False)

    g = ReleaseGroups()
    g.add(c(0), (0, 0, 1))
    g.add(c(1), (1, 0, 3))
    g.add(c(2), (1, 1, 3))  # ... and the motion service dies before index 2
    assert [b[1] for b in g.ready][0][0].seq == 0 and len(g.ready) == 1
    g.add(c(9), (0, 0, 2))  # the restarted service numbers from 0 again
    assert g.abandoned == 1 and [[x.seq for x in b] for _, b, *_ in g.ready] == [[0], [1, 2]]
    g.add(c(10), (0, 1, 2))
    assert [[x.seq for x in b] for _, b, *_ in g.ready][-1] == [9, 10]
    g.add(c(20), (5, 0, 2))
    g.add(c(21), (5, 0, 2))  # an index already there: a new release under a reused number
    assert g.abandoned == 2


def test_render_refuses_one_far_future_frame_and_follows_a_confirmed_renumbering():
    from quick_stream.core.render_stage import RenderStage
    from quick_stream.io.sources.synthetic import SyntheticSource

    fr = next(iter(SyntheticSource(width=64, height=48, frames=1)))
    st = RenderStage()
    st.add_frame(0, fr)
    with pytest.raises(ValueError, match="frames ahead of frame 0"):
        st.add_frame(10**12, fr)
    st.add_frame(1, fr)  # the stream goes on
    for s in range(9000, 9004):
        with pytest.raises(ValueError, match="ahead"):
            st.add_frame(s, fr)
    st.add_frame(9004, fr)  # the fifth in a row: a new numbering
    assert st.hold.buffered == 3


def test_flow_refuses_one_far_future_frame_and_breaks_at_a_confirmed_renumbering():
    """One frame from the far future used to become the previous frame, so every later one was
    refused as out of order and the stream halted for good."""
    from quick_stream.core.continuity import FrameRefused
    from quick_stream.io.sources.synthetic import SyntheticSource

    frames = list(SyntheticSource(width=64, height=48, frames=12))
    st = FlowStage()
    st.push(frames[0])
    with pytest.raises(FrameRefused, match="frames ahead of frame 0"):
        st.push(frames[1].with_(seq=10**12))
    [f] = st.push(frames[1])  # the stream goes on from frame 0
    assert (f.seq, f.seq_next, f.problem) == (0, 1, "")
    renumbered = [frames[2 + i].with_(seq=7000 + i) for i in range(5)]
    for fr in renumbered[:4]:
        with pytest.raises(FrameRefused, match="ahead"):
            st.push(fr)
    [f] = st.push(renumbered[4])  # the fifth in a row: a discontinuity, the path restarts there
    assert (f.seq, f.seq_next) == (1, 7004) and "missing" in f.problem
    assert st.check.counts["seq_jumps"] == 5


def _corrected(motion: MotionStage, flows) -> tuple[list[int], list, int]:
    """Every correction's seq (in release order), every motion and the flows refused, the flows pushed
    one by one."""
    batches, motions, refused = [], [], 0
    for fl in flows:
        try:
            m, b = motion.push(fl)
        except ValueError:
            refused += 1
            continue
        motions += m
        batches += b
    batches += motion.finish()
    return [c.seq for b in batches for c in b], motions, refused


@pytest.mark.parametrize("forged", [(7, 2**64 - 1), (10**12, 10**12 + 1), (25, 10**9)])
def test_motion_stage_holds_a_far_future_flow_and_the_stream_goes_on(frames, forged):
    """A valid flow ``7 -> 18446744073709551615`` forged among real ones (the live fuzz, issue 30) became the
    path's newest frame: every later flow was refused as stale (90 frames lost, 175 uncorrected)."""
    import dataclasses

    flows = flows_of(frames)
    fake = dataclasses.replace(flows[3], seq=forged[0], seq_next=forged[1])
    motion = MotionStage()
    seqs, motions, refused = _corrected(motion, flows[:10] + [fake] + flows[10:])
    assert seqs == list(range(len(frames)))  # every frame corrected once, in order: nothing lost
    assert all(m.valid for m in motions) and motion.gaps == 0
    assert refused + motion.ahead.dropped == 1  # refused as it came (it overlaps), or held and then dropped
    assert motion.reached == len(frames) - 1


def test_motion_stage_takes_a_confirmed_jump_whole(frames):
    """A stream that really jumps ahead (the flow stage's break after five frames in a row): the held flows
    are all taken once the run confirms it, none lost."""
    jumped = frames[:12] + [f.with_(seq=9000 + f.seq) for f in frames[12:]]
    flows = flows_of(jumped)
    motion = MotionStage()
    seqs, _, refused = _corrected(motion, flows)
    assert refused == 0
    taken = [f.seq for f in jumped[:12]] + [9000 + s for s in range(16, len(frames))]  # flow refused 4 of them
    assert seqs == taken and motion.ahead.dropped == 0
    assert flows[11].seq == 11 and flows[11].seq_next == 9016 and "missing" in flows[11].problem


@pytest.mark.parametrize("forged,why", [((3, 30), "stale or duplicate"), ((15, 14), "goes back")])
def test_motion_stage_refuses_a_flow_that_overlaps_or_goes_back(frames, forged, why):
    """A flow that begins before the newest frame reached (``415 -> 7`` was taken as a gap going back) or
    goes back without being a renumbering's break is refused; the stream goes on."""
    import dataclasses

    flows = flows_of(frames)
    motion = MotionStage()
    for fl in flows[:10]:
        motion.push(fl)
    with pytest.raises(ValueError, match=why):
        motion.push(dataclasses.replace(flows[3], seq=forged[0], seq_next=forged[1]))
    seqs, motions, _ = _corrected(motion, flows[10:])
    assert all(m.valid for m in motions) and motion.gaps == 0 and motion.reached == len(frames) - 1

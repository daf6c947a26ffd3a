"""The release and render policy the services, ``stabilize`` and ``rerun`` share (quick_stream/core/release.py,
the drivers of quick_stream/core/stages.py): when a release renders, the end of a stream, the latency
stamps, taking over, and the counters carried from one stream to the next. Time is a test clock."""
from __future__ import annotations

import numpy as np
import pytest

from quick_stream.core.path.planner import Correction
from quick_stream.core.release import RenderDriver
from quick_stream.core.release_tags import ReleaseNumbering
from quick_stream.core.flow_stage import FlowStage
from quick_stream.core.stages import MotionDriver
from quick_stream.io.sources import open_source
from quick_stream.stream.wire import EndOfStream


@pytest.fixture(scope="module")
def frames():
    return list(open_source("synthetic:frames=40,width=96,height=72"))


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def corrections(*seqs: int) -> list[Correction]:
    return [Correction(s, np.eye(4), 0, s == seqs[0]) for s in seqs]


def test_release_numbering_tags_each_batch_as_one_release_for_the_services_life():
    n = ReleaseNumbering()
    tags = [t for _, t in n.number([corrections(0), corrections(1, 2, 3)])] + [t for _, t in n.number([corrections(4)])]
    assert [t[:3] for t in tags] == [(0, 0, 1), (1, 0, 3), (1, 1, 3), (1, 2, 3), (2, 0, 1)] and n.sent == 5
    assert [t.closed_by for _, t in n.number([corrections(5)], closed_by=9)] == [9]


def test_a_release_renders_when_its_frames_are_in_a_newer_one_came_or_frame_wait_passed(frames):
    clock = Clock()
    d = RenderDriver(max_frames=50, frame_wait=1.0, clock=clock)
    for f in frames[:3]:
        d.add_frame(f.seq, f, pub_ns=1000 + f.seq)
    for c, tag in ReleaseNumbering().number([corrections(0, 1, 2), corrections(3, 4)]):
        d.add_correction(c, tag)
    first = list(d.due())  # frames 0-2 are in: the first release renders, the second waits for 3 and 4
    assert [r.id for r in first] == [0] and [x.frame.seq for x in d.render(first[0])] == [0, 1, 2]
    d.add_frame(3, frames[3], pub_ns=1003)
    assert list(d.due()) == []  # 4 may still come
    clock.t += 1.5  # ... and does not within --frame-wait: rendered without it, counted missing
    (late,) = list(d.due())
    out = list(d.render(late))
    assert [x.frame.seq for x in out] == [3] and d.stats()["missing"] == 1
    assert (out[0].src_pub_ns, out[0].ready_pub_ns) == (1003, 1003)  # frame 4 (the release's last) never came


def test_latency_stamps_name_the_frame_and_the_one_that_closed_its_release(frames):
    d = RenderDriver()
    for f in frames[:3]:
        d.add_frame(f.seq, f, pub_ns=5000 + f.seq)
    for c, tag in ReleaseNumbering().number([corrections(0, 1, 2)]):
        d.add_correction(c, tag)
    (rel,) = list(d.due())
    assert [(r.src_pub_ns, r.ready_pub_ns) for r in d.render(rel)] == [(5000, 5002), (5001, 5002), (5002, 5002)]


def test_ready_is_when_the_frame_that_closed_the_release_was_published(frames):
    """A release waits for frames beyond its own (the planner's look-ahead): the wait for them is
    the segment's, not processing. A closing frame that is not here, or not after the release,
    leaves the release's newest frame as ready."""
    d = RenderDriver()
    for f in frames[:6]:
        d.add_frame(f.seq, f, pub_ns=5000 + f.seq)
    n = ReleaseNumbering()
    for c, tag in n.number([corrections(0, 1)], closed_by=4) + n.number([corrections(2, 3)], closed_by=40):
        d.add_correction(c, tag)
    first, second = list(d.due())
    assert first.closed_by == 4 and [r.ready_pub_ns for r in d.render(first)] == [5004, 5004]
    assert [r.ready_pub_ns for r in d.render(second)] == [5003, 5003]  # frame 40 never came


def test_the_end_waits_for_overtaken_frames_then_renders_everything_and_counters_carry_over(frames):
    clock = Clock()
    d = RenderDriver(frame_wait=1.0, clock=clock)
    for f in frames[:2]:
        d.add_frame(f.seq, f)
    tagged = ReleaseNumbering().number([corrections(0, 1, 2, 3)])
    for c, tag in tagged[:3]:  # the motion service died before the last correction of the release
        d.add_correction(c, tag)
    d.end("marker")
    assert not d.takes_corrections and d.idle_s < 0.05 and d.stats()["pending_releases"] == 1  # what arrived of it
    assert not d.end_due()  # frame 2 may still be on its way (overtaken by the end): frame-wait
    clock.t += 0.5
    assert not d.end_due() and d.end_due(stopping=True)
    d.add_frame(frames[2].seq, frames[2])
    d.add_frame(frames[3].seq, frames[3])  # no correction reached it: rendered uncorrected at the end
    groups = list(d.finish())
    assert [label for label, _ in groups] == ["release 0 (frames 0..2)", "end of stream"]
    rendered = [[r.frame.seq for r in frames_] for _, frames_ in groups]
    assert rendered == [[0, 1, 2], [3]] and d.end_marker == "marker" and d.stats()["orphans"] == 1
    d.restart()
    assert d.takes_corrections and d.stage.orphans == 0
    st = d.stats()
    assert st["orphans"] == 1 and st["ended"] == 1 and st["buffered"] == 0  # carried over to the next stream


def test_a_restarted_render_skips_what_its_predecessor_rendered(frames):
    d = RenderDriver(resume_after=4)
    assert not d.add_frame(3, frames[3]) and d.add_frame(5, frames[5])
    d.add_correction(corrections(4)[0], (0, 0, 1))  # released before the restart: not again
    assert d.releases.ready == [] and d.stats()["taken_over"] == 1


def test_the_motion_driver_takes_over_tags_releases_and_carries_counters_over_streams(frames):
    flow = FlowStage()
    flows = [x for f in frames[:20] for x in flow.push(f)]
    d = MotionDriver(resume_after=5)
    outs = [d.push(x) for x in flows]
    assert outs[:6] == [None] * 6 and d.stats()["taken_over"] == 6  # flows 0->1 .. 5->6: corrected before
    tags = [t for o in outs if o is not None for _, t in o[1]] + [t for _, t in d.finish()]
    assert tags and tags[0][:2] == (0, 0) and all(t[0] <= u[0] for t, u in zip(tags, tags[1:]))
    assert d.push(flows[-1]) is None and d.stats()["refused_flows"] == 1  # stale: refused, counted
    d.restart()
    assert d.resume_after is None and d.stats()["segments"] == 0 and d.stats()["corrections"] == len(tags)


@pytest.mark.parametrize("far", [10**12, 2**64 - 1, 400])
def test_a_far_future_correction_orphans_nothing_and_the_stream_goes_on(frames, far):
    """One valid correction from the far future (forged, or garbled on its way) was a release of its own:
    once ``frame_wait`` passed it rendered every frame held for the real corrections as an orphan,
    uncorrected, and their corrections then found no frame. It is held until a run confirms it, and
    dropped when the stream's own next correction comes."""
    clock = Clock()
    d = RenderDriver(max_frames=50, frame_wait=1.0, clock=clock)
    for f in frames[:10]:
        d.add_frame(f.seq, f)
    real = ReleaseNumbering().number([corrections(0, 1, 2), corrections(3, 4, 5), corrections(6, 7, 8, 9)])
    out = []
    for c, tag in real[:3]:
        d.add_correction(c, tag)
    d.add_correction(Correction(far, np.eye(4), 2, False, True, ""), (5, 0, 1))
    clock.t += 1.5
    for c, tag in real[3:]:
        for rel in d.due():
            out += list(d.render(rel))
        d.add_correction(c, tag)
    for _, group in d.finish():
        out += list(group)
    assert [x.frame.seq for x in out] == list(range(10)) and not any(x.frame.flags for x in out)
    st = d.stats()
    assert st["orphans"] == st["missing"] == 0 and st["jump_corrections"] == 1


def test_a_correction_run_that_confirms_a_jump_is_taken_whole(frames):
    """Corrections of a stream that jumped ahead before its frames came: held, then all taken on the fifth."""
    d = RenderDriver(max_frames=50)
    d.add_frame(0, frames[0])
    for c, tag in ReleaseNumbering().number([corrections(0), corrections(*range(5000, 5005))]):
        d.add_correction(c, tag)
    assert [[c.seq for c in b] for _, b, *_ in d.releases.ready] == [[0], list(range(5000, 5005))]
    assert d.stats()["jump_corrections"] == 0
def loaders(frames, loaded: list[int]):
    """Each frame as render holds it: a loader (its message decoded when asked), recording what was."""
    def load(f):
        loaded.append(f.seq)
        return f
    return [(f.seq, lambda f=f: load(f)) for f in frames]


def test_frames_the_flow_stage_shed_are_let_go_undecoded_and_a_refused_one_is_still_an_orphan(frames):
    """Flow shed frames 2 and 3 (named on frame 4's correction) and refused frame 6 (bad input, named
    nowhere): render never decodes the shed ones, renders no orphan of them and counts them as shed
    upstream, not as its own drops; frame 6 still comes out uncorrected and flagged, as before."""
    loaded: list[int] = []
    d = RenderDriver()
    for seq, load in loaders(frames[:9], loaded):
        d.add_frame(seq, load, size=1000)
    cs = corrections(0, 1, 4, 5, 7, 8)
    cs[2].shed = (2, 3)
    for c, tag in ReleaseNumbering().number([cs]):
        d.add_correction(c, tag)
    assert d.stage.hold.buffered == 9 and d.stage.hold.held_bytes == 9000
    (rel,) = list(d.due())
    out = [r.frame for r in d.render(rel)]
    assert [sf.seq for sf in out] == [0, 1, 4, 5, 6, 7, 8] and [sf.seq for sf in out if sf.flags] == [6]
    assert sorted(loaded) == [0, 1, 4, 5, 6, 7, 8] and d.stage.hold.buffered == d.stage.hold.held_bytes == 0
    st = d.stats()
    assert (st["shed_upstream"], st["orphans"], st["missing"], st["dropped"], st["flagged"]) == (2, 1, 0, 0, 1)


def test_a_frame_named_shed_that_comes_after_its_release_and_those_shed_after_the_last_flow_are_let_go(frames):
    """Frame 4's correction names frame 3 as shed; the release renders (frame_wait passed) before frame 3
    reaches render: it is let go when it comes. Frames 6 and 7 were shed after the last flow: the end
    names them, and the end of the stream renders neither (frame 5, which nothing names, still comes
    out flagged)."""
    clock = Clock()
    d = RenderDriver(frame_wait=1.0, clock=clock)
    for f in frames[:3]:
        d.add_frame(f.seq, f)
    cs = corrections(0, 1, 2, 4)
    cs[3].shed = (3,)
    for c, tag in ReleaseNumbering().number([cs]):
        d.add_correction(c, tag)
    clock.t += 1.5
    (rel,) = list(d.due())
    assert [r.frame.seq for r in d.render(rel)] == [0, 1, 2]  # frame 4 missing: it never came in time
    assert not d.add_frame(3, frames[3]) and d.stage.hold.buffered == 0
    for f in frames[4:8]:
        assert d.add_frame(f.seq, f)
    d.end(EndOfStream(7, "done", (6, 7)))
    out = [r.frame for _, group in d.finish() for r in group]
    assert [sf.seq for sf in out] == [4, 5] and all(sf.flags for sf in out)  # too late for its correction
    st = d.stats()
    assert (st["shed_upstream"], st["orphans"], st["missing"]) == (3, 2, 1)

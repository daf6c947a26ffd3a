"""A stream whose numbering restarts lower (a camera or capture restarted without the stream's
cursor) is followed once a run of frames confirms it, by every stage that refuses out-of-order
messages: flow, motion, render and the arrival ledger (docs/reliability.md, "Renumbered stream").

Before this, every later frame was refused as out of order and the stream halted for good. The
rule (quick_stream/core/continuity.py, ``JumpGuard.renumbered``): ``resync`` (15) frames in a row at or
behind the newest accepted one, each following the previous by 1..step, none published before it.
"""
from __future__ import annotations

import numpy as np
import pytest

from quick_stream.core.continuity import ContinuityParams, FrameRefused, JumpGuard, RENUMBERED
from quick_stream.core.path.planner import Correction
from quick_stream.core.release import ReleaseGroups
from quick_stream.core.render_stage import RenderStage, STALE
from quick_stream.core.stabilizer import Stabilizer
from quick_stream.core.flow_stage import FlowStage
from quick_stream.core.stages import MotionStage
from quick_stream.io.sources import open_source
from quick_stream.io.sources.synthetic import SyntheticSource
from quick_stream.stream.arrivals import ArrivalLedger
from quick_stream.stream.wire import encode_frame
from tests.helpers import flows_of

RESYNC = ContinuityParams().resync
OLD, NEW = 40, 30  # frames 0..39, then the source renumbered 0..29
FIRST = RESYNC - 1  # the new numbering's first frame taken: 14 (0..13 refused, 14 confirms)


def renumbered(frames: list) -> list:
    """``frames[:OLD]`` as they are, then the next ``NEW`` numbered from 0 again (capture time goes on)."""
    return frames[:OLD] + [f.with_(seq=i) for i, f in enumerate(frames[OLD:OLD + NEW])]


@pytest.fixture(scope="module")
def small():
    return list(SyntheticSource(width=64, height=48, frames=OLD + NEW))


@pytest.fixture(scope="module")
def frames():
    return list(open_source(f"synthetic:frames={OLD + NEW},width=160,height=120"))


def test_the_rule_takes_a_run_going_back_and_nothing_else():
    g = JumpGuard(resync=RESYNC)
    assert [g.renumbered(s) for s in range(RESYNC)] == [False] * (RESYNC - 1) + [True]
    assert g.run == list(range(RESYNC))
    g = JumpGuard(resync=RESYNC)
    for s in range(60):  # a second publisher's frames alternating with the accepted stream's
        assert g.admit(100 + s, 101 + s) and not g.renumbered(s)
    assert not any(g.renumbered(s, fresh=False) for s in range(60))  # a history replay
    assert not any(g.renumbered(s) for s in range(0, 600, 40))  # not following each other
    assert not g.renumbered(7)  # one stray old seq


def test_flow_breaks_at_a_confirmed_renumbering_and_goes_on(small):
    st = FlowStage()
    flows = []
    for f in renumbered(small):
        try:
            flows.append(st.push(f))
        except FrameRefused as e:
            assert f.seq < FIRST and "out of order" in str(e)
    assert flows[0] == []  # the first frame
    flows = [None] + [f for fs in flows[1:] for f in fs]
    brk = flows[OLD]
    assert (brk.seq, brk.seq_next, len(brk)) == (OLD - 1, FIRST, 0) and RENUMBERED in brk.problem
    assert [(f.seq, f.seq_next) for f in flows[OLD + 1:]] == [(s, s + 1) for s in range(FIRST, NEW - 1)]
    assert not any(RENUMBERED in f.problem for f in flows[1:OLD] + flows[OLD + 1:])
    c = st.check.counts
    assert (c["renumberings"], c["breaks"], c["out_of_order_frames"]) == (1, 1, FIRST)


def test_flow_never_takes_an_interleaved_publisher_a_replay_or_a_stray_frame(small):
    st = FlowStage()
    pairs = []
    for i, f in enumerate(small[:OLD]):
        pairs += st.push(f, pub_ns=1000 + 2 * i)
        if i >= 5:  # from frame 5 on a second publisher numbered from 0 alternates with it
            with pytest.raises(FrameRefused, match="out of order|duplicate"):
                st.push(small[OLD + i % NEW].with_(seq=i - 5), pub_ns=1001 + 2 * i)
    for f in small[10:OLD]:  # the capture's history answering a restarted service, after live frames
        with pytest.raises(FrameRefused):
            st.push(f, pub_ns=1000 + 2 * f.seq)
    with pytest.raises(FrameRefused):
        st.push(small[3], pub_ns=10**6)  # one stray old seq
    nxt = st.push(small[OLD].with_(seq=OLD), pub_ns=10**6 + 1)
    assert [(p.seq, p.seq_next) for p in pairs + nxt] == [(s, s + 1) for s in range(OLD)]
    assert st.check.counts["renumberings"] == 0 and st.check.counts["breaks"] == 0


def test_motion_restarts_the_path_at_the_renumbering_and_still_refuses_stale_flows(frames):
    flows = flows_of(renumbered(frames))
    m = MotionStage()
    batches = []
    for fl in flows:
        batches += m.push(fl)[1]
    batches += m.finish()
    assert m.renumberings == 1
    assert all(all(a.seq < b.seq for a, b in zip(b, b[1:])) for b in batches)  # no batch mixes numberings
    seqs = [c.seq for b in batches for c in b]
    assert seqs == list(range(OLD)) + list(range(FIRST, NEW))  # every frame corrected once, in order
    restart = next(b for i, b in enumerate(batches) if b[0].seq == FIRST and i and batches[i - 1][-1].seq == OLD - 1)
    # the path restarts at the break in a new pose chain, handed over without a jump (docs/method.md 4.4):
    # the restart frame is placed with the new numbering's first window, corrected and named
    assert restart[0].valid and restart[0].motion == "restart" and RENUMBERED in restart[0].reason
    assert restart[0].chain == batches[0][0].chain + 1
    brk = flows[OLD - 1]
    for stale in (flows[5], brk):  # an old flow, and the renumbering's break again
        with pytest.raises(ValueError, match="stale or duplicate"):
            m.push(stale)


def ident(seq: int) -> Correction:
    return Correction(seq, np.eye(4), 0, True)


def restart(seq: int, after: int) -> Correction:
    """A restart correction released alone at a renumbering's break (as the ``ep`` planner releases it)."""
    return Correction(seq, np.eye(4), 1, True, True, f"motion {after}->{seq} not known ({RENUMBERED}: ...): "
                      "path restarted; the last correction held", motion="restart")


def test_render_keeps_the_old_numbering_apart_and_renders_it_first(small):
    r = RenderStage()
    for f in small[:OLD]:
        r.add_frame(f.seq, f)
    out = list(r.iter_release([ident(s) for s in range(25)]))
    with pytest.raises(ValueError, match="not after"):
        r.add_frame(3, small[3])  # one stray old seq
    new = [f.with_(seq=i) for i, f in enumerate(small[OLD:])]
    for f in new[:FIRST]:
        with pytest.raises(ValueError, match="not after"):
            r.add_frame(f.seq, f)
    assert not r.hold.can_render([restart(FIRST, OLD - 1)])  # its frame has not come yet
    r.add_frame(FIRST, new[FIRST])  # the 15th in a row: a new numbering
    assert (r.hold.renumberings, r.hold.numbering, r.hold.buffered) == (1, 1, OLD - 25 + 1)
    for f in new[FIRST + 1:20]:
        r.add_frame(f.seq, f)
    assert r.hold.can_render([restart(FIRST, OLD - 1)]) and r.hold.can_render([ident(s) for s in range(25, 38)])
    out += list(r.iter_release([ident(s) for s in range(25, 38)]))  # the old numbering's last corrections
    out += list(r.iter_release([restart(FIRST, OLD - 1)]))  # the new numbering's first
    out += list(r.iter_release([ident(s) for s in range(FIRST + 1, 20)]))
    assert [(sf.seq, sf.numbering) for sf in out] == ([(s, 0) for s in range(OLD)]
                                                       + [(s, 1) for s in range(FIRST, 20)])
    flagged = {(sf.seq, sf.numbering): sf.flags[0] for sf in out if sf.flags}
    assert flagged.keys() == {(38, 0), (39, 0)}  # no correction reached 38, 39: orphans
    assert flagged[(38, 0)] == STALE and out[OLD].correction.motion == "restart"
    assert (r.orphans, r.missing, r.hold.buffered) == (2, 0, 0)
    for sf, f in zip(out[-5:], new[FIRST + 1:20]):  # the new frames, not the old ones of the same seq
        assert sf.timestamp_ns == f.timestamp_ns


def test_render_never_takes_an_interleaved_publisher_or_a_replay(small):
    r = RenderStage()
    for i, f in enumerate(small[:OLD]):
        r.add_frame(f.seq, f, pub_ns=1000 + 2 * i)
        if i >= 5:
            with pytest.raises(ValueError, match="not after"):
                r.add_frame(i - 5, small[OLD], pub_ns=1001 + 2 * i)
    for f in small[:OLD]:  # a replay published before the newest frame
        with pytest.raises(ValueError, match="not after"):
            r.add_frame(f.seq, f, pub_ns=1000 + 2 * f.seq)
    assert r.hold.renumberings == 0 and r.hold.buffered == OLD


def test_release_groups_put_the_new_numbering_after_the_old_one():
    g = ReleaseGroups()
    g.add(ident(29), (0, 0, 1))
    g.add(ident(30), (1, 0, 2))
    g.add(ident(31), (1, 1, 2))  # released, not yet rendered (its frames are late)
    g.add(restart(FIRST, 31), (2, 0, 1))
    g.add(ident(FIRST + 1), (3, 0, 1))
    assert [[c.seq for c in b] for _, b, *_ in g.ready] == [[29], [30, 31], [FIRST], [FIRST + 1]]
    assert g.numbering == 1


_F = next(iter(SyntheticSource(width=32, height=24, frames=1)))


def test_the_ledger_follows_a_renumbered_stage_and_not_an_interleaved_one():
    led = ArrivalLedger()
    key = "quick/@v1/cam0/flow"
    for s in [*range(OLD), *range(NEW)]:
        led.account(key, "flow", s)
    # the cursor a restarted service resumes from follows the new numbering; nothing counted late,
    # duplicated or missing
    assert led.newest() == {("cam0", "flow"): NEW - 1} and led.renumberings == 1
    assert (led.late, led.duplicates, led.unreceived()) == (0, 0, {})
    led.account(key, "flow", 3)  # one stray old seq: a duplicate
    assert led.duplicates == 1 and led.newest() == {("cam0", "flow"): NEW - 1}
    led.account(key, "flow", NEW + 2)  # 2 never arrived in the new numbering
    assert led.unreceived() == {"flow": 2}

    other = ArrivalLedger()
    for s in range(OLD):  # a second publisher numbered from 0 alternates with the stage's messages
        other.account(key, "flow", 100 + s)
        other.account(key, "flow", s)
    assert other.renumberings == 0 and other.newest() == {("cam0", "flow"): 100 + OLD - 1}

    replay = ArrivalLedger()  # frames replayed from a history cache after live ones: published earlier
    fkey = "quick/@v1/cam0/frame"
    for s in [*range(OLD), *range(20, OLD)]:
        replay.add(fkey, encode_frame(_F.with_(seq=s), "cam0", pub_ns=1000 + s))
    assert replay.renumberings == 0 and replay.newest() == {("cam0", "frame"): OLD - 1}
    for s in range(RESYNC):  # published after them: a camera restarted from 0
        replay.add(fkey, encode_frame(_F.with_(seq=s), "cam0", pub_ns=2000 + s))
    assert replay.renumberings == 1 and replay.newest() == {("cam0", "frame"): RESYNC - 1}


def test_the_stabilizer_stabilizes_the_renumbered_stream_after_the_run(frames):
    st = Stabilizer()
    out = []
    for f in renumbered(frames):
        out += st.push(f)
    out += st.finish()
    assert [(sf.seq, sf.numbering) for sf in out] == ([(s, 0) for s in range(OLD)]
                                                       + [(s, 1) for s in range(FIRST, NEW)])
    assert not any(sf.flags for sf in out)
    # the break: the path restarts there, without a jump (docs/method.md 4.4), then goes on stabilized
    assert out[OLD].correction.motion == "restart" and RENUMBERED in out[OLD].correction.reason
    assert all(sf.correction.valid for sf in out)
    assert len(st.bad_frames) == FIRST and all("out of order" in b["error"] for b in st.bad_frames)
    assert st.flow.check.counts["renumberings"] == st.motion.renumberings == st.render.hold.renumberings == 1
    assert st.render.orphans == st.render.missing == 0


def test_a_confirming_frame_refused_for_its_depth_leaves_the_next_one_to_confirm(small):
    st = FlowStage()
    for f in small[:OLD]:
        st.push(f)
    new = [f.with_(seq=i) for i, f in enumerate(small[OLD:])]
    for f in new[:FIRST]:
        with pytest.raises(FrameRefused, match="out of order"):
            st.push(f)
    with pytest.raises(FrameRefused, match="depth"):
        st.push(new[FIRST].with_(depth=np.zeros_like(new[FIRST].depth)))
    [brk] = st.push(new[FIRST + 1])  # continues the run: confirms at once, not 15 frames later
    assert (brk.seq, brk.seq_next) == (OLD - 1, FIRST + 1) and RENUMBERED in brk.problem


def test_a_service_taking_over_skips_the_replay_but_not_a_live_renumbered_stream():
    """The inbox of a restarted service skips what its predecessor handled (at or below its cursor),
    replayed from the capture's history; a frame published after those it queued is live: a stream
    renumbered below the cursor, which must reach the stage to be confirmed."""
    import threading

    from types import SimpleNamespace

    from quick_stream.stream.runtime import Inbox

    def sample(seq: int, pub_ns: int):
        data = encode_frame(_F.with_(seq=seq), "cam0", pub_ns=pub_ns)
        return SimpleNamespace(key_expr="quick/@v1/cam0/frame", payload=SimpleNamespace(to_bytes=lambda: data))

    box = Inbox(30, threading.Condition())
    box.skip_through = 93
    for seq in (94, 95):  # live frames first
        box._on_sample(sample(seq, 1000 + seq))
    for seq in range(60, 94):  # then the history: published before them, skipped
        box._on_sample(sample(seq, 1000 + seq))
    assert box.skipped == 34 and len(box) == 2
    for seq in range(RESYNC):  # a capture restarted from 0, published after them: queued
        box._on_sample(sample(seq, 2000 + seq))
    assert box.skipped == 34 and len(box) == 2 + RESYNC

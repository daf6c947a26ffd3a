"""The pipeline's one shedding decision, at the flow stage (quick_stream/core/admission.py), on a simulated clock."""
from __future__ import annotations

from collections import deque

import numpy as np
import pytest

from quick_stream.core.admission import FLOW_LIMITS, FlowAdmission, split_named
from quick_stream.core.shedding import DEFAULT_LIMITS, Shedder

TICK = 0.001  # s


def simulate(offered_fps: float, flow_fps: float, out_fps: float, seconds: float = 20.0, batch: int = 15,
             capture: bool = False):
    """Frames arrive at ``offered_fps`` (through a capture of ours that sheds with its own policy:
    ``capture``) at flow, which decides on each as it arrives and again as it takes it from its
    queue, and works ``1 / flow_fps`` on each it takes (the motion stage follows at once); the output
    renders the admitted frames in order at ``out_fps`` and reports its progress every ``batch``
    frames (a release). Returns (admission, admitted seqs, named seqs, sent seqs, in-flight samples,
    flow's longest queue)."""
    adm = FlowAdmission(backlog=30)
    upstream = Shedder(DEFAULT_LIMITS) if capture else None
    for service in ("flow", "motion", "render"):
        adm.set_up(service, True, 0.0)
        if upstream is not None:
            upstream.set_up(service, True, 0.0)
    adm.taken(-1)  # (what flow took before: nothing)
    queue: deque[int] = deque()
    outq: deque[tuple[int, float]] = deque()  # admitted frames and when flow is done with them
    admitted, named, sent, inflight = [], [], [], []
    flow_free = out_free = 0.0
    rendered: list[int] = []
    next_seq, longest = 0, 0

    def progressed(stage: str, seq: int, t: float) -> None:
        adm.progressed(stage, seq, t)
        if upstream is not None:
            upstream.progressed(stage, seq, t)

    for k in range(int(seconds / TICK)):
        t = k * TICK
        while next_seq / offered_fps <= t:
            if upstream is None or upstream.admit(next_seq, t):
                sent.append(next_seq)
                if adm.offer(next_seq, t):
                    queue.append(next_seq)
            next_seq += 1
        longest = max(longest, len(queue))
        while queue and flow_free <= t:
            seq = queue.popleft()
            if adm.take(seq, len(queue)):
                adm.taken(seq)
                admitted.append(seq)
                flow_free = t + 1.0 / flow_fps
                outq.append((seq, flow_free))
                progressed("motion", seq, flow_free)
            named += adm.take_shed()
        if outq and out_free <= t and outq[0][1] <= t:
            rendered.append(outq.popleft()[0])
            out_free = t + 1.0 / out_fps
            if len(rendered) % batch == 0:
                progressed("stabilized", rendered[-1], out_free)
        inflight.append(adm.shedder.in_flight("stabilized"))
    named += adm.take_shed()
    return adm, np.array(admitted), np.array(named), np.array(sent), np.array(inflight), longest


def steady(seqs: np.ndarray, fps: float, after_s: float) -> np.ndarray:
    return seqs[seqs > fps * after_s]


def test_a_flood_beyond_the_output_is_admitted_at_its_pace_evenly_and_every_frame_shed_is_named():
    """120 fps offered, flow could take 70, the output renders 30: flow admits about 30 a second,
    the gaps between them small enough for flow to bridge (at most 20 frames, 0.17 s at 120 fps),
    what the output holds stays bounded, and every frame is either admitted or named shed, once."""
    adm, admitted, named, _, inflight, _ = simulate(120, 70, 30)
    s = steady(admitted, 120, 8.0)
    assert 26 <= len(s) / 12.0 <= 34, len(s) / 12.0
    assert (np.diff(s) - 1).max() <= 20, np.bincount(np.diff(s) - 1)
    assert inflight[8000:].max() <= 1.5 * FLOW_LIMITS["stabilized"].hard
    assert len(set(admitted)) == len(admitted) and not set(admitted) & set(named)
    offered = set(range(int(admitted.max()) + 1))
    assert set(admitted) | set(named) >= offered and adm.shed == len(named) > 0


def test_flow_slower_than_the_flood_admits_at_its_own_pace_evenly_and_its_queue_stays_short():
    """The output keeps up (200 fps) but flow takes 40 of the 120 frames a second: flow's own queue is
    in flight to the motion stage, so it admits at its own pace as the frames arrive, one in three,
    each shed frame named; the queue stays under the backlog bound (nothing shed there) and the gaps
    are the one or two frames flow bridges."""
    adm, admitted, named, _, _, longest = simulate(120, 40, 200)
    assert adm.shed == len(named) > 0 and adm.shed_backlog == 0
    assert longest <= FLOW_LIMITS["motion"].hard + 1
    s = steady(admitted, 120, 5.0)
    assert 36 <= len(s) / 15.0 <= 42 and (np.diff(s) - 1).max() <= 4


def test_a_stalled_flow_sheds_its_backlog_by_name():
    """Frames taken from the queue with more than ``backlog`` waiting behind them, and frames the
    queue dropped for room, are shed and named like the others."""
    adm = FlowAdmission(backlog=2)
    assert [adm.offer(s, 0.0) for s in range(6)] == [True] * 6
    assert [adm.take(s, 5 - s) for s in range(6)] == [False, False, False, True, True, True]
    adm.dropped(6)
    assert adm.take_shed() == [0, 1, 2, 6] and adm.shed == adm.shed_backlog == 4


def test_behind_a_capture_of_ours_that_sheds_flow_sheds_nothing():
    """Our live capture sheds first, with bounds under flow's (DEFAULT_LIMITS): flow admits every frame
    it is sent, so a frame is shed once, at the capture."""
    adm, admitted, named, sent, _, _ = simulate(120, 70, 30, capture=True)
    assert adm.shed == 0 and len(named) == 0 and len(sent) < 0.5 * 120 * 20
    assert list(admitted) == list(sent)


def test_a_pipeline_that_keeps_up_sheds_nothing():
    adm, admitted, _, _, _, _ = simulate(30, 70, 45)
    assert adm.shed == 0 and len(admitted) == 600


def test_frames_out_of_order_or_far_ahead_are_never_shed_and_never_counted_in_flight():
    """A stale, duplicate or far-future seq (a stray message, a stream renumbered lower) goes to the
    flow stage, which refuses it (or confirms a new numbering with it); it takes no place in the
    in-flight account. Once flow takes one (confirmed), the account starts afresh there."""
    adm = FlowAdmission(backlog=30, limits={"stabilized": FLOW_LIMITS["stabilized"]})
    for service in ("flow", "motion", "render"):
        adm.set_up(service, True, 0.0)
    assert adm.offer(10, 0.0)
    adm.taken(10)
    assert adm.offer(10, 0.1) and adm.offer(3, 0.1) and adm.offer(10 + 301, 0.1)
    assert adm.shed == 0 and adm.shedder.in_flight("stabilized") == 1 and adm.newest == 10
    adm.taken(3)  # a renumbering the flow stage confirmed
    assert adm.newest == 3 and adm.shedder.in_flight("stabilized") == 0 and adm.offer(4, 0.2)
    adm.taken(4)
    adm.taken(4 + 400)  # a far jump it confirmed
    assert adm.newest == 404 and adm.offer(405, 0.3) and adm.shedder.in_flight("stabilized") == 1


def test_progress_of_an_earlier_stream_says_nothing_and_a_restart_keeps_the_services_up():
    adm = FlowAdmission(backlog=30)
    for service in ("motion", "render"):
        adm.set_up(service, True, 0.0)
    adm.offer(0, 0.0)
    adm.taken(0)
    adm.progressed("stabilized", 900, 0.1)  # the last stream's output, still draining
    assert adm.shedder.done["stabilized"] == -1
    adm.restart()
    assert adm.newest is None and adm.shedder.up == {"motion", "render"}


@pytest.mark.parametrize("backlog", [-1])
def test_a_negative_backlog_is_refused(backlog):
    with pytest.raises(ValueError, match="backlog"):
        FlowAdmission(backlog)


def _stalled_motion(adm: FlowAdmission) -> list[bool]:
    """Frames 0..59 offered while the motion stage, up, has reached frame 1 only (a slow start)."""
    for service in ("flow", "motion", "render"):
        adm.set_up(service, True, 0.0)
    first = [adm.offer(s, 0.0) for s in range(3)]
    adm.progressed("motion", 1, 0.1)
    return first + [adm.offer(s, 0.2 + s / 1000) for s in range(3, 60)]


def test_while_a_capture_of_ours_is_up_nothing_is_shed_on_arrival_and_the_queue_bound_still_holds():
    """Our capture paces or sheds itself: flow does not second-guess it (its bounds, raised by a slow
    start's backlog, need not agree with flow's); without it the same offers are shed. A frame taken
    behind too many waiting is shed either way."""
    alone = FlowAdmission(backlog=30)
    assert not all(_stalled_motion(alone)) and alone.shed > 0
    ours = FlowAdmission(backlog=30)
    ours.set_up("capture", True, 0.0)
    assert all(_stalled_motion(ours)) and ours.shed == 0
    assert ours.shedder.in_flight("motion") == 58  # still counted in flight: the account holds if it goes
    assert not ours.take(59, 31) and ours.take_shed() == [59]
    ours.set_up("capture", False, 1.0)  # gone (a foreign publisher goes on): the policy applies again
    assert not all(ours.offer(s, 1.0 + s / 1000) for s in range(60, 80))


def test_names_not_sent_at_a_lower_numbering_are_dropped_and_kept_across_a_jump():
    """Shed frames of the old numbering never name the new numbering's frames of the same seqs."""
    adm = FlowAdmission(backlog=0)
    adm.offer(35, 0.0)
    adm.taken(35)
    adm.dropped(36)
    adm.taken(14)  # the flow stage confirmed a lower numbering
    assert adm.take_shed() == []
    adm.dropped(15)
    adm.taken(500)  # a jump ahead it confirmed: the same numbering
    assert adm.take_shed() == [15]


def test_a_flow_names_the_frames_shed_before_its_end_and_a_renumbering_drops_the_old_ones():
    assert split_named([3, 7, 12], 5, 10) == ([3, 7], [12], 0)
    assert split_named([36, 37, 38, 39], 35, 14) == ([], [], 4)
    assert split_named([20, 36], 35, 14) == ([20], [], 1)
    assert split_named([], 0, 1) == ([], [], 0)

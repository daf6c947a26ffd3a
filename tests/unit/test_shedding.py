"""Load shedding at a live capture (quick_stream/core/shedding.py), on a simulated clock."""
from __future__ import annotations

from collections import deque

import numpy as np
import pytest

from quick_stream.core.shedding import DEFAULT_LIMITS, ShedLimits, Shedder

MOTION, OUTPUT = DEFAULT_LIMITS["motion"], DEFAULT_LIMITS["stabilized"]


def simulate(offered_fps: float, motion_fps: float, seconds: float = 20.0, batch: int = 1,
             stall: tuple[float, float] | None = None, limits=None, killed: bool = True):
    """A camera at ``offered_fps``; one stage takes the sent frames in order at ``motion_fps`` and
    reports its progress every ``batch`` frames (15: like the stabilized output's releases); during
    ``stall`` (start, end) it takes nothing: its flow service is down (``killed``, its liveliness
    token gone until the end of the stall) or just slow. Returns (shedder, sent seqs, in-flight samples)."""
    sh = Shedder(limits or {"motion": MOTION})
    stage = next(iter(sh.limits))
    for service in sh.limits[stage].needs:
        sh.set_up(service, True, 0.0)
    queue: deque[int] = deque()
    sent, inflight = [], []
    period, work = 1.0 / offered_fps, 1.0 / motion_fps
    busy_until, done_in_batch, t = 0.0, [], 0.0
    for seq in range(int(seconds * offered_fps)):
        t = seq * period
        if stall and killed:
            sh.set_up("flow", not stall[0] <= t < stall[1], t)
        # the stage works through its queue up to now
        while queue and busy_until <= t and not (stall and stall[0] <= busy_until < stall[1]):
            busy_until = max(busy_until, 0.0) + work
            done_in_batch.append(queue.popleft())
            if len(done_in_batch) >= batch:
                sh.progressed(stage, done_in_batch[-1], busy_until)
                done_in_batch.clear()
        if stall and stall[0] <= busy_until < stall[1]:
            busy_until = stall[1]
        if not queue:
            busy_until = max(busy_until, t)
        if sh.admit(seq, t):
            sent.append(seq)
            queue.append(seq)
        inflight.append(sh.in_flight(stage))
    return sh, np.array(sent), np.array(inflight)


def test_a_pipeline_that_keeps_up_sheds_nothing():
    sh, sent, inflight = simulate(30, 45)
    assert sh.shed == 0 and len(sent) == 600 and inflight.max() <= 2


def test_overload_sends_at_the_pipelines_pace_evenly_spaced():
    """120 fps offered, 30 taken: about one frame in four is sent, never two gaps in a row that a
    bridge cannot span (gaps of 3-4 frames, not bursts), and in flight stays bounded."""
    sh, sent, inflight = simulate(120, 30)
    steady = sent[sent > 120 * 5]  # after the rate estimate has settled
    rate = len(steady) / 15.0
    assert 27 <= rate <= 31, rate
    gaps = np.diff(steady) - 1
    assert gaps.max() <= 5, np.bincount(gaps)
    assert inflight[120 * 5:].mean() <= MOTION.hard and inflight.max() < 1.5 * MOTION.hard
    assert sh.shed == 2400 - len(sent)


def test_bursty_progress_still_gives_evenly_spaced_frames():
    """The stabilized output moves on a release (15 frames) at a time: the frames sent stay evenly
    spaced (the share of a 3 s window, not a gate that opens for a burst and closes)."""
    sh, sent, inflight = simulate(120, 30, batch=15, limits={"stabilized": OUTPUT})
    steady = sent[sent > 120 * 8]
    gaps = np.diff(steady) - 1
    assert 25 <= len(steady) / 12.0 <= 33
    assert gaps.max() <= 5, np.bincount(gaps)
    # held about its hard bound (drained below the pace there: a sawtooth of one release), never
    # near twice it
    assert inflight[120 * 8:].mean() <= OUTPUT.hard + 15 / 2 and inflight.max() < 1.5 * OUTPUT.hard


def test_a_restarting_service_sheds_nothing():
    """A stage whose service is restarting (its liveliness token gone) is not a slow stage: the
    frames go out (into the publishers' history, for its successor) instead of being shed, and
    the backlog drains once it is back."""
    sh, sent, inflight = simulate(30, 45, stall=(5.0, 7.0))
    assert sh.shed == 0 and inflight.max() > MOTION.hard


def test_a_hiccup_within_the_bounds_sheds_nothing_and_a_long_stall_of_a_live_service_does():
    """A service that is up but stalls for half a second (15 frames at 30 fps, under the hard
    bound) sheds nothing; one that stalls for 2 s while up is slow, and the capture sheds."""
    sh, _, _ = simulate(30, 45, stall=(5.0, 5.5), killed=False)
    assert sh.shed == 0
    sh, _, inflight = simulate(30, 45, stall=(5.0, 7.0), killed=False)
    assert sh.shed > 0 and inflight.max() < 2 * MOTION.hard


def test_a_bursty_stage_back_from_a_stop_drains_its_backlog_without_shedding():
    """The output (releases of 15) stops for 3.5 s while flow restarts: 105 frames in flight, more
    than its hard bound. Back, it moves in bursts; what it left drains, nothing is shed."""
    sh, sent, inflight = simulate(30, 45, batch=15, stall=(5.0, 8.5), limits={"stabilized": OUTPUT})
    assert inflight.max() > OUTPUT.hard
    assert sh.shed == 0 and len(sent) == 600


def test_limits_are_checked():
    with pytest.raises(ValueError):
        ShedLimits(soft=5, hard=4, needs=("flow",))
    assert not Shedder({"motion": ShedLimits(0, 0, ("flow",))}).enabled


@pytest.mark.parametrize("pace", ["fast", "realtime"])
def test_the_capture_takes_no_progress_beyond_the_newest_frame_sent(pace):
    """One motion (or stabilized image) forged with a far-future seq told the capture that the pipeline had
    reached it: flow control (fast pace) and shedding (realtime pace) were off for the rest of the stream."""
    import threading
    from types import SimpleNamespace

    from quick_stream.core.motion import MotionEstimate
    from quick_stream.stream.capture import OutputCredit
    from quick_stream.stream.wire import encode

    rt = SimpleNamespace(subscribe=lambda key, cb: None, watch_health=lambda cb: None, stop=threading.Event())
    oc = OutputCredit(rt, "cam0", 30 if pace == "fast" else 0, shed=DEFAULT_LIMITS if pace == "realtime" else None)
    for service in ("flow", "motion", "render"):
        oc._on_health(service, True)

    def progress(seq: int, seq_next: int) -> None:
        m = MotionEstimate(seq, seq_next, "se3", "exact", np.eye(4), np.zeros(6), True, "", 9, 0.9, 0.3)
        oc._on_output(SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: encode(m, "cam0"))))

    for seq in range(40):
        oc.sending(seq)
        if pace == "realtime":
            oc.admit(seq)
    progress(4, 5)
    progress(7, 2**64 - 1)  # forged
    assert oc.credit.done["motion"] == 5
    if pace == "fast":
        assert oc.credit.blocked(40)  # the motion stage is 35 frames behind: more than window // 3
    else:
        assert oc.shedder.done["motion"] == 5 and oc.shedder.in_flight("motion") == 34

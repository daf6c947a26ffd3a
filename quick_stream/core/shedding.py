"""Load shedding at the capture: a live source offered faster than the pipeline takes frames.

A live camera cannot wait for the pipeline. Without shedding, every frame is published and every
receiver (flow, render, the recorder) pays for it, while flow's and render's drop-oldest queues
throw most of them away later, unevenly: the gaps flow cannot bridge restart the path, and the
corrections render waits for point at frames it already dropped (docs/reliability.md, overload).
:class:`Shedder` decides per offered frame, before it is encoded, whether to send it:

* per downstream stage (the motion stage, which follows flow; the stabilized output) it counts the
  frames *in flight*: sent, and not yet reached by that stage (its newest seq, from its messages);
* while the services a stage needs are up (their liveliness tokens: a slow service is up, a killed
  one is not) and more than ``soft`` frames are in flight to it, the capture sends ``headroom``
  (1.25) times the share of the offered frames that the stage completed over the last ``rate_s``
  seconds, evenly spaced (an accumulator: one frame in k, not bursts), so the pipeline gets frames
  at its own pace and the gaps stay bridgeable, while a stage that keeps up on average sheds
  nothing for a hiccup;
* from ``hard`` frames in flight the share drops below the stage's pace (divided by
  ``headroom``), so the backlog drains, still evenly spaced; before its pace is known, and at
  twice ``hard``, nothing is sent;
* while a service the stage needs is down (restarting), and until the stage's first progress once
  all are up again, nothing is shed on its account: the frames wait in the publishers' history for
  its successor, as without shedding; from then on the backlog left may drain (not shed) but not
  grow (beyond ``hard - soft``, the stage's bursts), and the stage's pace is measured afresh.

Pure logic: the caller feeds it the stages' progress (:meth:`progressed`), the services'
liveliness (:meth:`set_up`) and the clock.
"""
from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass


@dataclass(frozen=True)
class ShedLimits:
    """Frames in flight to one stage: above ``soft`` the capture sends at the stage's pace, from
    ``hard`` a little under it (0: no limit); ``needs``: the services the stage's progress needs."""

    soft: int
    hard: int
    needs: tuple[str, ...]

    def __post_init__(self) -> None:
        if not 0 <= self.soft <= self.hard:
            raise ValueError(f"need 0 <= soft <= hard, got {self}")


# The services each shed-limited stage's progress needs: what its key is computed through (the
# pipeline's table, stream/topology.upstream, which core cannot import: a test ties the two).
UPSTREAM: dict[str, tuple[str, ...]] = {"motion": ("flow", "motion"), "stabilized": ("flow", "motion", "render")}

# Frames in flight (sent, not yet through the stage) before a live capture sheds: the motion stage
# follows flow a frame or two behind when keeping up, and flow's queue holds 30, which absorbs a
# hiccup (hard stays under it); the output lags one planning window (30 frames, up to 45 with the
# look-ahead) plus rendering, so its bounds sit above that (render holds 150).
DEFAULT_LIMITS = {"motion": ShedLimits(soft=8, hard=20, needs=UPSTREAM["motion"]),
                  "stabilized": ShedLimits(soft=60, hard=90, needs=UPSTREAM["stabilized"])}


class Shedder:
    """Which offered frames a live capture sends (module docstring)."""

    def __init__(self, limits: dict[str, ShedLimits], rate_s: float = 3.0, headroom: float = 1.25) -> None:
        """``headroom``: the share sent is that many times the stage's measured pace (a stage that
        keeps up on average, behind by a hiccup, sheds nothing; a slow one is held about its hard bound)."""
        self.limits = {k: v for k, v in limits.items() if v.hard > 0}
        self.rate_s, self.headroom = rate_s, headroom
        self.done = dict.fromkeys(limits, -1)  # each stage's newest seq
        self.up: set[str] = set()  # services whose liveliness token is up
        # when the stage last started (its services all up, then its first progress); inf: not started
        self._since = dict.fromkeys(limits, math.inf)
        self._pending: set[str] = set()  # stages whose services are up, waiting for their first progress
        self._backlog = dict.fromkeys(limits, 0)  # in flight when they came back, as it drains: not shed
        self._completed: dict[str, deque[tuple[float, int]]] = {k: deque() for k in limits}
        self._offered: list[float] = []  # when frames were offered, over the last rate_s
        self._sent: list[int] = []  # seqs sent that some stage has not reached (ascending)
        self._acc = 0.0
        self.shed = 0

    @property
    def enabled(self) -> bool:
        return bool(self.limits)

    def _running(self, stage: str) -> bool:
        return all(s in self.up for s in self.limits[stage].needs)

    def set_up(self, service: str, up: bool, now: float) -> None:
        """``service``'s liveliness token appeared (``up``) or went away. A stage whose services are
        all up again starts afresh at its first progress (a restarted service first works through
        its history): its backlog then may drain, and its pace is measured from there."""
        before = {st: self._running(st) for st in self.limits}
        (self.up.add if up else self.up.discard)(service)
        for st in self.limits:
            running = self._running(st)
            if running and not before[st]:
                self._pending.add(st)
            elif not running:
                self._pending.discard(st)
                self._since[st] = math.inf

    def progressed(self, stage: str, seq: int, now: float) -> None:
        """``stage`` has reached frame ``seq`` (its newest message)."""
        old = self.done.get(stage)
        if old is None or seq <= old:
            return
        n = bisect.bisect_right(self._sent, seq) - bisect.bisect_right(self._sent, old)
        self.done[stage] = seq
        if stage in self._pending:  # (re)started: from here on
            self._pending.discard(stage)
            self._since[stage] = now
            self._completed[stage].clear()
            self._backlog[stage] = self.in_flight(stage)
            return
        self._completed[stage].append((now, n))

    def resume_from(self, seq: int) -> None:
        """A restarted capture: every stage had reached ``seq`` (the stream's cursor)."""
        for stage in self.done:
            self.done[stage] = max(self.done[stage], seq)

    def in_flight(self, stage: str) -> int:
        """Frames sent that ``stage`` has not reached yet."""
        return len(self._sent) - bisect.bisect_right(self._sent, self.done[stage])

    def _forget_reached(self) -> None:
        """Drop the frames sent that every stage has reached (no longer in flight anywhere)."""
        del self._sent[:bisect.bisect_right(self._sent, min(self.done.values()))]

    def sent(self, seq: int) -> None:
        """Frame ``seq`` went out without asking :meth:`admit` (counted in flight only)."""
        if self.limits and (not self._sent or seq > self._sent[-1]):
            self._forget_reached()
            self._sent.append(seq)

    def admit(self, seq: int, now: float) -> bool:
        """Send frame ``seq`` (True: counted in flight) or shed it (False: counted in ``shed``)."""
        if not self.limits:
            return True
        self._offered.append(now)
        horizon = now - self.rate_s
        if self._offered[0] < horizon:
            del self._offered[:bisect.bisect_left(self._offered, horizon)]
        self._forget_reached()
        share = 1.0
        for stage, lim in self.limits.items():
            done = self._completed[stage]
            while done and done[0][0] < horizon:
                done.popleft()
            if self._since[stage] == math.inf:
                continue  # a service it needs is down (restarting): nothing to match
            n = self.in_flight(stage)
            # a backlog drains and does not grow back, give or take the stage's bursts (a release
            # of the output moves 15 frames at once): hard - soft of slack above its lowest point
            self._backlog[stage] = min(self._backlog[stage], n)
            hard = max(lim.hard, self._backlog[stage] + lim.hard - lim.soft)
            pace = sum(k for _, k in done) / len(self._offered) if self._since[stage] < horizon else None
            if n >= hard and (pace is None or n >= 2 * hard):
                share = 0.0  # pace unknown yet (or far behind): nothing more
            elif n >= hard:
                share = min(share, pace / self.headroom)  # drain back under the bound, still evenly
            elif n > lim.soft and pace is not None:
                share = min(share, pace * self.headroom)
        self._acc += share
        if self._acc >= 1.0 - 1e-9:
            self._acc = min(self._acc - 1.0, 1.0)
            self._sent.append(seq)
            return True
        self.shed += 1
        return False

"""The pipeline's one shedding decision: which arriving frames the flow stage takes.

A live capture of ours sheds before it publishes (:mod:`quick_stream.core.shedding`); a publisher
that is not ours (docs/wire-format.md) does not, and every subscriber of the frame key gets all its
frames. Then the flow stage, the first heavy one, decides for the whole pipeline, before decoding a
frame (:class:`FlowAdmission`):

* **on arrival** (:meth:`FlowAdmission.offer`), before the frame takes a place in flow's queue,
  the same policy as a live capture's (:class:`~quick_stream.core.shedding.Shedder` with
  :data:`FLOW_LIMITS`): past a soft bound of frames admitted and not yet through the motion stage
  (flow's own queue and work included) or not yet stabilized, flow admits about the share those
  stages complete, evenly spaced (one frame in k, so the gaps stay small enough to bridge); from a
  hard bound a share under it, so the backlog drains. Its bounds sit above the capture's, so behind
  a capture of ours that sheds, flow sheds nothing;
* **when taken from the queue** (:meth:`FlowAdmission.take`): a frame with more than ``backlog``
  frames waiting behind it is shed (flow fell behind faster than its pace estimate followed), and
  a frame the queue itself dropped for room is counted and named too (:meth:`FlowAdmission.dropped`).

Every frame shed is counted once (``shed``; ``shed_backlog`` of them at the queue) and named:
:meth:`FlowAdmission.take_shed` hands the seqs shed since the last call to the flow service, which
sends them with its next flow (or its ``end``); the motion stage puts them on that flow's frame's
correction, and the render stage, which receives every frame too, lets those go undecoded instead
of rendering them uncorrected and flagged (docs/architecture.md, Overload). Flow bridges the gaps
shedding leaves as it bridges any missing frames (:class:`~quick_stream.core.continuity.ContinuityCheck`:
up to ``max_missing`` frames, or more within ``max_bridge_s`` of capture time), so the motion is a
fit across them, not a restart of the path.

While a capture of ours is up on the stream (its liveliness token), nothing is shed on arrival: it
paces itself by the same stages' progress (``--pace fast``) or sheds before it publishes (live), and
the two policies' dynamic bounds (a backlog left by a slow start) need not agree, so flow shedding
behind it would throw away frames the capture chose to send. The queue's own bounds still hold.

A frame that is not after the newest one offered, or far ahead of it (``max_jump``), is never
shed: the flow stage refuses it or confirms a new numbering with it (then :meth:`restart`), and a
stray seq never enters the in-flight account. Names not yet sent when the flow stage confirms a
lower numbering are of the old one: they are dropped (:func:`split_named`), never read against the
new numbering's frames (those frames of the old numbering go out uncorrected and flagged, as any
frame whose correction never came). Pure logic: the caller feeds it the stages' progress, the
services' liveliness and the clock.
"""
from __future__ import annotations

from .shedding import UPSTREAM, ShedLimits, Shedder

# Frames admitted by flow and not yet through the stage: above the capture's own bounds (motion 8/20
# frames sent, output 60/90 and a release; core/shedding.DEFAULT_LIMITS), which count the same frames
# and those on their way, so a capture of ours that sheds keeps flow under them.
FLOW_LIMITS = {"motion": ShedLimits(soft=20, hard=30, needs=UPSTREAM["motion"]),
               "stabilized": ShedLimits(soft=110, hard=140, needs=UPSTREAM["stabilized"])}
MAX_NAMED = 10_000  # shed frames named on one message at most (the wire's bound, codec.MAX_SEQ_LIST)
CAPTURE = "capture"  # the service of ours that publishes a stream's frames (its liveliness token)


def split_named(shed: list[int], seq: int, seq_next: int) -> tuple[list[int], list[int], int]:
    """The shed frames a flow from ``seq`` to ``seq_next`` names (those before its end), the ones left
    for a later message, and how many are dropped: a flow to a lower numbering (``seq_next < seq``)
    names those before ``seq`` and drops the rest, which belong to the old numbering."""
    if seq_next < seq:
        named = [s for s in shed if s < seq]
        return named, [], len(shed) - len(named)
    return [s for s in shed if s < seq_next], [s for s in shed if s >= seq_next], 0


class FlowAdmission:
    """Which frames the flow stage takes (module docstring). ``backlog``: frames that may wait in its
    queue behind the one taken; ``limits``: per downstream stage, frames admitted and not through it."""

    def __init__(self, backlog: int, limits: dict[str, ShedLimits] | None = None, max_jump: int = 300,
                 rate_s: float = 3.0, headroom: float = 1.5) -> None:
        if backlog < 0:
            raise ValueError(f"backlog must be >= 0, got {backlog}")
        self.backlog, self.max_jump = backlog, max_jump
        self._make = lambda: Shedder(FLOW_LIMITS if limits is None else limits, rate_s, headroom)
        self.shedder = self._make()
        self.newest: int | None = None  # the newest frame offered in order (in this stream's numbering)
        self._taken: int | None = None  # the newest frame the flow stage took
        self.shed = 0  # frames shed, for every reason
        self.shed_backlog = 0  # ... of which at flow's queue (taken behind too many, or dropped for room)
        self._named: list[int] = []  # shed since the last take_shed

    def _in_order(self, seq: int) -> bool:
        return self.newest is None or 0 < seq - self.newest <= self.max_jump

    def _shed(self, seq: int) -> bool:
        self.shed += 1
        self._named.append(seq)
        if len(self._named) > MAX_NAMED:  # no frame taken for that long: the oldest go unnamed
            del self._named[:-MAX_NAMED]
        return False

    def offer(self, seq: int, now: float) -> bool:
        """Frame ``seq`` arrived at ``now``: whether it goes into flow's queue (False: shed, counted,
        named by :meth:`take_shed`)."""
        if not self._in_order(seq):
            return True  # for the flow stage to refuse, or to confirm as a new numbering
        self.newest = seq
        if CAPTURE in self.shedder.up:
            self.shedder.sent(seq)  # our capture paces or sheds itself: counted in flight, never shed here
            return True
        return self.shedder.admit(seq, now) or self._shed(seq)

    def take(self, seq: int, waiting: int) -> bool:
        """Whether the flow stage decodes and takes frame ``seq``, taken from its queue with ``waiting``
        frames behind it; False: shed (counted, named)."""
        if waiting > self.backlog:
            self.shed_backlog += 1
            return self._shed(seq)
        return True

    def dropped(self, seq: int) -> None:
        """Flow's queue dropped frame ``seq`` for room (a stalled flow): counted and named as shed."""
        self.shed_backlog += 1
        self._shed(seq)

    def taken(self, seq: int) -> None:
        """The flow stage took frame ``seq``. One at or behind the last it took (a new numbering it
        confirmed: the names not yet sent are dropped) or beyond every frame offered in order (a jump
        it confirmed: they are kept) starts the downstream account afresh there."""
        if self._taken is not None and seq <= self._taken:  # a lower numbering: the names are of the old one
            self.restart()
            self.newest = seq
        elif self.newest is not None and seq > self.newest:  # a jump ahead: the same numbering
            self.restart(keep_named=True)
            self.newest = seq
        self._taken = seq

    def progressed(self, stage: str, seq: int, now: float) -> None:
        """``stage`` (``motion``, ``stabilized``) has reached frame ``seq``; a seq beyond the newest frame
        offered is a message of an earlier stream (its output still draining) and says nothing."""
        if self.newest is not None and seq <= self.newest:
            self.shedder.progressed(stage, seq, now)

    def set_up(self, service: str, up: bool, now: float) -> None:
        """A service's liveliness token appeared or went away (nothing is shed on account of a stage
        whose service is down: :meth:`~quick_stream.core.shedding.Shedder.set_up`)."""
        self.shedder.set_up(service, up, now)

    def take_shed(self) -> list[int]:
        """The seqs shed since the last call (sent with the next flow, or the ``end``)."""
        out, self._named = self._named, []
        return out

    def restart(self, keep_named: bool = False) -> None:
        """A new stream (or numbering): the downstream account starts afresh, the services' liveliness
        and the counters carry on; ``keep_named``: the seqs not yet sent too."""
        up = self.shedder.up
        self.shedder = self._make()
        for service in up:
            self.shedder.set_up(service, True, 0.0)
        self.newest = self._taken = None
        if not keep_named:
            self._named = []

    def stats(self) -> dict[str, int]:
        return {"shed": self.shed, "shed_backlog": self.shed_backlog}

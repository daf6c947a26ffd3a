"""The flow stage: scene flow of each good frame from the one before it, over a stream
(:class:`FlowStage`) and over a service's life (:class:`FlowDriver`): the continuity check, frames whose
flow starves reached over (docs/method.md 2.4), what is refused counted and logged. The motion and render
sides are :mod:`.stages` and :mod:`.release`."""
from __future__ import annotations

import logging
from dataclasses import replace
from typing import Collection

from .continuity import ContinuityCheck, ContinuityParams, published_after
from .frame import RGBDFrame
from .logs import log_or_quiet
from .sceneflow import SceneFlow, SceneFlowParams, SceneFlowResult


class FlowStage:
    """Scene flow between each good frame and the previous one (one instance per stream).

    Each frame first passes :class:`~quick_stream.core.continuity.ContinuityCheck` (counted in
    ``check.counts``); ``notes`` holds what it reported of the last frame pushed. A frame whose flow
    starves (fewer than ``reach_min_pairs`` pairs: smeared by motion blur, blank) is reached over: the
    flow to the next frame starts from the frame before it, for at most ``reach_over`` frames
    (docs/method.md 2.4); ``reached_over`` counts them. A weak flow (fewer than ``reach_back_pairs``, or
    lifted loose) is held one frame: when the flow out of its frame starves, the smeared frame is that one, and the flow
    from the frame before it to the next is tried in place of both (reached back over it).
    """

    def __init__(self, params: SceneFlowParams | None = None, continuity: ContinuityParams | None = None) -> None:
        self.flow = SceneFlow(params)
        self.check = ContinuityCheck(continuity)
        self.notes: list[str] = []
        self._prev: RGBDFrame | None = None
        self._prev_pub: int | None = None  # when the previous good frame was published (None: unknown)
        self._anchor: RGBDFrame | None = None  # while frames are reached over: the frame before them
        self._pending: SceneFlowResult | None = None  # ... and the starved flow from it to the newest of them
        self._from_good = True  # whether the flow into the last frame had pairs enough (a reach may start there)
        self._weak: SceneFlowResult | None = None  # a weak flow into the last frame, held one frame ...
        self._weak_from: RGBDFrame | None = None  # ... and the frame it starts from
        self.reached_over = 0  # frames reached over, over the stage's life
        self.loose = 0  # flows passed on lifted loose (docs/method.md (1c)), over the stage's life
        self.began = False  # whether the last frame pushed began a chain (the first of a stream)

    def push(self, frame: RGBDFrame, pub_ns: int | None = None, shed: Collection[int] = ()) -> list[SceneFlowResult]:
        """Add the next frame (:meth:`_push`); counts the flows it passes on lifted loose."""
        return self._counted(self._push(frame, pub_ns, shed))

    def _counted(self, flows: list[SceneFlowResult]) -> list[SceneFlowResult]:
        self.loose += sum(bool(f.counts.get("loose")) for f in flows)
        return flows

    def _push(self, frame: RGBDFrame, pub_ns: int | None, shed: Collection[int]) -> list[SceneFlowResult]:
        """Add the next frame; returns the flows it completes, in order: none for the first frame of a
        chain or one reached over, else the flow into it (from the frame before those reached over,
        naming them in ``over``), after a discontinuity the held starved flow first.

        A frame the check refuses (no valid depth, duplicate, out of order) raises
        :class:`~quick_stream.core.continuity.FrameRefused` (a ValueError) and is not used. Across a
        discontinuity (too many missing frames, a timestamp jump, a size change, a confirmed
        renumbering: the flow then goes back, ``seq_next < seq``) the flow is empty and its
        ``problem`` names the discontinuity, so the path restarts there. ``pub_ns``: when the frame
        was published (a frame message's ``pub_ns``), so a history replay of older frames never
        passes for a new numbering (:func:`~quick_stream.core.continuity.published_after`). ``shed``:
        frames this stage shed (:mod:`~quick_stream.core.admission`); those between the previous good
        frame and this one are bridged as any missing frame but not counted missing.
        """
        prev = self._prev
        n_shed = 0 if prev is None else sum(prev.seq < s < frame.seq for s in shed)
        verdict = self.check.inspect(prev, frame, published_after(pub_ns, self._prev_pub), shed=n_shed)
        self.notes = verdict.notes
        self._prev, self._prev_pub = frame, pub_ns
        self.began = prev is None
        if prev is None:
            return []
        if verdict.brk:
            held = self._finish()
            self._from_good = True  # the frame after a break starts afresh
            return held + [SceneFlowResult.empty(prev, frame, verdict.brk)]
        start = self._anchor or prev
        flow = self.flow.compute(start, frame)
        if self._pending is not None:
            flow = replace(flow, over=(*self._pending.over, self._pending.seq_next))
        p = self.flow.params
        out: list[SceneFlowResult] = []
        weak, weak_from, self._weak = self._weak, self._weak_from, None
        if weak is not None:
            back = self._reach_back(weak, weak_from, flow, frame) if len(flow) < p.reach_min_pairs else None
            if back is None:
                out.append(weak)  # its frame holds: the weak flow goes on as it is
                self.reached_over += len(weak.over)
            else:
                start, flow = weak_from, back
        starved = len(flow) < p.reach_min_pairs
        # reach over the frame, unless the reach is spent or the frame it would start from is itself the
        # starved one (the flow into it starved: reaching past its successor could not help)
        if starved and len(flow.over) < p.reach_over and (self._pending is not None or self._from_good):
            self._anchor, self._pending = start, flow
            self.notes = [*self.notes, f"frame {frame.seq}: its flow from frame {start.seq} starved "
                                       f"({flow.problem or f'{len(flow)} pairs'}): reached over, the next "
                                       f"flow starts from frame {start.seq}"]
            return out
        self._anchor = self._pending = None
        self._from_good = not starved
        holds_little = len(flow) < p.reach_back_pairs or bool(flow.counts.get("loose"))
        if not starved and holds_little and p.reach_back_pairs and len(flow.over) < p.reach_over:
            self._weak, self._weak_from = flow, start  # held: the next flow tells whether its frame is smeared
            return out
        self.reached_over += len(flow.over)
        return [*out, flow]

    def _reach_back(self, weak: SceneFlowResult, weak_from: RGBDFrame, flow: SceneFlowResult,
                    frame: RGBDFrame) -> SceneFlowResult | None:
        """The flow from the frame before a weak flow's (``weak_from``) to ``frame``, over the weak flow's
        frame, when the flow out of that frame (``flow``) starved and the one over it is better than the weak
        one (:func:`rank`: that frame is the smeared one); else None."""
        back = self.flow.compute(weak_from, frame)
        if rank(back) <= rank(weak):
            return None
        self.notes = [*self.notes, f"frame {weak.seq_next}: the flow out of it to frame {frame.seq} starved "
                                   f"({flow.problem or f'{len(flow)} pairs'}) after a weak one into it ({len(weak)} "
                                   f"pairs): reached back over it, the flow from frame {weak_from.seq} has "
                                   f"{len(back)} pairs"]
        return replace(back, over=(*weak.over, weak.seq_next))

    def finish(self) -> list[SceneFlowResult]:
        """The held flows: a weak one, and the starved one if frames are being reached over (the end of a
        stream or a break ends the reach: the motion stage bridges it)."""
        return self._counted(self._finish())

    def _finish(self) -> list[SceneFlowResult]:
        held = [f for f in (self._weak, self._pending) if f is not None]
        self.reached_over += sum(len(f.over) for f in held)
        self._from_good = self._pending is None
        self._anchor = self._pending = self._weak = self._weak_from = None
        return held

    def restart(self) -> None:
        """End of stream: the next frame starts a new chain (the counters go on); call :meth:`finish` first."""
        self._prev = self._prev_pub = self._anchor = self._pending = self._weak = self._weak_from = None
        self._from_good = True


def rank(flow: SceneFlowResult) -> tuple[bool, int]:
    """How much a flow tells, for comparing two flows: a strict one before one lifted loose, then by pairs."""
    return not flow.counts.get("loose"), len(flow)


class FlowDriver:
    """The flow stage over a service's life: a frame refused (``refused_frames``) or a flow made empty
    by a discontinuity (``empty_flows``) is counted and reported on ``log`` (None: silent), with what
    the continuity check noted; one stream after another (:meth:`restart`)."""

    def __init__(self, params: SceneFlowParams | None = None, continuity: ContinuityParams | None = None,
                 log: logging.Logger | None = None) -> None:
        self.stage = FlowStage(params, continuity)
        self.log = log_or_quiet(log)
        self.refused = self.empty = 0
        self.taken: int | None = None  # the seq of the frame the last push took (None: it was refused)

    def push(self, frame: RGBDFrame, pub_ns: int | None = None, shed: Collection[int] = ()) -> list[SceneFlowResult]:
        """The flows ``frame`` completes (:meth:`FlowStage.push`; ``shed``: the frames shed before it);
        none for the first frame of a stream, one reached over and a refused one."""
        self.taken = None
        try:
            flows = self.stage.push(frame, pub_ns, shed)
        except ValueError as e:
            self.refused += 1
            self.log.log(logging.ERROR, "refused: %s", e)
            return []
        self.taken = frame.seq
        for note in self.stage.notes:
            self.log.log(logging.WARNING, "%s", note)
        return self._said(flows)

    def finish(self) -> list[SceneFlowResult]:
        """The end of a stream: the flow held while frames were reached over (:meth:`FlowStage.finish`)."""
        return self._said(self.stage.finish())

    def _said(self, flows: list[SceneFlowResult]) -> list[SceneFlowResult]:
        for flow in flows:
            if flow.over:
                self.log.log(logging.WARNING, "flow %d->%d reaches over frame%s %s (their own flow starved)",
                             flow.seq, flow.seq_next, "s" * (len(flow.over) > 1), ", ".join(map(str, flow.over)))
            if flow.counts.get("loose"):
                self.log.log(logging.WARNING, "flow %d->%d lifted loose (%d pairs; the strict tests kept too few: "
                             "motion blur)", flow.seq, flow.seq_next, len(flow))
            if flow.problem:
                self.empty += 1
                self.log.log(logging.WARNING, "flow %d->%d: %s", flow.seq, flow.seq_next, flow.problem)
        return flows

    def restart(self) -> None:
        """End of stream: the next frame starts a new chain (the counters go on); :meth:`finish` first."""
        self.stage.restart()

    def stats(self) -> dict[str, int]:
        return {"refused_frames": self.refused, "empty_flows": self.empty, "reached_over": self.stage.reached_over,
                "loose_flows": self.stage.loose, **self.stage.check.counts}

"""When a capture sends each frame, and under which number: pure policy (the transport is
:mod:`quick_stream.stream.capture`).

* :class:`Pacer` (``--pace realtime``): each frame at its own capture time (scaled by ``speed``) or
  at a fixed rate, measured from the first frame; how far behind the capture is (``behind_ms``).
* :class:`CreditWindow` (``--pace fast``): frame ``seq`` waits until the stabilized output has
  reached ``seq - window`` and the motion stage ``seq - window // 3``, so a replay runs as fast as
  the slowest stage without overrunning its drop-oldest queue (flow holds 30 frames; the output
  lags by a segment, so its window is wider).
* :class:`Numbering`: the stream seq of a source frame, its own, or continuing after the newest
  frame the stream had reached when a restarted capture came up (its cursor).

Live sources that are offered more than the pipeline takes shed frames instead of waiting:
:class:`~quick_stream.core.shedding.Shedder` (docs/reliability.md, overload).
"""
from __future__ import annotations

import time
from typing import Callable

CREDIT_STAGES = ("stabilized", "motion")  # the stages whose progress a capture follows (their newest frame)


class Pacer:
    """Realtime pacing: frame ``i`` is due ``i / fps`` seconds after the start, or (no ``fps``) when
    its capture time, less the first frame's and divided by ``speed``, has passed."""

    def __init__(self, fps: float | None = None, speed: float = 1.0, clock: Callable[[], float] = time.monotonic) -> None:
        self.period = None if fps is None else 1.0 / fps
        self.speed, self.clock = speed, clock
        self.t_start = clock()
        self.ts0: int | None = None  # the first frame's capture time
        self.behind_ms = 0.0  # how late the last frame was

    def _since_start(self, i: int, timestamp_ns: int) -> float:
        return i * self.period if self.period else (timestamp_ns - (self.ts0 or 0)) / 1e9 / self.speed

    def delay(self, i: int, timestamp_ns: int) -> float:
        """Seconds until frame ``i`` (capture time ``timestamp_ns``) is due: wait that long when
        positive; a late frame goes at once and counts in ``behind_ms``."""
        if self.ts0 is None:
            self.ts0 = timestamp_ns
        delay = self.t_start + self._since_start(i, timestamp_ns) - self.clock()
        self.behind_ms = max(0.0, -delay * 1e3)
        return delay

    def restart_at(self, i: int, timestamp_ns: int) -> None:
        """Frame ``i`` went out only now (the capture waited until every receiver had the stream's first
        frame): the frames after it are paced from here."""
        self.t_start, self.ts0 = self.clock() - (i * self.period if self.period else 0.0), timestamp_ns


class CreditWindow:
    """Fast pace's flow control (module docstring): ``window`` frames in flight to the stabilized
    output, a third of it to the motion stage (0: no limit)."""

    def __init__(self, window: int) -> None:
        self.window = window
        self.done = dict.fromkeys(CREDIT_STAGES, -1)  # each stage's newest frame

    def progressed(self, stage: str, seq: int) -> None:
        self.done[stage] = max(self.done[stage], seq)

    def resume_from(self, seq: int) -> None:
        """A restarted capture: the stream had reached frame ``seq`` downstream (the cursor), so the
        credit counts from there, not from -1 (it waited for output the idle pipeline never made,
        then sent without flow control and overran the stages)."""
        for stage in self.done:
            self.progressed(stage, seq)

    def blocked(self, seq: int) -> bool:
        """Whether frame ``seq`` must wait for the pipeline."""
        return self.window > 0 and (seq - self.done["stabilized"] > self.window
                                    or seq - self.done["motion"] > self.window // 3)


class Numbering:
    """The stream seq of each source frame: the source's own, or, for a capture restarted while its
    stream was under way (``resume_after``: the newest frame any service had seen), continuing after it."""

    def __init__(self, resume_after: int | None = None) -> None:
        self.resume_after = resume_after
        self.offset: int | None = None  # added to the source's seq, fixed by the first frame

    def seq(self, source_seq: int) -> int:
        if self.offset is None:
            self.offset = 0 if self.resume_after is None else max(0, self.resume_after + 1 - source_seq)
        return source_seq + self.offset

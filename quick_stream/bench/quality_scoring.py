"""The one scorer of ``quick-stream bench quality``: every method's output frames against the same
input frames, through :class:`~quick_stream.quality.metrics.MetricsAccumulator` and the
border-free cropping of :mod:`quick_stream.quality.metrics_border` (given the metrics'
input-output homography of each frame, so dark scene content is not taken for a border).

``jitter_px_border_free``: the jitter in pixels a method would show once made border-free by the one
static crop that removes every border it left (its border-free scale s zooms the output by 1 / s, so its
pixel jitter grows by 1 / s; a border-free method's is its jitter). The pixel jitter of methods that
leave black borders is only comparable with a border-free one's through it.

``jitter_bound_px`` / ``jitter_bound_deg``: the least jitter a border-free 2D crop-shift-and-turn
stabilizer at constant zoom can reach at the method's border-free cropping, from the same input
(docs/method.md 6.3): how much of a 2D method's jitter its cropping left it no way to remove."""
from __future__ import annotations

import time
from typing import Iterable

import numpy as np

from ..quality.jitter_bound import border_free_jitter_bound
from ..quality.metrics import MetricsAccumulator
from ..quality.metrics_border import BorderFreeAccumulator, border_free_cropping


class Scorer:
    """The one scorer: quality metrics and border-free cropping, frame pair by frame pair."""

    def __init__(self, fps: float) -> None:
        self.metrics = MetricsAccumulator(fps)
        self.border = BorderFreeAccumulator()
        self.seconds = 0.0
        self.size: tuple[int, int] | None = None  # input (width, height)

    def add(self, input_frame: np.ndarray, output_frame: np.ndarray) -> None:
        t0 = time.perf_counter()
        self.size = self.size or (input_frame.shape[1], input_frame.shape[0])
        self.metrics.add(input_frame, output_frame)
        self.border.add(output_frame, input_frame, self.metrics.last_homography)
        self.seconds += time.perf_counter() - t0

    def result(self) -> dict:
        m = self.metrics.result().as_dict()
        m.update(self.border.as_dict())
        m["border_free_cropping"] = border_free_cropping(m["cropping"], self.border.scale)
        # the static crop that removes every border magnifies what is left of the shake by 1 / scale
        m["jitter_px_border_free"] = m["jitter_px"] / self.border.scale if self.border.scale > 0 else float("inf")
        bfc = m["border_free_cropping"]
        bound = (float("nan"), float("nan"))
        if self.size is not None and bfc > 0 and len(self.metrics.frames) >= 2:  # a fit's noise can read 1.0004
            bound = border_free_jitter_bound(self.metrics.input_motions(), min(bfc, 1.0), *self.size, self.metrics.jitter_sigma)
        m["jitter_bound_px"], m["jitter_bound_deg"] = bound
        m["scorer_seconds"] = self.seconds
        return m


def score_frames(inputs: list[np.ndarray], outputs: Iterable[np.ndarray], fps: float) -> dict:
    """Metrics of ``outputs`` (aligned with ``inputs``, same count) with :class:`Scorer`."""
    sc = Scorer(fps)
    n = 0
    for a, b in zip(inputs, outputs):
        sc.add(a, b)
        n += 1
    if n != len(inputs):
        raise ValueError(f"{n} output frames for {len(inputs)} inputs")
    return sc.result()

"""Per-stage wall-clock timing (the stages, the in-process stabilizer, ``quick-stream motion``)."""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Iterable, Iterator

import numpy as np


@dataclass
class StageTimer:
    """Per-stage wall-clock samples in milliseconds."""

    samples: dict[str, list[float]] = field(default_factory=dict)

    def add(self, stage: str, ms: float) -> None:
        self.samples.setdefault(stage, []).append(ms)

    def summary(self) -> dict[str, dict[str, float]]:
        out = {}
        for k, v in self.samples.items():
            a = np.asarray(v)
            out[k] = {
                "mean": float(a.mean()),
                "median": float(np.median(a)),
                "p95": float(np.percentile(a, 95)),
                "n": int(a.size),
            }
        return out


def timed_iter(it: Iterable, timer: StageTimer, stage: str) -> Iterator:
    """Yield from ``it`` recording how long each item took to produce."""
    it = iter(it)
    while True:
        t0 = time.perf_counter()
        try:
            item = next(it)
        except StopIteration:
            return
        timer.add(stage, (time.perf_counter() - t0) * 1e3)
        yield item

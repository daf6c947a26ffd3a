"""Per-period measurements a service reports in its stats: item rates and latency percentiles."""
from __future__ import annotations

import time

import numpy as np


class RateMeter:
    """Items and per-item milliseconds over the last stats period."""

    def __init__(self) -> None:
        self.total = 0
        self._n = 0
        self._ms: list[float] = []
        self._t0 = time.monotonic()

    def add(self, ms: float | None = None) -> None:
        self.total += 1
        self._n += 1
        if ms is not None:
            self._ms.append(ms)

    def take(self, prefix: str) -> dict[str, float]:
        """fps and ms p50/p99 since the last take, keys prefixed."""
        now = time.monotonic()
        dt = max(now - self._t0, 1e-9)
        out = {f"{prefix}_fps": round(self._n / dt, 2), f"{prefix}_total": self.total}
        if self._ms:
            a = np.asarray(self._ms)
            out[f"{prefix}_ms_p50"] = round(float(np.percentile(a, 50)), 3)
            out[f"{prefix}_ms_p99"] = round(float(np.percentile(a, 99)), 3)
        self._n, self._ms, self._t0 = 0, [], now
        return out


class Percentiles:
    """Samples of one quantity over the last stats period: p50/p99/max on take."""

    def __init__(self) -> None:
        self._v: list[float] = []

    def add(self, v: float) -> None:
        self._v.append(v)

    def take(self, prefix: str) -> dict[str, float]:
        if not self._v:
            return {}
        a = np.asarray(self._v)
        self._v = []
        return {f"{prefix}_p50": round(float(np.percentile(a, 50)), 2),
                f"{prefix}_p99": round(float(np.percentile(a, 99)), 2),
                f"{prefix}_max": round(float(a.max()), 2), f"{prefix}_n": int(a.size)}

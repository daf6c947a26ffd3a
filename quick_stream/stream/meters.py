"""Per-period measurements a service reports in its stats: item rates, percentiles, frame latencies."""
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


class Latency:
    """A stabilized frame's latencies from its stamps (docs/wire-format.md), over the last stats
    period: processing (since the frame that closed its release was published, ``lat_proc_ms``)
    and total (since the frame itself was published, ``lat_total_ms``)."""

    def __init__(self) -> None:
        self.proc, self.total = Percentiles(), Percentiles()

    def add(self, src_pub_ns: int | None, ready_pub_ns: int | None, now_ns: int | None = None) -> None:
        now = time.time_ns() if now_ns is None else now_ns
        if ready_pub_ns:
            self.proc.add((now - ready_pub_ns) / 1e6)
        if src_pub_ns:
            self.total.add((now - src_pub_ns) / 1e6)

    def take(self) -> dict[str, float]:
        return {**self.proc.take("lat_proc_ms"), **self.total.take("lat_total_ms")}

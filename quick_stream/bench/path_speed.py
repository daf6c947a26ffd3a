"""Path solver speed per group: ms per frame amortised over 30-frame segments (target <= 1 ms).

Segments are built from the synthetic source's ground-truth motions (hand-held
shake with roll), expressed in each group, with smoothed-mode-like end
constraints; zeta_bar comes precomputed from the motion stage, as in the pipeline.
"""
from __future__ import annotations

import time

import numpy as np

from ..lie import GROUPS, get_group
from ..path import solve_segment, zeta_bar
from ..sources.synthetic import SyntheticSource


def run(segments: int = 20, length: int = 30) -> dict:
    poses = SyntheticSource(frames=segments * length + 1, width=64, height=48).poses()
    motions = np.linalg.inv(poses[:-1]) @ poses[1:]
    out = {}
    rng = np.random.default_rng(0)
    for name in sorted(GROUPS):
        g = get_group(name)
        ms, iters, worst = [], [], 0.0
        for k in range(segments):
            seg = motions[k * length:(k + 1) * length]
            zb = zeta_bar(g, seg)
            C1 = g.exp(rng.normal(0, 0.005, g.dim))
            t0 = time.perf_counter()
            sol = solve_segment(g, seg, None, C1, zbar=zb)
            ms.append((time.perf_counter() - t0) * 1e3)
            iters.append(sol.iterations)
            worst = max(worst, sol.residual)
        out[name] = {"ms_per_frame": float(np.sum(ms) / (segments * length)),
                     "ms_per_segment_p95": float(np.percentile(ms, 95)),
                     "iterations_mean": float(np.mean(iters)), "max_residual": worst}
    return out


def format_table(r: dict) -> str:
    lines = [f"{'group':6s} {'ms/frame':>9s} {'p95 ms/segment':>15s} {'iterations':>11s} {'max residual':>13s}"]
    for name, m in r.items():
        lines.append(f"{name:6s} {m['ms_per_frame']:9.3f} {m['ms_per_segment_p95']:15.2f} "
                     f"{m['iterations_mean']:11.1f} {m['max_residual']:13.1e}")
    return "\n".join(lines)

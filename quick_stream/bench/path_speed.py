"""Path solver speed per group: ms per frame amortised over 30-frame segments (target <= 1 ms).

Default table: segments from the synthetic source's ground-truth motions (hand-held
shake with roll), expressed in each group, with smoothed-mode-like end constraints;
zeta_bar comes precomputed from the motion stage, as in the pipeline.

Stress table (``quick-stream bench path --shake DEG,M``): seeded large-motion segments
(:func:`stress_segment`: random per-frame rotations of DEG degrees and translations of M
metres on top of a smooth path, the paper's full-undo zeta_bar, random end-constraints
of the same size); per group the segments whose Newton solve did not converge, how many
of those the fallback path still stabilized (docs/method.md 4.1), iterations, ms per
frame and the largest end-constraint residual |log(C1^-1 g_s(tf))| of the returned paths.
"""
from __future__ import annotations

import time
from typing import Callable

import numpy as np

from ..core.lie import GROUPS, LieGroup, get_group
from ..core.path import solve_segment, zeta_bar
from ..io.sources.synthetic import SyntheticSource

SMOOTH_TRANS_M = 0.02  # stress: per-axis sd of the smooth path's per-frame translation
SMOOTH_ROT_DEG = 0.3  # and rotation


def run(segments: int = 20, length: int = 30, progress: Callable[[str], None] | None = None) -> dict:
    """``progress``: told each segment solved."""
    poses = SyntheticSource(frames=segments * length + 1, width=64, height=48).poses()
    motions = np.linalg.inv(poses[:-1]) @ poses[1:]
    out = {}
    rng = np.random.default_rng(0)
    for name in sorted(GROUPS):
        g = get_group(name)
        ms, iters, worst = [], [], 0.0
        for k in range(segments):
            if progress:
                progress(f"{name}: segment {k + 1}/{segments}")
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


def _random_rigid(rng: np.random.Generator, rot_deg: float, trans_m: float, count: int) -> np.ndarray:
    """``count`` rigid motions (count, 4, 4): rms rotation angle ``rot_deg``, rms translation ``trans_m``."""
    xi = np.concatenate([rng.normal(0.0, trans_m / np.sqrt(3), (count, 3)),
                         rng.normal(0.0, np.radians(rot_deg) / np.sqrt(3), (count, 3))], axis=1)
    return get_group("se3").exp(xi)


def stress_segment(rng: np.random.Generator, length: int = 30, rot_deg: float = 4.0,
                   trans_m: float = 0.05) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One seeded large-motion segment: (motions (length, 4, 4), C0, C1).

    The camera motion of frame t is ``S D_t``: S a smooth path's constant per-frame step
    (translation N(0, 2 cm), rotation N(0, 0.3 deg) per axis, drawn per segment) and D_t the
    shake, a random rotation of rms angle ``rot_deg`` and translation of rms length ``trans_m``.
    C0 and C1 are random rigid corrections of the same size. Rigid motions belong to every
    group, so the same segment serves SE(3), SIM(3), SA(3) and GA(3).
    """
    smooth = _random_rigid(rng, np.sqrt(3) * SMOOTH_ROT_DEG, np.sqrt(3) * SMOOTH_TRANS_M, 1)[0]
    motions = smooth @ _random_rigid(rng, rot_deg, trans_m, length)
    C0, C1 = _random_rigid(rng, rot_deg, trans_m, 2)
    return motions, C0, C1


def run_stress(rot_deg: float = 4.0, trans_m: float = 0.05, segments: int = 100, length: int = 30,
               seed: int = 0, groups: tuple[str, ...] | None = None,
               progress: Callable[[str], None] | None = None) -> dict:
    """Solve ``segments`` stress segments (the same ones for every group, paper's zeta_bar);
    ``progress``: told each segment."""
    out = {}
    for name in groups or sorted(GROUPS):
        g: LieGroup = get_group(name)
        rng = np.random.default_rng(seed)
        ms, iters, init_iters, failed, fallback, worst = [], [], [], 0, 0, 0.0
        for k in range(segments):
            if progress:
                progress(f"{name}: segment {k + 1}/{segments}")
            motions, C0, C1 = stress_segment(rng, length, rot_deg, trans_m)
            zb = zeta_bar(g, motions)
            t0 = time.perf_counter()
            sol = solve_segment(g, motions, C0, C1, zbar=zb)
            ms.append((time.perf_counter() - t0) * 1e3)
            iters.append(sol.iterations)
            init_iters.append(sol.init_iterations)
            failed += not sol.converged
            fallback += bool(not sol.converged and sol.fallback)
            worst = max(worst, sol.residual)
        out[name] = {"segments": segments, "failed": failed, "fallback": fallback,
                     "unstabilized": failed - fallback,
                     "iterations_mean": float(np.mean(iters)), "iterations_max": int(np.max(iters)),
                     "init_iterations_mean": float(np.mean(init_iters)),
                     "ms_per_frame": float(np.sum(ms) / (segments * length)),
                     "ms_per_segment_p95": float(np.percentile(ms, 95)), "max_residual": worst}
    return out


def format_table(r: dict) -> str:
    lines = [f"{'group':6s} {'ms/frame':>9s} {'p95 ms/segment':>15s} {'iterations':>11s} {'max residual':>13s}"]
    for name, m in r.items():
        lines.append(f"{name:6s} {m['ms_per_frame']:9.3f} {m['ms_per_segment_p95']:15.2f} "
                     f"{m['iterations_mean']:11.1f} {m['max_residual']:13.1e}")
    return "\n".join(lines)


def format_stress_table(r: dict, rot_deg: float, trans_m: float, length: int = 30) -> str:
    """The stress table: failed = Newton did not converge; fallback = of those, stabilized anyway."""
    lines = [f"stress: {length}-frame segments, per-frame shake {rot_deg:g} deg / {trans_m:g} m (rms), "
             "paper's zeta_bar, random end-constraints of the same size",
             f"{'group':6s} {'failed':>8s} {'fallback':>9s} {'iterations mean/max':>20s} {'init it':>8s} "
             f"{'ms/frame':>9s} {'p95 ms/segment':>15s} {'max residual':>13s}"]
    for name, m in r.items():
        fails = f"{m['failed']}/{m['segments']}"
        its = f"{m['iterations_mean']:.2f}/{m['iterations_max']}"
        lines.append(f"{name:6s} {fails:>8s} {m['fallback']:9d} {its:>20s} {m['init_iterations_mean']:8.2f} "
                     f"{m['ms_per_frame']:9.3f} {m['ms_per_segment_p95']:15.2f} {m['max_residual']:13.1e}")
    return "\n".join(lines)

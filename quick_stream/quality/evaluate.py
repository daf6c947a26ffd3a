"""The paper's evaluation protocol on a TUM-layout folder.

K random subsequences of L frames (seeded), each stabilized with every group,
each scored with the quality metrics and the failure rule (a failed sequence
counts 0 for cropping, distortion and stability); the averages form a table.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from ..core.frame import BadFrame, RGBDFrame
from ..core.motion import MotionParams
from ..core.path.planner import PlannerParams
from ..core.render import FramingParams
from ..core.stabilizer import StabilizedFrame, Stabilizer, StabilizerParams
from ..io.sources.tum import TumSource
from .metrics import MetricsAccumulator

GROUPS = ("se3", "sim3", "sa3", "ga3")
AVERAGED = ("cropping", "distortion", "stability", "jitter_px", "jitter_deg", "input_jitter_px")


@dataclass
class EvaluateParams:
    subsequences: int = 20  # K
    length: int = 30  # L frames
    seed: int = 0
    groups: tuple[str, ...] = GROUPS
    end: str = "smoothed"
    framing: str = "auto"


def pick_starts(n_frames: int, p: EvaluateParams) -> list[int]:
    """K start indices of L-frame windows, seeded, sorted (with replacement only if the clip is short)."""
    if n_frames < p.length:
        raise ValueError(f"clip has {n_frames} frames, fewer than the subsequence length {p.length}")
    rng = np.random.default_rng(p.seed)
    choices = n_frames - p.length + 1
    return sorted(int(s) for s in rng.choice(choices, p.subsequences, replace=p.subsequences > choices))


def run_timed(st: Stabilizer, source: Iterable[RGBDFrame | BadFrame],
              take: Callable[[list[StabilizedFrame]], None]) -> tuple[float, int]:
    """Push ``source`` through ``st`` (then finish), handing each output batch to ``take``.

    Returns (seconds spent in the stabilizer alone, frames read)."""
    t, frames = 0.0, 0
    for fr in source:
        frames += 1
        t0 = time.perf_counter()
        batch = st.push(fr)
        t += time.perf_counter() - t0
        take(batch)
    t0 = time.perf_counter()
    batch = st.finish()
    t += time.perf_counter() - t0
    take(batch)
    return t, frames


def stabilize_and_score(source: Iterable[RGBDFrame | BadFrame], params: StabilizerParams, fps: float) -> dict:
    """Stabilize ``source`` (read lazily) and score the output against its input.

    Returns the metrics plus our compute time per frame (stabilizer only, not the
    metrics), flagged frames, bad frames and segments.
    """
    st = Stabilizer(params, keep_inputs=True)
    acc = MetricsAccumulator(fps)
    flagged = 0

    def score(batch: list[StabilizedFrame]) -> None:
        nonlocal flagged
        for sf in batch:
            acc.add(sf.input_image, sf.image)
            flagged += bool(sf.flags)

    t, frames = run_timed(st, source, score)
    m = acc.result().as_dict()
    m.update(ms_per_frame=1e3 * t / max(frames, 1), flagged_frames=flagged, bad_frames=len(st.bad_frames),
             segments=st.planner.segment_count)
    return m


def stabilize_window(folder: Path, start: int, p: EvaluateParams, group: str) -> dict:
    src = TumSource(folder, start=start, count=p.length)
    params = StabilizerParams(motion=MotionParams(group=group), planner=PlannerParams(group=group, end=p.end),
                              framing=FramingParams(mode=p.framing))
    m = stabilize_and_score(src, params, src.fps)
    m.update(start=start, group=group)
    return m


def evaluate(folder: Path, p: EvaluateParams | None = None, progress=None) -> dict:
    p = p or EvaluateParams()
    folder = Path(folder)
    starts = pick_starts(len(TumSource(folder)), p)
    runs: list[dict] = []
    for group in p.groups:
        for s in starts:
            runs.append(stabilize_window(folder, s, p, group))
            if progress:
                progress(len(runs), len(starts) * len(p.groups))
    table = {}
    for group in p.groups:
        rs = [r for r in runs if r["group"] == group]
        row = {k: float(np.mean([r[k] for r in rs])) for k in AVERAGED}
        row["failures"] = sum(r["failed"] for r in rs)
        row["ms_per_frame"] = float(np.mean([r["ms_per_frame"] for r in rs]))
        table[group] = row
    return {"folder": str(folder), "subsequences": p.subsequences, "length": p.length, "seed": p.seed,
            "starts": starts, "end": p.end, "framing": p.framing, "table": table, "runs": runs}


def markdown(r: dict) -> str:
    head = ("| group | cropping | distortion | stability | jitter px | jitter deg | input jitter px "
            "| failures | ms/frame |")
    lines = [f"{r['folder']}: {r['subsequences']} subsequences x {r['length']} frames (seed {r['seed']}), "
             f"{r['end']} end-constraints, {r['framing']} framing", "", head, "|" + "---|" * 9]
    for g, row in r["table"].items():
        lines.append(f"| {g} | {row['cropping']:.3f} | {row['distortion']:.3f} | {row['stability']:.3f} | "
                     f"{row['jitter_px']:.3f} | {row['jitter_deg']:.4f} | {row['input_jitter_px']:.3f} | "
                     f"{row['failures']} | {row['ms_per_frame']:.1f} |")
    return "\n".join(lines)

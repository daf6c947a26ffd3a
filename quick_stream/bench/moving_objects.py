"""Moving objects: does the robust estimator stay with the static background?

On ``jointvosf_pairs`` (people, a door, a robot moving through the view; no ground
truth) the reference is the background's own motion: the ``exact`` estimator run
only on scene-flow pairs outside hand-drawn boxes around everything that moves
(:data:`MOVING_BOXES`, drawn on frame 0 and 1 of each pair with a margin). Each
estimator on the *whole* flow is then compared with that reference:

* ``exact`` (robust, the default) should stay close to it;
* ``exact`` with robust weighting off (plain least squares) and ``induced`` (the
  paper's plain mean of induced twists) are pulled by the moving pixels.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from ..core.motion import ExactParams, MotionEstimator, MotionParams
from ..core.sceneflow import SceneFlow, SceneFlowParams
from ..io.sources.tum import TumSource
from ..quality.evaluation.rpe import relative_pose_error

# Hand-drawn boxes (x0, y0, x1, y1) in 640x480 pixels around what moves in each pair.
MOVING_BOXES: dict[str, list[tuple[int, int, int, int]]] = {
    "cleaning_whiteboard": [(180, 0, 470, 480)],
    "opening_door": [(20, 40, 210, 480), (160, 200, 330, 480)],
    "person_standing": [(160, 40, 540, 480)],
    "robot": [(300, 0, 520, 480)],
    "two_people_moving": [(120, 0, 340, 480), (360, 140, 640, 480)],
    "two_people_walking": [(0, 0, 250, 480), (270, 0, 450, 480)],
}

ESTIMATORS = {
    "exact (robust)": MotionParams(),
    "exact, plain LS": MotionParams(exact=ExactParams(robust=False)),
    "induced (mean)": MotionParams(estimator="induced"),
}


def outside_boxes(pixels: np.ndarray, boxes: list[tuple[int, int, int, int]]) -> np.ndarray:
    """True for pixels outside every box."""
    keep = np.ones(len(pixels), bool)
    for x0, y0, x1, y1 in boxes:
        keep &= ~((pixels[:, 0] >= x0) & (pixels[:, 0] < x1) & (pixels[:, 1] >= y0) & (pixels[:, 1] < y1))
    return keep


def evaluate_scene(folder: Path, boxes: list[tuple[int, int, int, int]]) -> dict:
    """Deviation (deg, mm) of each estimator on the full flow from the masked background reference."""
    src = TumSource(folder)
    f0, f1 = src.frame(0), src.frame(1)
    flow = SceneFlow(SceneFlowParams(max_points=20000)).compute(f0, f1)
    keep = outside_boxes(flow.pixels, boxes)
    ref = MotionEstimator(MotionParams()).estimate(flow.subset(keep))
    out = {"points": len(flow), "moving_share": float(1 - keep.mean()), "reference_valid": ref.valid,
           "reference_rot_deg": float(np.degrees(np.linalg.norm(ref.twist[3:6]))),
           "reference_trans_mm": float(np.linalg.norm(ref.twist[:3]) * 1000)}
    for name, params in ESTIMATORS.items():
        m = MotionEstimator(params).estimate(flow)
        rot, tr = relative_pose_error(m.matrix, ref.matrix)
        out[name] = {"rot_dev_deg": rot, "trans_dev_mm": tr, "valid": m.valid}
    return out


def run(data_root: Path, progress: Callable[[str], None] | None = None) -> dict[str, dict]:
    """``progress``: told each scene."""
    root = data_root / "jointvosf_pairs"
    out = {}
    for i, (name, boxes) in enumerate(MOVING_BOXES.items(), 1):
        if progress:
            progress(f"scene {i}/{len(MOVING_BOXES)}: {name}")
        out[name] = evaluate_scene(root / name, boxes)
    return out


def format_table(results: dict[str, dict]) -> str:
    names = list(ESTIMATORS)
    head = f"{'scene':<20} {'moving':>6} {'ref rot':>8} {'ref mm':>7} " + " ".join(f"{n:>26}" for n in names)
    lines = [
        "deviation from the background's own motion (rotation deg / translation mm):",
        head,
    ]
    for scene, r in results.items():
        cells = " ".join(f"{r[n]['rot_dev_deg']:>13.3f} / {r[n]['trans_dev_mm']:>8.1f}" for n in names)
        lines.append(f"{scene:<20} {r['moving_share']:>6.0%} {r['reference_rot_deg']:>8.3f} "
                     f"{r['reference_trans_mm']:>7.1f} {cells}")
    return "\n".join(lines)

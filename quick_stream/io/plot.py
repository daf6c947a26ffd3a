"""Line plots drawn with OpenCV (no plotting dependency): the camera path before and after."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from ..core.lie import so3
from .files import write_file

COLORS = {"before": (60, 60, 220), "after": (60, 170, 40)}  # BGR: red, green


def path_components(poses: np.ndarray) -> np.ndarray:
    """(N, 4, 4) -> (N, 6): translation (mm) and rotation vector (deg) relative to the first pose."""
    rel = np.linalg.inv(poses[0]) @ poses
    R = so3.nearest_rotation(rel[:, :3, :3])  # affine groups carry more than a rotation
    rv = Rotation.from_matrix(R).as_rotvec()
    return np.column_stack([rel[:, :3, 3] * 1000.0, np.degrees(rv)])


def plot_paths(series: dict[str, np.ndarray], fps: float, path: str, width: int = 1200,
               row_height: int = 150) -> None:
    """One row per component (tx, ty, tz in mm; rx, ry, rz in deg), one line per series."""
    labels = ["tx (mm)", "ty (mm)", "tz (mm)", "rx (deg)", "ry (deg)", "roll rz (deg)"]
    margin_l, margin_r, margin_t = 110, 20, 40
    H = margin_t + row_height * 6 + 30
    img = np.full((H, width, 3), 255, np.uint8)
    cv2.putText(img, "camera path: " + ", ".join(f"{k}" for k in series), (margin_l, 26),
                cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
    x_legend = width - 260
    for i, name in enumerate(series):
        col = COLORS.get(name, (120, 120, 120))
        cv2.line(img, (x_legend + 130 * i, 20), (x_legend + 130 * i + 30, 20), col, 2)
        cv2.putText(img, name, (x_legend + 130 * i + 36, 25), cv2.FONT_HERSHEY_SIMPLEX, 0.5, col, 1, cv2.LINE_AA)
    n = max(len(v) for v in series.values())
    xs = margin_l + np.arange(n) * (width - margin_l - margin_r) / max(n - 1, 1)
    for r in range(6):
        top = margin_t + r * row_height
        y0, y1 = top + 10, top + row_height - 10
        vals = np.concatenate([v[:, r] for v in series.values()])
        lo, hi = float(vals.min()), float(vals.max())
        if hi - lo < 1e-9:
            lo, hi = lo - 1, hi + 1
        cv2.rectangle(img, (margin_l, y0), (width - margin_r, y1), (200, 200, 200), 1)
        cv2.putText(img, labels[r], (8, (y0 + y1) // 2), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
        cv2.putText(img, f"{hi:.2f}", (8, y0 + 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (90, 90, 90), 1, cv2.LINE_AA)
        cv2.putText(img, f"{lo:.2f}", (8, y1), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (90, 90, 90), 1, cv2.LINE_AA)
        for name, v in series.items():
            ys = y1 - (v[:, r] - lo) / (hi - lo) * (y1 - y0)
            pts = np.column_stack([xs[: len(v)], ys]).round().astype(np.int32)
            cv2.polylines(img, [pts], False, COLORS.get(name, (120, 120, 120)), 1, cv2.LINE_AA)
    cv2.putText(img, f"frames (0..{n - 1}, {fps:g} fps)", (margin_l, H - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                (0, 0, 0), 1, cv2.LINE_AA)
    ok, png = cv2.imencode(Path(path).suffix or ".png", img)
    if not ok:
        raise OSError(f"cannot encode plot {path}")
    write_file(path, png.tobytes())


PALETTE = [(40, 40, 200), (200, 120, 30), (40, 160, 40), (160, 60, 160), (30, 160, 200), (120, 120, 120)]  # BGR


def plot_xy(panels: list[tuple[str, dict[str, tuple[np.ndarray, np.ndarray]]]], path: str, width: int = 900,
            row_height: int = 220) -> None:
    """One row per panel (title, {series: (xs, ys)}), a line with point markers per series, the same colour
    for a series name in every panel, its legend in the panel; x and y ranges per panel."""
    names = list(dict.fromkeys(n for _, series in panels for n in series))
    colour = {n: PALETTE[i % len(PALETTE)] for i, n in enumerate(names)}
    margin_l, margin_r, margin_t = 80, 20, 10
    H = margin_t + row_height * len(panels) + 10
    img = np.full((H, width, 3), 255, np.uint8)
    font = cv2.FONT_HERSHEY_SIMPLEX
    for r, (title, series) in enumerate(panels):
        top = margin_t + r * row_height
        x0, x1, y0, y1 = margin_l, width - margin_r, top + 30, top + row_height - 30
        cv2.putText(img, title, (x0, top + 20), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        cv2.rectangle(img, (x0, y0), (x1, y1), (200, 200, 200), 1)
        if not series:
            continue
        xs_all = np.concatenate([np.asarray(x, float) for x, _ in series.values()])
        ys_all = np.concatenate([np.asarray(y, float) for _, y in series.values()])
        xlo, xhi = float(xs_all.min()), float(xs_all.max())
        ylo, yhi = 0.0, float(ys_all.max()) * 1.05
        xhi, yhi = (xhi if xhi > xlo else xlo + 1), (yhi if yhi > ylo else ylo + 1)
        for v, y in ((ylo, y1), (yhi, y0)):
            cv2.putText(img, f"{v:.3g}", (8, y + 4), font, 0.4, (90, 90, 90), 1, cv2.LINE_AA)
        for xv in np.unique(xs_all):
            px = int(round(x0 + (xv - xlo) / (xhi - xlo) * (x1 - x0)))
            cv2.putText(img, f"{xv:.2f}", (px - 14, y1 + 16), font, 0.4, (90, 90, 90), 1, cv2.LINE_AA)
        for i, (name, (x, y)) in enumerate(series.items()):
            pts = np.column_stack([x0 + (np.asarray(x, float) - xlo) / (xhi - xlo) * (x1 - x0),
                                   y1 - (np.asarray(y, float) - ylo) / (yhi - ylo) * (y1 - y0)]).round().astype(np.int32)
            col = colour[name]
            cv2.polylines(img, [pts], False, col, 2 if name == "ours" else 1, cv2.LINE_AA)
            for p in pts:
                cv2.circle(img, (int(p[0]), int(p[1])), 3, col, -1, cv2.LINE_AA)
            lx, ly = x1 - 200, y0 + 14 + 15 * i
            cv2.line(img, (lx, ly - 4), (lx + 20, ly - 4), col, 2)
            cv2.putText(img, name, (lx + 26, ly), font, 0.4, col, 1, cv2.LINE_AA)
    ok, png = cv2.imencode(Path(path).suffix or ".png", img)
    if not ok:
        raise OSError(f"cannot encode plot {path}")
    write_file(path, png.tobytes())

"""Stabilizer settings as CLI flags, shared by ``quick-stream stabilize`` and every service.

The offline command and the services must be given the same settings to give the same
output; one flag set and one :func:`stabilizer_params` make that hold by construction.
"""
from __future__ import annotations

import argparse
import dataclasses
import math
from typing import Callable

from ..core.lie import GROUPS
from ..core.motion import ESTIMATORS, MotionParams
from ..core.path.budget import BudgetParams
from ..core.path.constraints import END_MODES
from ..core.path.keyframes import KeyframeParams
from ..core.path.optimal import PathParams
from ..core.path.planner import PATH_MODES, PlannerParams
from ..core.render import FramingParams
from ..core.stabilizer import StabilizerParams


# --latency presets: (keyframe interval, look-ahead, smoothness); the interval is the longest wait
# (frames) a frame has before its correction is released (docs/method.md 4.3). A shorter window
# sees less of the future, so it smooths less (measured: docs/method.md 4.3).
LATENCY_PRESETS = {"normal": (KeyframeParams.interval, PlannerParams.lookahead, PlannerParams.smoothness),
                   "low": (15, 10, 3000.0)}


def add_stabilizer_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("stabilizer settings")
    g.add_argument("--group", choices=sorted(GROUPS), default="se3",
                   help="Lie group of the camera motion: se3 rigid, sim3 + scale, sa3 + per-axis scale, "
                        "ga3 general affine (default se3)")
    g.add_argument("--estimator", choices=ESTIMATORS, default="exact",
                   help="motion estimator: exact = robust fit of the group element, induced = the paper's mean "
                        "of induced twists (default exact)")
    g.add_argument("--latency", choices=sorted(LATENCY_PRESETS), default="normal",
                   help="path latency preset: normal = keyframe interval %d, look-ahead %d, smoothness %g "
                        "(1 s at 30 fps); low = interval %d, look-ahead %d, smoothness %g (0.5 s); "
                        "--keyframe-interval/--lookahead/--smoothness override it (default normal)"
                        % (*LATENCY_PRESETS["normal"], *LATENCY_PRESETS["low"]))
    g.add_argument("--keyframe-interval", type=int, default=None,
                   help="frames per path window (the longest a frame waits for its correction), >= 2 "
                        "(default from --latency)")
    g.add_argument("--lookahead", type=int, default=None,
                   help="smooth path: of each window's frames, the last this many are re-planned with the next "
                        "window before release, < the interval (default from --latency)")
    g.add_argument("--end", choices=END_MODES, default="smoothed",
                   help="--path ep: end-constraint mode (default smoothed)")
    g.add_argument("--lowpass-sigma", type=float, default=PlannerParams.lowpass_sigma,
                   help="--path ep: frames; the path keeps the camera velocity low-passed with this Gaussian "
                        f"(default {PlannerParams.lowpass_sigma:g}; 0 = the paper's full undo)")
    g.add_argument("--path-weights", default=None, metavar="W1,W2,...",
                   help="--path ep: diagonal of the path cost's weight W, one per twist component (default identity)")
    g.add_argument("--path", choices=PATH_MODES, default="smooth",
                   help="smooth: smoothed path with a crop budget; ep: the Euler-Poincare path with "
                        "--end/--lowpass-sigma targets (default smooth)")
    g.add_argument("--max-zoom", type=float, default=BudgetParams.max_zoom,
                   help="smooth path: every frame border-free at a zoom <= this (0 = no budget; "
                        f"default {BudgetParams.max_zoom:g})")
    g.add_argument("--smoothness", type=float, default=None,
                   help="smooth path: weight of the path's acceleration against its distance from the camera, "
                        "lambda of docs/method.md (8) (default from --latency)")
    g.add_argument("--fill-frames", type=int, default=FramingParams.fill_frames,
                   help="border fill: output pixels a frame leaves uncovered are taken from up to this many "
                        f"neighbouring frames on each side (0 = no fill; default {FramingParams.fill_frames})")
    g.add_argument("--fill-band", type=float, default=BudgetParams.fill,
                   help="border fill: share of half the short side the smooth path may leave uncovered for the "
                        f"fill (0 = the crop alone removes every border; default {BudgetParams.fill:g})")
    g.add_argument("--framing", choices=("black", "crop", "auto"), default="auto",
                   help="what the output shows past the frame's edge: black = nothing, crop = a fixed "
                        "--crop-zoom, auto = the planned zoom (default auto)")
    g.add_argument("--crop-zoom", type=float, default=FramingParams.crop_zoom,
                   help=f"zoom for --framing crop, >= 1 (default {FramingParams.crop_zoom:g})")


def _flag_error(flag: str, check: Callable[[], object]) -> None:
    """Run ``check``; its ValueError comes back prefixed with the flag at fault."""
    try:
        check()
    except ValueError as e:
        raise ValueError(f"{flag}: {e}") from None


def _path_weights(text: str | None) -> tuple[float, ...] | None:
    if text is None:
        return None
    try:
        return tuple(float(w) for w in text.split(","))
    except ValueError:
        raise ValueError(f"--path-weights: expected comma-separated numbers, got {text!r}") from None


def _check_lowpass(sigma: float) -> None:
    if not (math.isfinite(sigma) and sigma >= 0):
        raise ValueError(f"must be a finite number >= 0 (frames), got {sigma!r}")


def latency(args: argparse.Namespace) -> tuple[int, int, float]:
    """(keyframe interval, look-ahead, smoothness) from --latency and the explicit flags that override it."""
    interval, lookahead, smoothness = LATENCY_PRESETS[args.latency]
    if args.keyframe_interval is not None:
        interval = args.keyframe_interval
        if args.lookahead is None:  # keep the preset's share of the window re-planned
            lookahead = (interval * lookahead) // LATENCY_PRESETS[args.latency][0]
    if args.lookahead is not None:
        lookahead = args.lookahead
    if args.smoothness is not None:
        smoothness = args.smoothness
    return interval, lookahead, smoothness


def stabilizer_params(args: argparse.Namespace) -> StabilizerParams:
    """StabilizerParams from the flags; ValueError naming the flag when a value is wrong."""
    weights = _path_weights(args.path_weights)
    interval, lookahead, smoothness = latency(args)
    params = StabilizerParams(
        motion=MotionParams(group=args.group, estimator=args.estimator),
        planner=PlannerParams(group=args.group, mode=args.path, smoothness=smoothness,
                              budget=BudgetParams(max_zoom=args.max_zoom,
                                                  fill=args.fill_band if args.fill_frames > 0 else 0.0,
                                                  fill_reach=max(args.fill_frames, 0)), end=args.end,
                              lowpass_sigma=args.lowpass_sigma, lookahead=lookahead,
                              path=PathParams(weights=weights),
                              keyframes=KeyframeParams(interval=interval, min_interval=max(1, min(10, interval - 1)))),
        framing=FramingParams(mode=args.framing, crop_zoom=args.crop_zoom, fill_frames=args.fill_frames,
                              max_zoom=args.max_zoom if args.max_zoom > 0 else FramingParams.max_zoom),
    )
    _flag_error("--keyframe-interval", params.planner.keyframes.validate)
    _flag_error("--lookahead/--smoothness", params.planner.validate)
    _flag_error("--max-zoom/--fill-band", params.planner.budget.validate)
    _flag_error("--lowpass-sigma", lambda: _check_lowpass(args.lowpass_sigma))
    _flag_error("--path-weights", lambda: params.planner.path.weight_vector(GROUPS[args.group].dim))
    _flag_error("--crop-zoom/--fill-frames", params.framing.validate)
    return params


def path_label(p: PlannerParams) -> str:
    """A few words naming the path settings (summaries)."""
    if p.mode == "ep":
        return f"EP path, {p.end} end-constraints"
    budget = f"max zoom {p.budget.max_zoom:g}" if p.budget.enabled else "no crop budget"
    return f"smooth path, {budget}, window {p.keyframes.interval} frames"


def stabilizer_settings(params: StabilizerParams) -> dict:
    """Every stabilizer setting as plain data (reports)."""
    return dataclasses.asdict(params)


def settings_argv(args: argparse.Namespace) -> list[str]:
    """The flags that reproduce these settings (the launcher passes them to every service)."""
    interval, lookahead, smoothness = latency(args)
    out = ["--group", args.group, "--estimator", args.estimator, "--keyframe-interval", str(interval),
           "--lookahead", str(lookahead), "--end", args.end, "--lowpass-sigma", repr(args.lowpass_sigma),
           "--path", args.path, "--max-zoom", repr(args.max_zoom), "--smoothness", repr(smoothness),
           "--framing", args.framing, "--crop-zoom", repr(args.crop_zoom)]
    if args.path_weights:
        out += ["--path-weights", args.path_weights]
    return out

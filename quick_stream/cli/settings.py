"""Stabilizer settings as CLI flags, shared by ``quick-stream stabilize`` and every service.

The offline command and the services must be given the same settings to give the same
output; one flag set and one :func:`stabilizer_params` make that hold by construction.
"""
from __future__ import annotations

import argparse
import math
from typing import Callable

from ..lie import GROUPS
from ..motion import ESTIMATORS, MotionParams
from ..path.constraints import END_MODES
from ..path.keyframes import KeyframeParams
from ..path.optimal import PathParams
from ..path.planner import PlannerParams
from ..render import FramingParams
from ..stabilizer import StabilizerParams


def add_stabilizer_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("stabilizer settings")
    g.add_argument("--group", choices=sorted(GROUPS), default="se3")
    g.add_argument("--estimator", choices=ESTIMATORS, default="exact")
    g.add_argument("--keyframe-interval", type=int, default=KeyframeParams.interval,
                   help=f"frames per path segment at most, >= 2 (default {KeyframeParams.interval})")
    g.add_argument("--end", choices=END_MODES, default="smoothed", help="end-constraint mode (default smoothed)")
    g.add_argument("--lowpass-sigma", type=float, default=PlannerParams.lowpass_sigma,
                   help="frames; the path keeps the camera velocity low-passed with this Gaussian "
                        f"(default {PlannerParams.lowpass_sigma:g}; 0 = the paper's full undo)")
    g.add_argument("--path-weights", default=None, metavar="W1,W2,...",
                   help="diagonal of the path cost's weight W, one per twist component (default identity)")
    g.add_argument("--framing", choices=("black", "crop", "auto"), default="auto")
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


def stabilizer_params(args: argparse.Namespace) -> StabilizerParams:
    """StabilizerParams from the flags; ValueError naming the flag when a value is wrong."""
    weights = _path_weights(args.path_weights)
    params = StabilizerParams(
        motion=MotionParams(group=args.group, estimator=args.estimator),
        planner=PlannerParams(group=args.group, end=args.end, lowpass_sigma=args.lowpass_sigma,
                              path=PathParams(weights=weights),
                              keyframes=KeyframeParams(interval=args.keyframe_interval,
                                                       min_interval=min(10, args.keyframe_interval - 1))),
        framing=FramingParams(mode=args.framing, crop_zoom=args.crop_zoom),
    )
    _flag_error("--keyframe-interval", params.planner.keyframes.validate)
    _flag_error("--lowpass-sigma", lambda: _check_lowpass(args.lowpass_sigma))
    _flag_error("--path-weights", lambda: params.planner.path.weight_vector(GROUPS[args.group].dim))
    _flag_error("--crop-zoom", params.framing.validate)
    return params


def settings_argv(args: argparse.Namespace) -> list[str]:
    """The flags that reproduce these settings (the launcher passes them to every service)."""
    out = ["--group", args.group, "--estimator", args.estimator, "--keyframe-interval", str(args.keyframe_interval),
           "--end", args.end, "--lowpass-sigma", repr(args.lowpass_sigma), "--framing", args.framing,
           "--crop-zoom", repr(args.crop_zoom)]
    if args.path_weights:
        out += ["--path-weights", args.path_weights]
    return out

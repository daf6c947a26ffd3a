"""Stabilizer settings from ``--settings FILE`` and CLI flags, shared by every command and service.

The offline command and the services must run with the same settings to give the same output:
one settings file (``--settings``; ``quick-stream up`` writes one and hands it to every service), one
flag set over it and one :func:`stabilizer_params` make that hold by construction. Precedence,
lowest first: the defaults (or the settings a replayed recording was made with), the file, the flags.
"""
from __future__ import annotations

import argparse
import math
import os
from typing import Callable

from ..core.lie import GROUPS
from ..core.motion import ESTIMATORS
from ..core.params import LATENCY_ALIASES, LATENCY_NAMES, LATENCY_PRESETS, USER_SETTINGS, StabilizerParams, user_defaults, with_user_settings
from ..core.path.constraints import END_MODES
from ..core.path.planner import PATH_MODES, PlannerParams
from ..core.settings import SettingsError
from .settings_file import load_settings_file


SETTINGS_ENV = "QUICK_STREAM_SETTINGS"  # the settings file when --settings is not given (a host's services)

FLAGS = USER_SETTINGS  # a flag per user-facing setting (--max-zoom for max_zoom)
FLAG_DEFAULTS = user_defaults()  # the flags' values when not given: StabilizerParams()'s


def add_stabilizer_args(p: argparse.ArgumentParser) -> None:
    """The stabilizer settings: ``--settings FILE`` (not ``--config``: that is zenoh's configuration
    file in every service, the zenoh examples' convention) and the flags that override it. A flag left out keeps
    the file's value (or the recording's, replaying one; or the default shown)."""
    d = FLAG_DEFAULTS
    g = p.add_argument_group("stabilizer settings", "A flag left out keeps the --settings file's value, else the "
                             "replayed recording's (mcap:FILE), else the default shown.")
    g.add_argument("--settings", metavar="FILE",
                   help="settings file, TOML or JSON (docs/settings.md; 'quick-stream settings show' prints every "
                        f"setting); the flags below override it (default: ${SETTINGS_ENV}, else none)")
    g.add_argument("--group", choices=sorted(GROUPS),
                   help="Lie group of the camera motion: se3 rigid, sim3 + scale, sa3 + per-axis scale, "
                        f"ga3 general affine (default {d['group']})")
    g.add_argument("--estimator", choices=ESTIMATORS,
                   help="motion estimator: exact = robust fit of the group element, induced = the paper's mean "
                        f"of induced twists (default {d['estimator']})")
    g.add_argument("--latency", choices=LATENCY_NAMES, metavar="{%s}" % ",".join(LATENCY_PRESETS),
                   help="path latency preset, named by the delay it gives at 30 fps (the window is in frames): "
                        + "; ".join(f"{name} = keyframe interval {i}, look-ahead {la}, smoothness {sm:g}"
                                    for name, (i, la, sm) in LATENCY_PRESETS.items())
                        + " (" + ", ".join(f"{a} = {n}" for a, n in LATENCY_ALIASES.items())
                        + f"); --keyframe-interval/--lookahead/--smoothness override it (default {d['latency']})")
    g.add_argument("--keyframe-interval", type=int,
                   help="frames per path window (the longest a frame waits for its correction), >= 2 "
                        "(default from --latency)")
    g.add_argument("--lookahead", type=int,
                   help="smooth path: of each window's frames, the last this many are re-planned with the next "
                        "window before release, < the interval (default from --latency)")
    g.add_argument("--end", choices=END_MODES,
                   help=f"--path ep: end-constraint mode (default {d['end']})")
    g.add_argument("--lowpass-sigma", type=float,
                   help="--path ep: frames; the path keeps the camera velocity low-passed with this Gaussian "
                        f"(default {d['lowpass_sigma']:g}; 0 = the paper's full undo)")
    g.add_argument("--path-weights", metavar="W1,W2,...",
                   help="--path ep: diagonal of the path cost's weight W, one per twist component (default identity)")
    g.add_argument("--path", choices=PATH_MODES,
                   help="smooth: smoothed path with a crop budget; ep: the Euler-Poincare path with "
                        f"--end/--lowpass-sigma targets (default {d['path']})")
    g.add_argument("--smoothness", type=float,
                   help="smooth path: weight of the path's acceleration against its distance from the camera, "
                        "lambda of docs/method.md (8) (default from --latency)")
    g.add_argument("--max-zoom", type=float,
                   help="smooth path: every frame border-free at a zoom <= this, at most 100 (0 = no budget; "
                        f"default {d['max_zoom']:g})")
    g.add_argument("--fill-frames", type=int,
                   help="border fill: output pixels a frame leaves uncovered are taken from up to this many "
                        f"neighbouring frames on each side (0 = no fill; default {d['fill_frames']})")
    g.add_argument("--framing", choices=("black", "crop", "auto"),
                   help="what the output shows past the frame's edge: black = nothing, crop = a fixed "
                        f"--crop-zoom, auto = the planned zoom (default {d['framing']})")
    g.add_argument("--fill-band", type=float,
                   help="border fill: share of half the short side the smooth path may leave uncovered for the "
                        f"fill (0 = the crop alone removes every border; default {d['fill_band']:g})")
    g.add_argument("--max-tilt", type=float, metavar="DEG",
                   help="smooth path: the virtual camera's optical axis turns at most about this far from the real "
                        "one's (a keystone the eye reads as distortion); the rest of a larger turn is an image shift "
                        f"(docs/method.md 4.5; 0 = no cap; default {d['max_tilt']:g})")
    g.add_argument("--crop-zoom", type=float,
                   help=f"zoom for --framing crop, 1-100 (default {d['crop_zoom']:g})")


def given_flags(args: argparse.Namespace) -> dict[str, object]:
    """The stabilizer flags given on the command line (name -> value)."""
    return {k: getattr(args, k) for k in FLAGS if getattr(args, k, None) is not None}


def _flag_error(flag: str, check: Callable[[], object]) -> None:
    """Run ``check``; its ValueError comes back prefixed with the flag at fault."""
    try:
        check()
    except ValueError as e:
        raise ValueError(f"{flag}: {e}") from None


def _path_weights(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(w) for w in text.split(","))
    except ValueError:
        raise ValueError(f"--path-weights: expected comma-separated numbers, got {text!r}") from None


def apply_flags(params: StabilizerParams, flags: dict[str, object]) -> StabilizerParams:
    """``params`` with the given flags' settings (``flags``: :func:`given_flags`; the couplings are
    :func:`~quick_stream.core.params.with_user_settings`'); ``--path-weights`` as typed."""
    if isinstance(flags.get("path_weights"), str):
        flags = {**flags, "path_weights": _path_weights(str(flags["path_weights"]))}
    return with_user_settings(params, flags)


def default_settings() -> StabilizerParams:
    """The product's defaults: what ``quick-stream stabilize`` runs with no flags, ``StabilizerParams()``."""
    return StabilizerParams()


def stabilizer_params(args: argparse.Namespace, recorded: StabilizerParams | None = None) -> StabilizerParams:
    """The settings: ``recorded`` (a recording's, replaying one) or the defaults, then ``--settings FILE``
    (else ``$QUICK_STREAM_SETTINGS``),
    then the flags given; ValueError naming the file and key, or the flag, when a value is wrong."""
    params = recorded if recorded is not None else default_settings()
    path = getattr(args, "settings", None) or os.environ.get(SETTINGS_ENV)
    if path:
        try:
            params = load_settings_file(path, params)
        except SettingsError as e:
            raise SettingsError(f"${SETTINGS_ENV}={e}" if not getattr(args, "settings", None) else str(e)) from None
    flags = given_flags(args)
    if not flags:
        return params
    if "lowpass_sigma" in flags and not (math.isfinite(flags["lowpass_sigma"]) and flags["lowpass_sigma"] >= 0):
        raise ValueError(f"--lowpass-sigma: must be a finite number >= 0 (frames), got {flags['lowpass_sigma']!r}")
    params = apply_flags(params, flags)
    _flag_error("--group/--estimator", params.motion.validate)
    _flag_error("--keyframe-interval", params.planner.keyframes.validate)
    _flag_error("--max-zoom/--fill-band", params.planner.budget.validate)  # before the planner's, which checks it too
    _flag_error("--max-tilt", params.planner.validate_tilt)
    _flag_error("--lookahead/--smoothness", params.planner.validate)
    _flag_error("--path-weights", lambda: params.planner.path.weight_vector(GROUPS[params.planner.group].dim))
    _flag_error("--crop-zoom/--fill-frames", params.framing.validate)
    return params  # the rest (flow, continuity, warp, one group) is the base's, checked when it was made


def path_label(p: PlannerParams) -> str:
    """A few words naming the path settings (summaries)."""
    if p.mode == "ep":
        return f"EP path, {p.end} end-constraints"
    budget = f"max zoom {p.budget.max_zoom:g}" if p.budget.enabled else "no crop budget"
    return f"smooth path, {budget}, window {p.keyframes.interval} frames"

"""The product's settings in one place: the stabilizer's parameter tree with the product's defaults,
the latency presets, and how one user-facing setting sets several parameters.

Each algorithm describes its own parameters next to its code (``SceneFlowParams``, ``MotionParams``,
``PlannerParams``, ``WarpParams``, ``FramingParams``, ...); their defaults are the algorithm's own
(the motion estimator's free fit, the renderer's black framing). :class:`StabilizerParams` composes
them with the product's choices, so ``Stabilizer()`` is ``quick-stream stabilize`` with no flags,
and :func:`with_user_settings` applies the user-facing settings (the flags and a settings file's
short names: ``--max-zoom`` sets the crop budget and the framing's bound, ``--latency`` the window,
look-ahead and smoothness). This module imports parameter classes only, no stage.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Mapping

from .continuity import ContinuityParams
from .motion import MotionParams
from .path.budget import BudgetParams
from .path.keyframes import KeyframeParams
from .path.planner import PlannerParams
from .render.framing import FramingParams
from .render.warp import WarpParams
from .sceneflow import SceneFlowParams

__all__ = ["StabilizerParams", "LATENCY_PRESETS", "LATENCY_ALIASES", "LATENCY_NAMES", "USER_SETTINGS", "STABILIZER_TRANSLATION_PRIOR_MM",
           "check_groups", "latency_preset", "window_settings", "stabilizer_motion_params", "stabilizer_framing_params", "user_defaults", "with_user_settings"]


STABILIZER_TRANSLATION_PRIOR_MM = 0.2  # the stabilizer's fit takes hand-held jitter as rotation (docs/method.md (3n))


def stabilizer_motion_params() -> MotionParams:
    """The motion estimator as the stabilizer runs it: the exact fit with the translation prior (3n). The
    estimator's own default is the free fit, which recovers any motion of its group."""
    return MotionParams(translation_prior_mm=STABILIZER_TRANSLATION_PRIOR_MM)


def stabilizer_framing_params() -> FramingParams:
    """The framing as the stabilizer runs it: the planned zoom (``auto``), bounded by the crop budget's
    zoom (docs/method.md 4.3). The renderer's own default shows black past the frame's edge."""
    return FramingParams(mode="auto", max_zoom=BudgetParams.max_zoom)


def check_groups(motion: MotionParams, planner: PlannerParams) -> None:
    """The motion's and the path's Lie group must be one: ValueError naming both otherwise."""
    if planner.group != motion.group:
        raise ValueError(f"motion group {motion.group!r} and path group {planner.group!r} differ")


@dataclass
class StabilizerParams:
    """Every parameter of the stabilizer, with the product's defaults (``quick-stream stabilize``'s)."""

    flow: SceneFlowParams = field(default_factory=SceneFlowParams)
    continuity: ContinuityParams = field(default_factory=ContinuityParams)
    motion: MotionParams = field(default_factory=stabilizer_motion_params)
    planner: PlannerParams = field(default_factory=PlannerParams)
    warp: WarpParams = field(default_factory=WarpParams)
    framing: FramingParams = field(default_factory=stabilizer_framing_params)

    def __post_init__(self) -> None:
        check_groups(self.motion, self.planner)


# latency presets, named by the delay they give at 30 fps: (keyframe interval, look-ahead, smoothness).
# The interval is the longest wait (frames) a frame has before its correction is released (docs/method.md
# 4.3), so the delay is fixed in frames: at 60 fps "1s" waits 0.5 s. A shorter window sees less of the
# future: it re-plans a larger share and smooths less (lambda falls about as the window cubed), as
# measured on real and known-shake clips (docs/method.md 4.3). "normal" and "low" are the earlier
# names of "1s" and "0.5s".
LATENCY_PRESETS: dict[str, tuple[int, int, float]] = {
    "1s": (KeyframeParams.interval, PlannerParams.lookahead, PlannerParams.smoothness),
    "0.5s": (15, 10, 3000.0),
    "0.33s": (10, 7, 300.0),
    "0.2s": (6, 5, 100.0),
    "0.1s": (3, 2, 10.0)}
LATENCY_ALIASES = {"normal": "1s", "low": "0.5s"}
LATENCY_NAMES = (*LATENCY_PRESETS, *LATENCY_ALIASES)  # what --latency accepts


def latency_preset(name: str) -> tuple[int, int, float]:
    """The preset ``name`` (a name of :data:`LATENCY_PRESETS` or an alias): (interval, look-ahead, smoothness)."""
    key = LATENCY_ALIASES.get(name, name)
    if key not in LATENCY_PRESETS:
        raise ValueError(f"unknown latency preset {name!r}; known: {list(LATENCY_NAMES)}")
    return LATENCY_PRESETS[key]


# the user-facing settings (a flag each: --max-zoom for max_zoom), in the order they are applied
USER_SETTINGS = ("group", "estimator", "latency", "keyframe_interval", "lookahead", "end", "lowpass_sigma",
                 "path_weights", "path", "max_zoom", "smoothness", "fill_frames", "fill_band", "max_tilt", "framing", "crop_zoom")


def user_defaults() -> dict[str, object]:
    """The user-facing settings' values in :class:`StabilizerParams` (those with a default of their own:
    the window's settings come from ``latency``, the path weights are the identity)."""
    p = StabilizerParams()
    return {"group": p.motion.group, "estimator": p.motion.estimator, "latency": "1s", "end": p.planner.end,
            "lowpass_sigma": p.planner.lowpass_sigma, "path": p.planner.mode, "max_zoom": p.planner.budget.max_zoom,
            "fill_frames": p.framing.fill_frames, "fill_band": p.planner.budget.fill, "max_tilt": p.planner.max_tilt_deg,
            "framing": p.framing.mode,
            "crop_zoom": p.framing.crop_zoom}


def _min_interval(interval: int) -> int:
    return max(1, min(10, interval - 1))


def window_settings(interval: int) -> tuple[int, float]:
    """(look-ahead, smoothness) for a window of ``interval`` frames given alone, from the presets'
    windows: between two presets, the smoothness interpolated on log-log scales and the share of the
    window re-planned linearly in the log of the window; beyond them, the nearest preset's share and
    its smoothness scaled with the window cubed (docs/method.md (9): the cut-off goes as
    lambda^(-1/4)). A preset's own window gives the preset; the look-ahead is at most ``interval`` - 1."""
    pts = sorted(LATENCY_PRESETS.values())
    n = max(int(interval), 1)
    lo = max((p for p in pts if p[0] <= n), default=pts[0])
    hi = min((p for p in pts if p[0] >= n), default=pts[-1])
    if lo[0] == hi[0]:  # a preset's window, or beyond the presets
        share, lam = lo[1] / lo[0], lo[2] * (n / lo[0]) ** 3
    else:
        t = math.log(n / lo[0]) / math.log(hi[0] / lo[0])
        share = (1 - t) * lo[1] / lo[0] + t * hi[1] / hi[0]
        lam = math.exp((1 - t) * math.log(lo[2]) + t * math.log(hi[2]))
    return max(0, min(n - 1, int(round(share * n)))), lam


def with_user_settings(params: StabilizerParams, given: Mapping[str, object]) -> StabilizerParams:
    """``params`` with the user-facing settings ``given`` (names of :data:`USER_SETTINGS`; ``path_weights`` a
    sequence of numbers). One setting may set several fields: ``group`` the motion's and the path's,
    ``max_zoom`` the crop budget's and the framing's, ``latency`` the window, look-ahead and smoothness, a
    ``keyframe_interval`` the look-ahead and smoothness that go with it (:func:`window_settings`; a
    ``lookahead`` or ``smoothness`` given wins). Values are not checked here: each
    part's ``validate`` does that."""
    f = given
    unknown = set(f) - set(USER_SETTINGS)
    if unknown:
        raise ValueError(f"unknown settings {sorted(unknown)}; known: {list(USER_SETTINGS)}")
    motion, planner, framing = params.motion, params.planner, params.framing
    kf, budget, path = planner.keyframes, planner.budget, planner.path
    if "group" in f:
        motion, planner = replace(motion, group=f["group"]), replace(planner, group=f["group"])
    if "estimator" in f:
        motion = replace(motion, estimator=f["estimator"])
    if "latency" in f:
        interval, lookahead, smoothness = latency_preset(str(f["latency"]))
        kf = replace(kf, interval=interval, min_interval=_min_interval(interval))
        planner = replace(planner, lookahead=lookahead, smoothness=smoothness)
    if "keyframe_interval" in f:
        interval = int(f["keyframe_interval"])  # type: ignore[call-overload]
        if interval > 0:  # the look-ahead and smoothness that go with the window (unless given)
            lookahead, smoothness = window_settings(interval)
            planner = replace(planner, lookahead=lookahead, smoothness=smoothness)
        kf = replace(kf, interval=interval, min_interval=_min_interval(interval))
    for name, fld in (("lookahead", "lookahead"), ("smoothness", "smoothness"), ("end", "end"),
                      ("lowpass_sigma", "lowpass_sigma"), ("path", "mode")):
        if name in f:
            planner = replace(planner, **{fld: f[name]})
    if "path_weights" in f:
        path = replace(path, weights=tuple(float(w) for w in f["path_weights"]))  # type: ignore[attr-defined]
    if "max_zoom" in f:
        z = float(f["max_zoom"])  # type: ignore[arg-type]
        budget = replace(budget, max_zoom=z)
        framing = replace(framing, max_zoom=z if z > 0 else FramingParams.max_zoom)
    if "fill_frames" in f:
        n = int(f["fill_frames"])  # type: ignore[call-overload]
        fill = 0.0 if n <= 0 else (budget.fill or BudgetParams.fill)
        framing, budget = replace(framing, fill_frames=n), replace(budget, fill=fill, fill_reach=max(n, 0))
    if "fill_band" in f:
        budget = replace(budget, fill=float(f["fill_band"]) if framing.fill_frames > 0 else 0.0)  # type: ignore[arg-type]
    if "max_tilt" in f:
        planner = replace(planner, max_tilt_deg=float(f["max_tilt"]))  # type: ignore[arg-type]
    if "framing" in f:
        framing = replace(framing, mode=f["framing"])
    if "crop_zoom" in f:
        framing = replace(framing, crop_zoom=float(f["crop_zoom"]))  # type: ignore[arg-type]
    planner = replace(planner, keyframes=kf, budget=budget, path=path)
    return replace(params, motion=motion, planner=planner, framing=framing)

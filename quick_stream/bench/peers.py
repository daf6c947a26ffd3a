"""Python 2D stabilisers people use, run frame by frame on BGR frames: ``vidstab`` and vidgear's ``Stabilizer``.

Both are optional (``pip install 'quick-stream[peers]'``); :func:`available` says which import
here and why not. Each runner returns exactly one output frame per input frame, in input order,
plus its own wall time; both stabilisers keep their defaults.

Alignment (both hand a frame back later than they are given it; checked by feeding frames whose
index is coded in their brightness, ``tests/unit/test_bench_quality.py``):

* ``vidstab.VidStab().stabilize_frame(frame, smoothing_window=30)`` (vidstab 1.7, defaults:
  GFTT corners, LK tracks, rigid fit, trajectory averaged over 30 frames, black borders, no
  crop): the first 30 calls return all-black warm-up frames; from call 31 on, call k returns
  input frame k - 30. Its documented flush is to keep calling with ``None``; that returns
  frames up to N-2 and then ``None``: the last frame has no frame-to-frame transform after it,
  so vidstab never returns it. We feed the last frame once more (a hold: zero motion after the
  end) and then ``None`` until it returns ``None``; the warm-up frames are dropped and output k
  is paired with input k. The duplicate's own output is dropped.
* ``vidgear.gears.stabilizer.Stabilizer()`` (vidgear 0.3.6, defaults: ASW mode, smoothing
  radius 25, black borders, no crop): returns ``None`` while its 25-frame queue fills, then one
  frame per call, 24 calls behind. Its first frame is never returned (the queue drops it when
  it first fills) and it has no flush. We feed the first frame twice (the first call only
  primes it) and, after the last frame, the last frame 24 more times; the 25 leading ``None``
  are dropped and output k is paired with input k. The padding is a hold at each end (zero
  motion beyond the clip), the same extension its box filter applies inside the window.

OpenCV 5 (the project's opencv-python-headless) and vidstab: vidstab imports
``imutils.feature.factories``, which reads ``cv2.BRISK_create`` at import time (BRISK left the
main modules in OpenCV 5), and it picks ``cv2.estimateAffinePartial2D`` only when
``imutils.is_cv4()`` (true for OpenCV 4 only; otherwise it calls ``cv2.estimateRigidTransform``,
removed in OpenCV 4). :func:`import_vidstab` therefore gives ``cv2`` a placeholder
``BRISK_create`` (raising if called; the default GFTT detector never calls it) only while vidstab
is imported, and makes vidstab's rigid-fit wrapper take its OpenCV 4 branch
(``cv2.estimateAffinePartial2D(prev, cur)[0]``, identical to what it runs on OpenCV 4). Nothing
else of vidstab is changed. vidgear needs no shim (it checks the major version itself).
"""
from __future__ import annotations

import importlib.metadata
import time
from dataclasses import dataclass, field
from types import ModuleType

import cv2
import numpy as np

INSTALL_HINT = "pip install 'quick-stream[peers]'"
VIDSTAB_WINDOW = 30  # VidStab.stabilize_frame's default smoothing_window
VIDGEAR_RADIUS = 25  # vidgear Stabilizer's default smoothing_radius


@dataclass
class PeerRun:
    """Outputs aligned with the inputs (``frames[i]`` is the stabilised input i) and timings."""

    frames: list[np.ndarray]
    seconds: float
    calls: int
    notes: list[str] = field(default_factory=list)


def version(dist: str) -> str | None:
    """Installed version of a distribution, or None."""
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return None


def _brisk_placeholder(*_args: object, **_kwargs: object) -> None:
    raise AttributeError("BRISK is not in OpenCV >= 5's main modules (vidstab's default GFTT does not need it)")


def _rigid_fit_cv4(from_pts: np.ndarray, to_pts: np.ndarray, full: bool = False) -> np.ndarray | None:
    """vidstab's ``cv2_estimateRigidTransform``, OpenCV 4 branch."""
    if not from_pts.shape[0] or not to_pts.shape[0]:
        return None
    return cv2.estimateAffinePartial2D(from_pts, to_pts)[0]


def import_vidstab() -> ModuleType:
    """``vidstab`` made to run on OpenCV 5 (module docstring); ImportError when it is not installed."""
    added = not hasattr(cv2, "BRISK_create")
    if added:
        cv2.BRISK_create = _brisk_placeholder
    try:
        import vidstab
        import vidstab.vidstab_utils as vu
    finally:
        if added:
            del cv2.BRISK_create
    if not hasattr(cv2, "estimateRigidTransform"):
        vu.cv2_estimateRigidTransform = _rigid_fit_cv4
    return vidstab


def import_vidgear_stabilizer() -> type:
    """vidgear's ``Stabilizer`` factory; ImportError when vidgear is not installed."""
    from vidgear.gears.stabilizer import Stabilizer

    return Stabilizer


def available() -> dict[str, str]:
    """Peer name -> "" when it imports, else why not (with the install command)."""
    out = {}
    for name, imp in (("vidstab", import_vidstab), ("vidgear", import_vidgear_stabilizer)):
        try:
            imp()
            out[name] = ""
        except ImportError as e:
            out[name] = f"not installed ({e}); install with: {INSTALL_HINT}"
        except Exception as e:  # noqa: BLE001 - a broken install is reported, not fatal
            out[name] = f"cannot be imported: {type(e).__name__}: {e}"
    return out


def run_vidstab(frames: list[np.ndarray], window: int = VIDSTAB_WINDOW) -> PeerRun:
    """``VidStab().stabilize_frame`` on every frame with its defaults, aligned (module docstring)."""
    if not frames:
        return PeerRun([], 0.0, 0)
    VidStab = import_vidstab().VidStab
    n = len(frames)
    if n < window:
        raise ValueError(f"clip of {n} frames is shorter than vidstab's smoothing window ({window}): "
                         "it would return only warm-up frames")
    t0 = time.perf_counter()
    stab = VidStab()
    raw: list[np.ndarray] = []
    calls = 0
    for f in [*frames, frames[-1]]:
        calls += 1
        raw.append(stab.stabilize_frame(input_frame=f, smoothing_window=window))
    while True:
        calls += 1
        o = stab.stabilize_frame(input_frame=None, smoothing_window=window)
        if o is None:
            break
        raw.append(o)
        if calls > n + 3 * window + 10:
            raise RuntimeError("vidstab kept returning frames after the end of the clip")
    seconds = time.perf_counter() - t0
    out = raw[window:window + n]
    if len(out) != n:
        raise RuntimeError(f"vidstab returned {len(raw) - window} frames after its {window}-frame warm-up, "
                           f"expected at least {n}")
    return PeerRun([np.ascontiguousarray(o[:, :, :3]) for o in out], seconds, calls,
                   [f"first {window} outputs (black warm-up) dropped; last frame fed twice, then None until "
                    "it returned None"])


def run_vidgear(frames: list[np.ndarray], radius: int = VIDGEAR_RADIUS) -> PeerRun:
    """vidgear ``Stabilizer(smoothing_radius=radius)`` (ASW) on every frame, its other settings the defaults,
    aligned (module docstring; ``radius`` 25 is its default)."""
    if not frames:
        return PeerRun([], 0.0, 0)
    Stabilizer = import_vidgear_stabilizer()
    n = len(frames)
    t0 = time.perf_counter()
    stab = Stabilizer(smoothing_radius=radius)
    out: list[np.ndarray] = []
    fed = [frames[0], *frames, *([frames[-1]] * (radius - 1))]
    for f in fed:
        o = stab.stabilize(f)
        if o is not None:
            out.append(o)
    seconds = time.perf_counter() - t0
    if len(out) != n:
        raise RuntimeError(f"vidgear returned {len(out)} frames for {len(fed)} calls, expected {n}")
    return PeerRun(out, seconds, len(fed),
                   [f"first frame fed twice, last frame {radius - 1} more times; "
                    f"{radius} leading None dropped"])

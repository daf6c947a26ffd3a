"""What the OAK source asks of a camera: the typed options of a ``depthai`` spec (size, rate, pairing,
retries and the stereo depth settings, :class:`StereoSettings`), the small interface every backend
provides (:class:`CameraBackend`: the real device, :mod:`~quick_stream.io.sources.oak_device`, or the
scripted stand-in, :mod:`~quick_stream.io.sources.stand_in.oak_fake`) and the errors a backend raises. Apart from
:mod:`~quick_stream.io.sources.oak` (the source itself), so the backends need nothing of the source.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Protocol

EXTRA_HINT = "install the depthai extra: pip install 'quick-stream[depthai]'"


class DeviceGone(RuntimeError):
    """The camera disconnected (or stopped answering) while streaming."""


class NoDevice(RuntimeError):
    """No camera found, or not the one asked for."""


class CameraBackend(Protocol):
    """The small interface every OAK backend provides (real device or fake)."""

    device_id: str

    def open(self) -> None: ...

    def read(self, timeout_s: float) -> tuple[list[Any], list[Any]]: ...  # (colour msgs, depth msgs)

    def close(self) -> None: ...


MAX_SIZE = 8192  # pixels per side

# option: (type, default, lowest, highest or None)
_OPTIONS: dict[str, tuple[type, Any, float, float | None]] = {
    "width": (int, 640, 16, MAX_SIZE), "height": (int, 400, 16, MAX_SIZE), "fps": (float, 30.0, 0.1, 1000.0),
    "tolerance_ms": (float, 10.0, 0.0, None), "retries": (int, 5, 0, None), "frames": (int, None, 1, None),
}

# depthai v3's StereoDepth.PresetMode names (3.12 has all of them; older 3.x lack DENSITY and ACCURACY,
# which the device backend then names); spelled in lower case in a spec
PRESETS = ("fast_accuracy", "fast_density", "default", "face", "high_detail", "robotics", "density", "accuracy")


@dataclass(frozen=True)
class StereoSettings:
    """The StereoDepth settings of a real OAK (spec options of the same names; docs/usage.md,
    "Live OAK (depthai) cameras", has the table). Stereo depth noise is sigma_z = k z^2 with k = sigma_d / (f B);
    at 640x400 on an OAK-D f = 441 px and B = 7.5 cm, so f B = 33 px m. Measured with the degrade
    tool's depth noise (its ``--stereo-k`` K) on a known-shake 7-Scenes clip: K = 0.003, 0.006 and
    0.012 left the stabilizer as on clean depth (shake removed 96.2-96.3 %, output jitter
    0.063-0.073 deg against 0.068, no uncorrected frame); K = 0.024 raised the jitter to 0.079 deg.

    * ``subpixel`` (3): fractional disparity bits, 0 = integer disparity, 3, 4 or 5. Integer
      disparity leaves sigma_d = 0.3-0.5 px, k = 0.009-0.015, around the last level measured
      lossless; 3 bits quantise to 1/8 px (0.036 px RMS), under the matching noise (Luxonis's
      accuracy figure, below 1 % at 0.7-4 m, bounds it at 0.17 px), so k = 0.003-0.005. 4 and 5
      bits add nothing above that noise and lose the median filter (depthai runs it with 3 bits
      only), so they need ``median=0``;
    * ``lr_check`` (1): occluded pixels come out invalid instead of with a wrong depth that the
      scene flow's masks would have to catch;
    * ``confidence`` (55): 0-255; depthai v3 keeps disparities whose confidence is above it
      (higher keeps fewer, surer ones). 55 is depthai's FAST_ACCURACY value (FAST_DENSITY: 15):
      an invalid pixel is dropped for free, a wrong one has to be rejected as an outlier;
    * ``median`` (7): median kernel 0 (off), 3, 5 or 7, in the stereo hardware (no added latency);
      7x7 removes the most per-pixel disparity noise;
    * ``spatial``, ``speckle`` (0): post-processing on the device's SHAVE cores (latency every
      frame) against noise the stabilizer already tolerates at 3-4 times the subpixel level;
      spatial hole filling also invents depth;
    * ``temporal`` (0): averages depth across frames, which smears it under fast motion, and the
      scene flow compares depth across frames;
    * ``extended`` (0): a 0-190 px disparity search halves the minimum depth (f B / 95 = 0.35 m at
      400P); depthai's docstring calls it incompatible with subpixel, its HIGH_DETAIL preset
      combines the two;
    * ``preset`` (``fast_accuracy``): the depthai preset applied first; the settings above are set
      on top of it, so a preset only adds what they leave alone (left-right check threshold, cost
      aggregation, threshold filter). ``fast_accuracy`` turns on no post-processing.

    The decimation filter stays 1 (depth keeps the colour's size) and depth is in millimetres.
    """

    preset: str = "fast_accuracy"
    subpixel: int = 3
    lr_check: bool = True
    confidence: int = 55
    median: int = 7
    spatial: bool = False
    temporal: bool = False
    speckle: bool = False
    extended: bool = False


_STEREO_CHOICES: dict[str, tuple[int, ...]] = {"subpixel": (0, 3, 4, 5), "median": (0, 3, 5, 7)}
_FLAGS = ("lr_check", "spatial", "temporal", "speckle", "extended")
_TRUE, _FALSE = ("1", "true", "on", "yes"), ("0", "false", "off", "no")


def _option(options: dict[str, str], key: str) -> Any:
    kind, default, lo, hi = _OPTIONS[key]
    raw = options.get(key)
    if raw is None:
        return default
    what = f"{'an integer' if kind is int else 'a finite number'} " + (f"in [{lo:g}, {hi:g}]" if hi else f">= {lo:g}")
    try:
        value = kind(raw)
    except ValueError:
        raise ValueError(f"depthai source option {key}={raw!r} must be {what}") from None
    if not (math.isfinite(value) and value >= lo and (hi is None or value <= hi)):
        raise ValueError(f"depthai source option {key}={raw!r} must be {what}")
    return value


def stereo_settings(options: dict[str, str]) -> StereoSettings:
    """The :class:`StereoSettings` of a spec's options (defaults for those not given); ValueError
    naming a bad value or a combination depthai cannot run."""
    got: dict[str, Any] = {}
    if "preset" in options:
        preset = options["preset"].strip().lower()
        if preset not in PRESETS:
            raise ValueError(f"depthai source option preset={options['preset']!r} must be one of {', '.join(PRESETS)}")
        got["preset"] = preset
    for key in _FLAGS:
        if key in options:
            raw = options[key].strip().lower()
            if raw not in _TRUE + _FALSE:
                raise ValueError(f"depthai source option {key}={options[key]!r} must be 1 or 0 (on/off, true/false)")
            got[key] = raw in _TRUE
    for key, allowed in _STEREO_CHOICES.items():
        if key in options:
            raw = options[key].strip().lower()
            value = 0 if raw == "off" else int(raw) if raw.isdigit() else None
            if value not in allowed:
                raise ValueError(f"depthai source option {key}={options[key]!r} must be one of "
                                 f"{', '.join(map(str, allowed))} (0 = off)")
            got[key] = value
    if "confidence" in options:
        raw = options["confidence"].strip()
        if not (raw.isdigit() and int(raw) <= 255):  # depthai would wrap 300 to 44 without a word
            raise ValueError(f"depthai source option confidence={raw!r} must be an integer in [0, 255]")
        got["confidence"] = int(raw)
    s = replace(StereoSettings(), **got)
    if s.median and s.subpixel not in (0, 3):
        raise ValueError(f"depthai source: median={s.median} runs only with subpixel=3 or subpixel=0 "
                         f"(depthai's median filter supports 3 fractional bits), got subpixel={s.subpixel}; "
                         "add median=0 for 4 or 5 bits")
    return s


def oak_settings(options: dict[str, str]) -> dict[str, Any]:
    """The typed options of a ``depthai`` spec (defaults filled in; the stereo ones as a
    :class:`StereoSettings` under ``stereo``); ValueError naming a bad one.
    Opens nothing: a launcher checks a spec with it before a capture process opens the camera."""
    stereo_keys = set(StereoSettings.__dataclass_fields__)
    known = set(_OPTIONS) | stereo_keys | {"fake"}
    unknown = set(options) - known
    if unknown:
        raise ValueError(f"depthai source: unknown option(s) {', '.join(sorted(unknown))} "
                         f"(known: {', '.join(sorted(known))})")
    out = {key: _option(options, key) for key in _OPTIONS}
    out["stereo"] = stereo_settings(options)
    return out

"""The embedded default source: a rendered RGB-D walk through a textured room, with ground truth.

``SyntheticSource`` needs no data. Each frame is rendered on demand (see
:mod:`quick_stream.io.sources.scene`) from a deterministic, seeded camera path: a slow
intended dolly and pan plus hand-held shake, band-limited noise (sums of 1-12 Hz
sinusoids with random phases) on rotation about all three axes - roll included -
and on translation, scaled by ``shake``. An optional zoom varies the focal length;
frames carry the true per-frame intrinsics, or with ``report_zoom=False`` the
nominal ones (a camera that zooms without telling). Poses are camera-to-world,
OpenCV convention (x right, y down, z forward), world = the nominal camera frame.

Spec: ``synthetic:seed=3,frames=100,width=320,height=240,zoom=0.05`` (see
:meth:`SyntheticSource.from_spec`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterator, Mapping

import numpy as np

from ...core.frame import Intrinsics, RGBDFrame, dequantize_depth, quantize_depth
from ...core.lie import so3
from .scene import Renderer, build_scene

# Intended path (m, deg, s) and shake (rms per axis at shake=1) parameters.
PATH_CENTRE = np.array([0.0, 0.0, -0.15])
PATH_AMPLITUDE = np.array([0.15, 0.04, 0.14])  # m: dolly/truck, <= ~6 cm/s
PAN_DEG, TILT_DEG = 4.0, 2.0  # slow pan/tilt amplitude, <= ~1.7 deg/s
SHAKE_ROT_RMS_DEG = 0.4  # per axis (x, y, z = roll); peaks ~1 deg
SHAKE_TRANS_RMS_M = 0.004  # per axis; peaks ~1 cm
SHAKE_ROT_BAND = (1.0, 12.0)  # Hz
SHAKE_TRANS_BAND = (0.8, 8.0)
MAX_SHAKE = 5.0
MAX_SIZE = 8192  # pixels per side
_CHUNK = 1024  # frames whose poses are computed together


@dataclass(frozen=True)
class _Sines:
    """Band-limited noise: per channel a sum of sinusoids (channels x components)."""

    freq: np.ndarray
    amp: np.ndarray
    phase: np.ndarray

    @classmethod
    def make(cls, rng, channels: int, n: int, band: tuple[float, float], rms: float) -> "_Sines":
        freq = np.exp(rng.uniform(np.log(band[0]), np.log(band[1]), (channels, n)))
        amp = rng.uniform(0.5, 1.0, (channels, n)) / freq  # ~1/f: roughly flat velocity spectrum
        amp *= rms / np.sqrt((amp ** 2).sum(axis=1, keepdims=True) / 2)
        return cls(freq, amp, rng.uniform(0, 2 * np.pi, (channels, n)))

    def __call__(self, t: np.ndarray) -> np.ndarray:  # (N,) -> (N, channels)
        arg = 2 * np.pi * t[:, None, None] * self.freq + self.phase
        return (self.amp * np.sin(arg)).sum(axis=2)


class CameraPath:
    """Deterministic camera motion for one seed: poses and focal scale as functions of time."""

    def __init__(self, seed: int, shake: float = 1.0, zoom: float = 0.0):
        rng = np.random.default_rng([seed, 0xCA3E4A])
        self.shake, self.zoom = shake, zoom
        self.pos_period = rng.uniform(16, 28, 3)
        self.pos_phase = rng.uniform(0, 2 * np.pi, 3)
        self.ang_period = rng.uniform(14, 24, 2)
        self.ang_phase = rng.uniform(0, 2 * np.pi, 2)
        self.rot = _Sines.make(rng, 3, 7, SHAKE_ROT_BAND, math.radians(SHAKE_ROT_RMS_DEG))
        self.trans = _Sines.make(rng, 3, 6, SHAKE_TRANS_BAND, SHAKE_TRANS_RMS_M)
        self.zoom_period, self.zoom_phase = rng.uniform(5, 9), rng.uniform(0, 2 * np.pi)
        self.zoom_jitter = _Sines.make(rng, 1, 3, (1.0, 5.0), 0.03)

    @staticmethod
    def bounds(shake: float) -> tuple[np.ndarray, np.ndarray]:
        """A box that contains every camera centre for this shake level."""
        r = PATH_AMPLITUDE + 3.5 * shake * SHAKE_TRANS_RMS_M
        return PATH_CENTRE - r, PATH_CENTRE + r

    def poses(self, t: np.ndarray) -> np.ndarray:
        """Camera-to-world poses (N, 4, 4) at times t (s)."""
        t = np.asarray(t, float)
        tc = 2 * np.pi * t[:, None]
        pos = PATH_CENTRE + PATH_AMPLITUDE * np.sin(tc / self.pos_period + self.pos_phase)
        ang = np.radians([PAN_DEG, TILT_DEG]) * np.sin(tc / self.ang_period + self.ang_phase)
        zero = np.zeros(len(t))
        # intended orientation: pan (yaw about y) then tilt (pitch about x), no roll
        r_int = so3.exp(np.column_stack([zero, ang[:, 0], zero])) @ \
            so3.exp(np.column_stack([ang[:, 1], zero, zero]))
        r_shake = so3.exp(self.shake * self.rot(t))  # about the camera's own x, y, z axes
        out = np.zeros((len(t), 4, 4))
        out[:, :3, :3] = r_int @ r_shake
        out[:, :3, 3] = pos + (r_int @ (self.shake * self.trans(t))[:, :, None])[:, :, 0]
        out[:, 3, 3] = 1.0
        return out

    def focal_scale(self, t: np.ndarray) -> np.ndarray:
        """f(t) / f0 = 1 + zoom * (smooth 0..1 zoom-in signal + small jitter)."""
        t = np.asarray(t, float)
        smooth = 0.5 - 0.5 * np.cos(2 * np.pi * t / self.zoom_period + self.zoom_phase)
        return 1.0 + self.zoom * (smooth + self.zoom_jitter(t)[:, 0])

    def min_focal_scale(self) -> float:
        """A lower bound of focal_scale over all times."""
        return 1.0 - self.zoom * float(np.abs(self.zoom_jitter.amp).sum())


def _parse_bool(raw: str) -> bool:
    s = raw.strip().lower()
    if s in ("1", "true", "yes", "on"):
        return True
    if s in ("0", "false", "no", "off"):
        return False
    raise ValueError("not a boolean (use true/false, 1/0, yes/no, on/off)")


_SPEC_TYPES = {"width": int, "height": int, "frames": int, "seed": int, "fps": float,
               "shake": float, "zoom": float, "report_zoom": _parse_bool, "hfov_deg": float}
_SPEC_ALIASES = {"hfov": "hfov_deg", "n": "frames"}


class SyntheticSource:
    """Rendered RGB-D frames of a textured room seen by a shaky, optionally zooming camera."""

    name = "synthetic"
    has_ground_truth = True
    depth_scale = 1000.0  # depth is delivered in whole millimetres

    def __init__(self, width: int = 640, height: int = 480, fps: float = 30.0, frames: int = 300,
                 seed: int = 0, shake: float = 1.0, zoom: float = 0.0, report_zoom: bool = True,
                 hfov_deg: float = 60.0):
        def check(name, ok, what, value):
            if not ok:
                raise ValueError(f"synthetic source: {name} must be {what}, got {value!r}")

        for name, v, lo in (("width", width, 16), ("height", height, 16), ("frames", frames, 1),
                            ("seed", seed, 0)):
            check(name, isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= lo,
                  f"an integer >= {lo}", v)
        for name, v, lo, hi in (("fps", fps, 1e-3, 1e4), ("shake", shake, 0.0, MAX_SHAKE),
                                ("zoom", zoom, 0.0, 1.0), ("hfov_deg", hfov_deg, 20.0, 80.0)):
            ok = isinstance(v, (int, float, np.number)) and not isinstance(v, bool)
            check(name, ok and math.isfinite(v) and lo <= v <= hi, f"a number in [{lo:g}, {hi:g}]", v)
        check("height", height <= 2 * width, "at most twice the width", height)
        for name, v in (("width", width), ("height", height)):  # beyond 8K the renderer's buffers run out of memory
            check(name, v <= MAX_SIZE, f"at most {MAX_SIZE}", v)
        self.width, self.height, self.fps, self.frames = int(width), int(height), float(fps), int(frames)
        self.seed, self.shake, self.zoom = int(seed), float(shake), float(zoom)
        self.report_zoom, self.hfov_deg = bool(report_zoom), float(hfov_deg)

        f0 = (self.width / 2) / math.tan(math.radians(self.hfov_deg) / 2)
        self.intrinsics = Intrinsics(f0, f0, (self.width - 1) / 2, (self.height - 1) / 2,
                                     self.width, self.height)
        self.path = CameraPath(self.seed, self.shake, self.zoom)
        self._chunks: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        lo, hi = CameraPath.bounds(self.shake)
        quads, boxes = build_scene(self.seed, f0 * self.path.min_focal_scale(), self.width,
                                   self.height, tuple(lo), tuple(hi))
        self._renderer = Renderer(quads, boxes, self.width, self.height,
                                  self.intrinsics.cx, self.intrinsics.cy)

    @classmethod
    def from_spec(cls, options: Mapping[str, str]) -> "SyntheticSource":
        """Build from string options, e.g. ``{"seed": "3", "frames": "100", "zoom": "0.05"}``.

        Options: width, height, frames, seed (integers); fps, shake, zoom, hfov_deg
        (alias hfov) (numbers); report_zoom (true/false). An unknown option or a bad
        value raises ValueError naming it.
        """
        kw: dict = {}
        for key, raw in options.items():
            name = _SPEC_ALIASES.get(key.strip().lower(), key.strip().lower())
            if name not in _SPEC_TYPES:
                known = ", ".join(sorted(_SPEC_TYPES))
                raise ValueError(f"synthetic source: unknown option {key!r} (known: {known})")
            try:
                kw[name] = _SPEC_TYPES[name](str(raw).strip())
            except ValueError as e:
                kind = {int: "an integer", float: "a number"}.get(_SPEC_TYPES[name], "a boolean")
                detail = "" if _SPEC_TYPES[name] in (int, float) else f": {e}"
                raise ValueError(f"synthetic source option {key}={raw!r} is not {kind}{detail}") from None
        return cls(**kw)

    # -- access --------------------------------------------------------------------------
    def __len__(self) -> int:
        return self.frames

    def __iter__(self) -> Iterator[RGBDFrame]:
        for i in range(self.frames):
            yield self.frame(i)

    def poses(self) -> np.ndarray:
        """Ground-truth camera-to-world poses of all frames, (N, 4, 4) float64 (no rendering)."""
        return np.concatenate([self._chunk(c)[0] for c in range(-(-self.frames // _CHUNK))])

    def intended_poses(self) -> np.ndarray:
        """The shake-free camera path (N, 4, 4): the same seed's path with shake 0.

        Stabilization is judged against it: shake = what the pose does beyond this path.
        """
        t = np.arange(self.frames) / self.fps
        return CameraPath(self.seed, 0.0, self.zoom).poses(t)

    def intrinsics_at(self, i: int) -> Intrinsics:
        """The true intrinsics of frame i (the zoomed focal length)."""
        i = self._index(i)
        f = float(self._chunk(i // _CHUNK)[1][i % _CHUNK])
        return Intrinsics(f, f, self.intrinsics.cx, self.intrinsics.cy, self.width, self.height)

    def _chunk(self, c: int) -> tuple[np.ndarray, np.ndarray]:
        """Poses and focal lengths of frames [c * _CHUNK, (c + 1) * _CHUNK), computed once.

        A frame's pose always comes from the same chunk computation, so it is bit-identical
        however the frames are visited, and memory stays bounded for very long sources.
        """
        got = self._chunks.get(c)
        if got is None:
            t = np.arange(c * _CHUNK, min(self.frames, (c + 1) * _CHUNK)) / self.fps
            got = (self.path.poses(t), self.intrinsics.fx * self.path.focal_scale(t))
            for a in got:
                a.setflags(write=False)
            if len(self._chunks) >= 8:
                self._chunks.pop(next(iter(self._chunks)))
            self._chunks[c] = got
        return got

    def frame(self, i: int) -> RGBDFrame:
        """Render frame i (0 <= i < len; negative counts from the end)."""
        i = self._index(i)
        true_k = self.intrinsics_at(i)
        pose = self._chunk(i // _CHUNK)[0][i % _CHUNK]
        color, depth = self._renderer.render(pose, true_k.K)
        # Millimetre depth, as a real sensor (and the wire's uint16 depth) delivers it.
        depth = dequantize_depth(quantize_depth(depth, self.depth_scale), self.depth_scale)
        return RGBDFrame(color=color, depth=depth,
                         intrinsics=true_k if self.report_zoom else self.intrinsics,
                         timestamp_ns=int(round(i * 1e9 / self.fps)), seq=i,
                         pose=pose.copy(), origin="synthetic")

    def _index(self, i: int) -> int:
        n = self.frames
        j = i + n if i < 0 else i
        if not 0 <= j < n:
            raise IndexError(f"synthetic source: frame index {i} out of range (0..{n - 1})")
        return int(j)

    def __repr__(self) -> str:
        return (f"SyntheticSource({self.width}x{self.height}, frames={self.frames}, fps={self.fps:g}, "
                f"seed={self.seed}, shake={self.shake:g}, zoom={self.zoom:g}, "
                f"report_zoom={self.report_zoom})")

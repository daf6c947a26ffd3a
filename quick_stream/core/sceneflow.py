"""Dense scene flow: DIS optical flow lifted to 3D with both depth maps.

docs/method.md section 1. For frames t and t+1 with depths Z_t, Z_{t+1} and
intrinsics K_t, K_{t+1}, each sampled pixel p of frame t with flow f(p) gives

    x  = K_t^-1 [p, 1] Z_t(p)                       (the point, camera-t coordinates)
    x' = K_{t+1}^-1 [p + f, 1] Z_{t+1}(p + f)       (the same point, camera-(t+1) coordinates)
    v  = x' - x                                     (its displacement)

Masks: invalid or out-of-range depth in either frame, pixels on depth edges
(depth is often misregistered to colour there), flow leaving the image,
forward-backward inconsistent flow (occlusions) and unnaturally large
velocities (robustly, relative to the median: the paper's only filter).
Depth at the sub-pixel position p + f is interpolated bilinearly only where its
four neighbours agree, never blended across a depth edge.

The result keeps the pixel positions as well as the 3D pairs, so the motion
estimator can weigh image-plane and depth errors separately.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from functools import lru_cache

import cv2
import numpy as np

from .frame import Intrinsics, RGBDFrame

DIS_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


@dataclass
class SceneFlowParams:
    """Parameters of :class:`SceneFlow` (each one documented where it acts)."""

    preset: str = "ultrafast"  # DIS preset: ultrafast | fast | medium
    flow_scale: float = 1.0  # compute optical flow on images resized by this factor
    fb_check: bool = True  # forward-backward consistency test (occlusions)
    fb_scale: float = 0.5  # backward flow (used only for the test) at this image scale
    fb_threshold_px: float = 1.5  # max |f_fwd(p) + f_bwd(p + f_fwd)| in full-resolution px
    grid_step: int = 4  # sample at most every grid_step-th pixel in x and y ...
    max_points: int = 3000  # ... coarser if needed for ~3x this many candidates; keep at most this many
    min_depth: float = 0.1  # metres; depth outside [min_depth, max_depth] is invalid
    max_depth: float = 8.0
    depth_edge: float = 0.03  # relative depth jump to a 4-neighbour that marks a depth edge
    border_px: float = 2.0  # flow must land this far inside the image
    outlier_k: float = 6.0  # |v| outlier if | |v| - median| > outlier_k * 1.4826 * MAD
    outlier_floor_m: float = 0.01  # ... and more than this many metres from the median
    min_contrast: float = 2.0  # grey-level std below this (black, saturated, blank): no flow
    refine: str = "lk"  # "lk": refine each kept sample's flow with Lucas-Kanade started from DIS | "none"
    lk_window: int = 9  # LK window (px, odd)
    lk_iters: int = 10  # LK iterations at most (it starts from the DIS flow)
    lk_max_shift_px: float = 2.0  # LK moving a sample further than this from DIS: sample dropped

    @classmethod
    def describe(cls) -> dict[str, str]:
        """Parameter name -> default, for CLIs and reports."""
        return {f.name: repr(f.default) for f in fields(cls)}

    def validate(self) -> None:
        if self.preset not in DIS_PRESETS:
            raise ValueError(f"sceneflow preset must be one of {sorted(DIS_PRESETS)}, got {self.preset!r}")
        for name in ("flow_scale", "fb_scale"):
            val = getattr(self, name)
            if not 0.1 <= val <= 1.0:
                raise ValueError(f"sceneflow {name} must be in [0.1, 1], got {val}")
        if self.grid_step < 1 or self.max_points < 3:
            raise ValueError("sceneflow grid_step must be >= 1 and max_points >= 3")
        if self.refine not in ("lk", "none"):
            raise ValueError(f"sceneflow refine must be 'lk' or 'none', got {self.refine!r}")
        if self.lk_window < 3 or self.lk_window % 2 == 0 or self.lk_iters < 1 or not self.lk_max_shift_px > 0:
            raise ValueError("sceneflow lk_window must be odd >= 3, lk_iters >= 1 and lk_max_shift_px > 0")


@dataclass
class SceneFlowResult:
    """Points ``x`` (camera t), displacements ``v`` and weights for one frame pair.

    ``pixels`` are the sampled pixel positions in frame t and ``pixels_next`` where
    the flow puts them in frame t+1 (full-resolution coordinates). ``counts``
    reports how many samples each mask removed.
    """

    seq: int
    seq_next: int
    points: np.ndarray  # (N, 3) float64
    displacements: np.ndarray  # (N, 3) float64
    weights: np.ndarray  # (N,) float64
    pixels: np.ndarray  # (N, 2) float64
    pixels_next: np.ndarray  # (N, 2) float64
    intrinsics: Intrinsics
    intrinsics_next: Intrinsics
    counts: dict[str, int] = field(default_factory=dict)
    problem: str = ""  # why the pair gave no usable flow (empty when it did)

    def __len__(self) -> int:
        return len(self.points)

    def subset(self, keep: np.ndarray) -> "SceneFlowResult":
        """The pairs selected by boolean mask or index array ``keep``."""
        return SceneFlowResult(
            self.seq, self.seq_next, self.points[keep], self.displacements[keep], self.weights[keep],
            self.pixels[keep], self.pixels_next[keep], self.intrinsics, self.intrinsics_next,
            dict(self.counts, kept=int(np.count_nonzero(keep) if np.asarray(keep).dtype == bool else len(keep))),
            self.problem,
        )

    @classmethod
    def empty(cls, f0: RGBDFrame, f1: RGBDFrame, problem: str) -> "SceneFlowResult":
        """No usable pairs, with the reason."""
        z = np.zeros((0, 3))
        z2 = np.zeros((0, 2))
        return cls(f0.seq, f1.seq, z, z, np.zeros(0), z2, z2, f0.intrinsics, f1.intrinsics, {"kept": 0}, problem)


def depth_edge_at(depth: np.ndarray, u: np.ndarray, v: np.ndarray, rel: float) -> np.ndarray:
    """True where pixel (u, v)'s depth differs from a 4-neighbour's by more than ``rel`` (relative).

    Only the requested pixels are tested (the full-image mask is never built);
    pixels on the image border compare with themselves across the border.
    """
    h, w = depth.shape
    flat = depth.ravel()
    i = v * w + u
    d = flat[i]
    edge = np.zeros(u.shape, bool)
    for j in (
        np.where(u < w - 1, i + 1, i), np.where(u > 0, i - 1, i),
        np.where(v < h - 1, i + w, i), np.where(v > 0, i - w, i),
    ):
        n = flat[j]
        edge |= np.abs(n - d) > rel * np.minimum(n, d)
    return edge


def sample_depth(depth: np.ndarray, u: np.ndarray, v: np.ndarray, rel: float) -> np.ndarray:
    """Bilinear depth at sub-pixel (u, v) where the 4 neighbours are valid and agree within ``rel``.

    Returns 0 where the neighbours straddle a depth edge or an invalid pixel
    (docs/method.md (1): no blending across depth edges).
    """
    h, w = depth.shape
    u0 = np.clip(np.floor(u).astype(np.intp), 0, w - 2)
    v0 = np.clip(np.floor(v).astype(np.intp), 0, h - 2)
    a = u - u0
    b = v - v0
    flat = depth.ravel()
    i = v0 * w + u0
    d00 = flat[i]
    d01 = flat[i + 1]
    d10 = flat[i + w]
    d11 = flat[i + w + 1]
    dmin = np.minimum(np.minimum(d00, d01), np.minimum(d10, d11))
    dmax = np.maximum(np.maximum(d00, d01), np.maximum(d10, d11))
    ok = (dmin > 0) & (dmax - dmin <= rel * dmin)
    z = (1 - b) * ((1 - a) * d00 + a * d01) + b * ((1 - a) * d10 + a * d11)
    return np.where(ok, z, 0.0)


@lru_cache(maxsize=8)
def _grid(h: int, w: int, step: int) -> tuple[np.ndarray, np.ndarray]:
    """Candidate pixel coordinates (u, v) on a regular grid, read-only and cached."""
    off = step // 2
    vv, uu = np.mgrid[off:h:step, off:w:step]
    uu, vv = uu.ravel(), vv.ravel()
    uu.setflags(write=False)
    vv.setflags(write=False)
    return uu, vv


def _sample_flow(flow: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear sample of a (H, W, 2) flow field at sub-pixel positions (edges replicated)."""
    if u.size == 0:  # nothing survived the masks (e.g. no valid depth): cv2.remap refuses empty maps
        return np.zeros((0, 2))
    mx = u.astype(np.float32).reshape(1, -1)
    my = v.astype(np.float32).reshape(1, -1)
    out = cv2.remap(flow, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(-1, 2).astype(np.float64)


class SceneFlow:
    """Computes :class:`SceneFlowResult` for consecutive frames.

    Keeps the last frame's grey images so a stream converts each frame once.
    Not thread-safe (one instance per stream).
    """

    def __init__(self, params: SceneFlowParams | None = None) -> None:
        self.params = params or SceneFlowParams()
        self.params.validate()
        self._dis = cv2.DISOpticalFlow_create(DIS_PRESETS[self.params.preset])
        self._dis_fb = cv2.DISOpticalFlow_create(DIS_PRESETS["ultrafast"])
        # Grey images of the last two frames, keyed by seq; the colour array is kept
        # with them so a hit is the very same image (identity, not a reused id).
        self._cache: dict[int, tuple[np.ndarray, dict[float, np.ndarray]]] = {}

    def _greys(self, frame: RGBDFrame) -> dict[float, np.ndarray]:
        """Grey images of ``frame`` at the flow scale and the backward-check scale (cached)."""
        hit = self._cache.get(frame.seq)
        if hit is not None and hit[0] is frame.color:
            return hit[1]
        p = self.params
        g = cv2.cvtColor(frame.color, cv2.COLOR_BGR2GRAY)
        out = {1.0: g}
        for sc in {p.flow_scale, p.fb_scale * p.flow_scale} if p.fb_check else {p.flow_scale}:
            if sc not in out:
                out[sc] = cv2.resize(g, None, fx=sc, fy=sc, interpolation=cv2.INTER_AREA)
        self._cache.pop(frame.seq, None)
        if len(self._cache) >= 2:
            del self._cache[next(iter(self._cache))]
        self._cache[frame.seq] = (frame.color, out)
        return out

    def optical_flow(self, f0: RGBDFrame, f1: RGBDFrame) -> tuple[np.ndarray, np.ndarray | None]:
        """Forward DIS flow (at flow_scale) and, with fb_check, the backward flow (at fb_scale x flow_scale)."""
        p = self.params
        g0 = self._greys(f0)
        g1 = self._greys(f1)
        fwd = self._dis.calc(g0[p.flow_scale], g1[p.flow_scale], None)
        bwd = None
        if p.fb_check:
            sb = p.fb_scale * p.flow_scale
            bwd = self._dis_fb.calc(g1[sb], g0[sb], None)
        return fwd, bwd

    def compute(self, f0: RGBDFrame, f1: RGBDFrame) -> SceneFlowResult:
        """Scene flow from frame ``f0`` (time t) to ``f1`` (time t+1).

        A frame without enough image contrast for optical flow (black, saturated,
        blank) gives an empty result whose ``problem`` names it.
        """
        for f in (f0, f1):
            g = self._greys(f)[self.params.flow_scale]
            std = float(cv2.meanStdDev(g)[1][0, 0])
            if std < self.params.min_contrast:
                return SceneFlowResult.empty(
                    f0, f1, f"{f.label}: too little image contrast for optical flow (grey std {std:.2f})"
                )
        fwd, bwd = self.optical_flow(f0, f1)
        return lift_flow(f0, f1, fwd, bwd, self.params, self.refiner(f0, f1))

    def refiner(self, f0: RGBDFrame, f1: RGBDFrame):
        """The sample-flow refinement :func:`lift_flow` takes for this pair (None when ``refine`` is "none")."""
        if self.params.refine != "lk":
            return None
        g0, g1 = self._greys(f0)[1.0], self._greys(f1)[1.0]

        def refine(u0: np.ndarray, v0: np.ndarray, u1: np.ndarray, v1: np.ndarray):
            return refine_lk(g0, g1, u0, v0, u1, v1, self.params)
        return refine


def refine_lk(g0: np.ndarray, g1: np.ndarray, u0: np.ndarray, v0: np.ndarray, u1: np.ndarray, v1: np.ndarray,
              p: SceneFlowParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lucas-Kanade refinement of sample flows started from DIS (docs/method.md (1)).

    DIS interpolates its flow from overlapping patches at a coarse scale, which leaves
    errors correlated across the image (they do not average out over the samples); a
    few LK iterations per sample at full resolution, started from the DIS estimate,
    remove most of them. Returns the refined (u1, v1) and a mask of samples LK kept: it
    converged and moved the sample at most ``lk_max_shift_px`` from DIS.
    """
    if u0.size == 0:
        return u1, v1, np.ones(0, bool)
    p0 = np.column_stack((u0, v0)).astype(np.float32).reshape(-1, 1, 2)
    p1 = np.column_stack((u1, v1)).astype(np.float32).reshape(-1, 1, 2)
    out, st, _ = cv2.calcOpticalFlowPyrLK(
        g0, g1, p0, p1, winSize=(p.lk_window, p.lk_window), maxLevel=0, flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, p.lk_iters, 0.01))
    out = out.reshape(-1, 2).astype(np.float64)
    ok = st.ravel().astype(bool) & np.all(np.isfinite(out), axis=1)
    ok &= np.hypot(out[:, 0] - u1, out[:, 1] - v1) <= p.lk_max_shift_px
    return np.where(ok, out[:, 0], u1), np.where(ok, out[:, 1], v1), ok


def _f32(a: np.ndarray) -> np.ndarray:
    """float64 array rounded to float32 precision (the flow message's depths are float32)."""
    return a.astype(np.float32).astype(np.float64)


# --- the flow as the wire carries it (docs/wire-format.md, flow, version 2) --------------------------

FIXED_MAX = 32767  # int16 fixed point
OFFSET_MAX_EXP = 10  # flow offsets in steps of 2^-k px, k <= 10: <= 0.0005 px off, 1/20 of LK's 0.01 px tolerance
DEPTH_MAX_EXP = 16  # depth changes in steps of 2^-k m, k <= 16: <= 8 um off, 1/130 of a 1 mm depth unit


def fixed_point_exp(values: np.ndarray, max_exp: int) -> int:
    """The largest ``k <= max_exp`` with every ``round(values * 2^k)`` within int16 (+-32767)."""
    m = float(np.max(np.abs(values))) if values.size else 0.0
    if not m > 0:
        return max_exp
    k = min(max_exp, math.floor(math.log2(FIXED_MAX / m)))
    while np.rint(m * 2.0 ** k) > FIXED_MAX:
        k -= 1
    return k


def lift_pairs(pixels: np.ndarray, depth: np.ndarray, pixels_next: np.ndarray, depth_next: np.ndarray,
               K0: Intrinsics, K1: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Points ``x = K0^-1 [p, 1] z`` and displacements ``v = K1^-1 [p', 1] z' - x`` (docs/method.md (1)),
    each rounded to float32. The one formula :func:`lift_flow` and the wire's flow decoder
    (:mod:`quick_stream.stream.wire.flowpack`) use: the same samples give the same bits in every process."""
    x = np.empty((len(depth), 3))
    x[:, 0] = (pixels[:, 0] - K0.cx) * (depth / K0.fx)
    x[:, 1] = (pixels[:, 1] - K0.cy) * (depth / K0.fy)
    x[:, 2] = depth
    vel = np.empty_like(x)
    vel[:, 0] = (pixels_next[:, 0] - K1.cx) * (depth_next / K1.fx) - x[:, 0]
    vel[:, 1] = (pixels_next[:, 1] - K1.cy) * (depth_next / K1.fy) - x[:, 1]
    vel[:, 2] = depth_next - depth
    return _f32(x), _f32(vel)


def quantized_flow(seq: int, seq_next: int, pixels: np.ndarray, depth: np.ndarray, pixels_next: np.ndarray,
                   depth_next: np.ndarray, K0: Intrinsics, K1: Intrinsics, counts: dict[str, int]) -> SceneFlowResult:
    """The flow of the kept samples as the wire carries it, so a stage fed from the wire computes bit
    for bit what an in-process one does: depths rounded to float32, each sample's flow
    ``p' - p`` and depth change ``z' - z`` in int16 fixed point (steps of ``2^-k`` px and ``2^-k'`` m,
    ``k``, ``k'`` the finest that hold the largest; :func:`fixed_point_exp`), then lifted with
    :func:`lift_pairs`. ``pixels`` are the sampled integer pixels."""
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    depth = _f32(np.asarray(depth, dtype=np.float64))
    off = pixels_next - pixels
    k = fixed_point_exp(off, OFFSET_MAX_EXP)
    pixels_next = pixels + np.rint(off * 2.0 ** k) * 2.0 ** -k
    dz = depth_next - depth
    kd = fixed_point_exp(dz, DEPTH_MAX_EXP)
    depth_next = depth + np.rint(dz * 2.0 ** kd) * 2.0 ** -kd
    points, displacements = lift_pairs(pixels, depth, pixels_next, depth_next, K0, K1)
    return SceneFlowResult(seq, seq_next, points, displacements, np.ones(len(depth)), pixels, pixels_next, K0, K1,
                           counts)


def lift_flow(
    f0: RGBDFrame,
    f1: RGBDFrame,
    fwd: np.ndarray,
    bwd: np.ndarray | None,
    p: SceneFlowParams,
    refine=None,
) -> SceneFlowResult:
    """Lift optical flow to 3D and apply the masks (docs/method.md (1)).

    Candidates are pixels on a regular grid (about twice ``max_points`` of them);
    each mask shrinks the candidate set before the next, dearer one runs. ``refine``
    (u0, v0, u1, v1) -> (u1, v1, kept), e.g. :func:`refine_lk`, corrects the flow of the
    samples that passed the image masks, before the second frame's depth is read.
    """
    h, w = f0.depth.shape
    s = p.flow_scale
    counts: dict[str, int] = {}
    step = max(p.grid_step, int(np.sqrt(h * w / (2.0 * p.max_points))))
    uu, vv = _grid(h, w, step)
    counts["sampled"] = uu.size
    z0 = f0.depth.ravel()[vv * w + uu]
    ok = (z0 >= p.min_depth) & (z0 <= p.max_depth)
    counts["invalid_depth"] = int(uu.size - np.count_nonzero(ok))
    if p.depth_edge > 0:
        edge = depth_edge_at(f0.depth, uu, vv, p.depth_edge) & ok
        counts["depth_edge"] = int(np.count_nonzero(edge))
        ok &= ~edge
    sel = np.flatnonzero(ok)
    uu, vv, z0 = uu[sel], vv[sel], z0[sel].astype(np.float64)
    # Flow at those pixels (computed at scale s: sample at s*p, scale back).
    if s == 1.0:
        fl = fwd.reshape(-1, 2)[vv * w + uu].astype(np.float64)
    else:
        fl = _sample_flow(fwd, (uu + 0.5) * s - 0.5, (vv + 0.5) * s - 0.5) / s
    u1 = uu + fl[:, 0]
    v1 = vv + fl[:, 1]
    b = p.border_px
    ok = (u1 >= b) & (u1 <= w - 1 - b) & (v1 >= b) & (v1 <= h - 1 - b)
    counts["out_of_image"] = int(ok.size - np.count_nonzero(ok))
    if bwd is not None:
        sb = s * p.fb_scale
        back = _sample_flow(bwd, (u1 + 0.5) * sb - 0.5, (v1 + 0.5) * sb - 0.5) / sb
        bad = np.hypot(fl[:, 0] + back[:, 0], fl[:, 1] + back[:, 1]) > p.fb_threshold_px
        counts["fb_inconsistent"] = int(np.count_nonzero(bad & ok))
        ok &= ~bad
    sel = np.flatnonzero(ok)
    uu, vv, z0, u1, v1 = uu[sel], vv[sel], z0[sel], u1[sel], v1[sel]
    if refine is not None:
        u1, v1, kept = refine(uu, vv, u1, v1)
        kept &= (u1 >= b) & (u1 <= w - 1 - b) & (v1 >= b) & (v1 <= h - 1 - b)
        counts["lk_rejected"] = int(kept.size - np.count_nonzero(kept))
        uu, vv, z0, u1, v1 = uu[kept], vv[kept], z0[kept], u1[kept], v1[kept]
    z1 = sample_depth(f1.depth, u1, v1, p.depth_edge if p.depth_edge > 0 else 0.05)
    ok = (z1 >= p.min_depth) & (z1 <= p.max_depth)
    counts["invalid_depth_next"] = int(ok.size - np.count_nonzero(ok))
    K0, K1 = f0.intrinsics, f1.intrinsics
    x = np.empty((uu.size, 3))
    x[:, 0] = (uu - K0.cx) * (z0 / K0.fx)
    x[:, 1] = (vv - K0.cy) * (z0 / K0.fy)
    x[:, 2] = z0
    vel = np.empty_like(x)
    vel[:, 0] = (u1 - K1.cx) * (z1 / K1.fx) - x[:, 0]
    vel[:, 1] = (v1 - K1.cy) * (z1 / K1.fy) - x[:, 1]
    vel[:, 2] = z1 - z0
    if np.count_nonzero(ok) >= 3:  # the outlier test on the unquantized samples; the kept ones go on the wire
        speed = np.sqrt(np.einsum("ij,ij->i", vel, vel))
        med = np.median(speed[ok])
        dev = np.abs(speed - med)
        mad = 1.4826 * np.median(dev[ok])
        out = dev > max(p.outlier_k * mad, p.outlier_floor_m)
        counts["velocity_outlier"] = int(np.count_nonzero(out & ok))
        ok &= ~out
    sel = np.flatnonzero(ok)
    if sel.size > p.max_points:
        sel = sel[np.linspace(0, sel.size - 1, p.max_points).round().astype(np.intp)]
    counts["kept"] = int(sel.size)
    return quantized_flow(f0.seq, f1.seq, np.column_stack((uu[sel], vv[sel])), z0[sel],
                          np.column_stack((u1[sel], v1[sel])), z1[sel], K0, K1, counts)

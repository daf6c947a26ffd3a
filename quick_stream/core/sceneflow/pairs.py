"""The scene flow's result, as the wire carries it: :class:`SceneFlowResult` and the quantization
that makes a flow decoded from the wire give back the in-process one bit for bit (docs/wire-format.md,
flow, version 2; the lift is docs/method.md (1))."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..frame import Intrinsics, RGBDFrame


@dataclass
class SceneFlowResult:
    """Points ``x`` (camera t), displacements ``v`` and weights for one frame pair.

    ``pixels`` are the sampled pixel positions in frame t and ``pixels_next`` where
    the flow puts them in frame t+1 (full-resolution coordinates). ``counts``
    reports how many samples each mask removed. ``over``: the frames between ``seq`` and ``seq_next``
    the flow stage reached over (their own flow starved, docs/method.md 2.4): they were not skipped, the
    motion is split across them.
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
    over: tuple[int, ...] = ()  # frames reached over, increasing, strictly between seq and seq_next

    def __len__(self) -> int:
        return len(self.points)

    def subset(self, keep: np.ndarray) -> "SceneFlowResult":
        """The pairs selected by boolean mask or index array ``keep``."""
        return SceneFlowResult(
            self.seq, self.seq_next, self.points[keep], self.displacements[keep], self.weights[keep],
            self.pixels[keep], self.pixels_next[keep], self.intrinsics, self.intrinsics_next,
            dict(self.counts, kept=int(np.count_nonzero(keep) if np.asarray(keep).dtype == bool else len(keep))),
            self.problem, self.over,
        )

    @classmethod
    def empty(cls, f0: RGBDFrame, f1: RGBDFrame, problem: str) -> "SceneFlowResult":
        """No usable pairs, with the reason."""
        z = np.zeros((0, 3))
        z2 = np.zeros((0, 2))
        return cls(f0.seq, f1.seq, z, z, np.zeros(0), z2, z2, f0.intrinsics, f1.intrinsics, {"kept": 0}, problem)


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

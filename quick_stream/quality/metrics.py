"""Stabilisation quality: cropping, distortion, stability (Liu et al. 2013) and residual jitter.

docs/method.md section 6, with the definitions of CodingFlow (Liu et al. 2017) and
the conventions of the widely used reimplementations (DIFRINT / StabNet metric
scripts) where the papers leave a choice open. Every choice is stated here.

Features. SIFT (``cv2.SIFT_create``, at most ``n_features`` per image) on the
grey image resized so its long side is at most ``max_side`` px (speed: 640x480
is described at 320x240), Lowe ratio test, RANSAC homography
(``cv2.findHomography``) refined on the inliers. Each image is described once:
output frame i serves both the input-output pair i and the output pairs
(i-1, i) and (i, i+1). Keypoints are put back in full-resolution pixels and
centred on the image centre before fitting, so every homography ``H`` below is
in centred full-resolution coordinates with ``H[2, 2] = 1``: its translation
is the exact motion of the image centre and its upper-left 2x2 block (the
"affine part") is the linear map about the centre.

Cropping. ``H`` maps OUTPUT pixels to INPUT pixels (it is fitted from output
keypoints to input keypoints). An output that shows the input zoomed in by z
maps onto a 1/z-sized region of the input, so the scale of this direction is
the linear fraction of the input that survives: 1.25x zoom-in -> 0.8,
unchanged -> 1.0. Scale = sqrt(|det A|) of the affine part A (the geometric
mean of its singular values, so rotation does not change it). Per frame value
unclipped (> 1 means the output shows more than the input, i.e. borders);
sequence value = mean over frames.

Distortion. The paper says "ratio of the two eigenvalues of the affine part";
eigenvalues of a matrix containing any rotation are a complex pair of equal
modulus, so that ratio would call every rotated-and-stretched frame
undistorted. We use the singular values (square roots of the eigenvalues of
A^T A), which equal the eigenvalues when A is a pure stretch and are
rotation-invariant otherwise: per frame sigma_min / sigma_max; sequence value
= the worst (minimum) frame.

Stability (``stability``: the published definition, docs/method.md (15)-(17)).
As the public metric scripts of Liu et al. 2013's successors (DIFRINT, StabNet)
compute it: for each pair of consecutive OUTPUT frames the homography M_t maps
frame t-1 to frame t (fitted from t-1's keypoints to t's); it is expressed in
pixel coordinates with the origin at the top-left pixel centre (the scripts use
OpenCV keypoint coordinates; ours are centred, so M_t = C H_t C^-1, renormalised
to M_t[2, 2] = 1) and accumulated into the path P_t = P_{t-1} M_t (P_0 = I, t =
1..L, L = frames - 1, the product not renormalised). Translation signal:
sqrt(P_t[0, 2]^2 + P_t[1, 2]^2) (px); rotation signal: atan2(P_t[1, 0], P_t[0, 0])
(deg). Each signal of length L: power of the full complex FFT, DC bin deleted,
the first (L-1)//2 remaining bins kept, score = power in the first ``low_bins``
of them (bins 2..6 of the spectrum for 5) over their sum.
``stability_translation`` and ``stability_rotation`` are those two scores and
``stability`` is their MEAN (as the DIFRINT script prints). Ours beyond the
scripts: a signal with no variation at all (identical frames) scores 1 instead
of 0/0; pairs whose homography cannot be fitted (or whose fit is degenerate, or
turns more than ``max_pair_turn_deg``, 30 deg: repeated texture under blur matched
a shifted copy, e.g. a striped carpet fitted as a 67 deg turn with 291 inliers) are
filled by linear interpolation of the neighbouring pairs' (centred, normalised)
homographies and counted in ``warnings`` (the scripts reuse the previous pair's matrix).
Properties worth knowing (measured, docs/method.md section 6): the score is
scale-free, so a still camera is scored on its feature-estimation noise alone;
per-pair estimation noise accumulates into a random walk, whose spectrum falls
as 1/k^2, so a still camera scores about 0.83-0.92 (expectation, 15-250 pairs;
0.71-0.90 measured through this module), not 1; and a steady pan makes the translation signal a ramp that scores about
0.9 whatever shake rides on it.

Per-pair stability (``stability_pairs``, this module's earlier definition, kept
for comparison). Each pair's centred homography gives its motion (tx, ty) = the
centre's displacement and the angle atan2(a10 - a01, a00 + a11) (the rotation
of the closest similarity); the three per-pair signals (not accumulated) are
transformed with a real FFT and scored as power in bins 1..``low_bins`` over
bins 1..L//2 (DC excluded). ``stability_pairs_translation`` is the average of
the x and y scores, ``stability_pairs_rotation`` the angle's score and
``stability_pairs`` = min(translation, rotation). Per-pair motions of a still or
steadily moving camera are white estimation noise, which scores about
5 / (L/2) whatever the stabiliser did.

Failure (docs/method.md section 6: "a frame mapped out of view"). The sequence
fails when any output frame is essentially empty (more than
``max_black_fraction`` of its pixels at or below ``black_level``), or its
input-output homography cannot be fitted (too few ratio-test matches or RANSAC
inliers), or the fit is degenerate (mirrored, or scale outside
[min_scale, max_scale]). Then cropping, distortion and stability are 0 and
``failure_reason`` names the first such frame and why. Jitter is still reported.

Residual jitter (ours, not Liu's). The per-pair motions (tx, ty, angle) are
summed into a trajectory (frame 0 = 0; additive, fine for the small
per-frame rotations of video). High-pass = trajectory minus its Gaussian
smoothing (sigma = fps/6 frames unless ``jitter_sigma_frames`` is set,
``scipy.ndimage.gaussian_filter1d``, padded by reflection about the end points
so that a steady pan has zero jitter; see ``metrics_jitter``). Translation
jitter is in OUTPUT pixels: a stabiliser that zooms in by z shows remaining
shake z times larger, and is charged for it. ``jitter_px`` = RMS
over frames of the high-passed translation's magnitude, ``jitter_deg`` = RMS of
the high-passed angle in degrees. The same is computed from consecutive INPUT
frames (``input_jitter_px/deg``, ``input_stability``, ``input_stability_pairs``)
so tables can show the reduction.

Speed: about 65 ms per 640x480 frame pair on one core (two SIFT descriptions
at 320x240, three match + RANSAC), i.e. ~17 s for 250 frames (measured on
7scenes_redkitchen, OpenCV single-threaded).
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field

import cv2
import numpy as np

from .metrics_jitter import low_frequency_ratio, motion_of, path_stability, trajectory_jitter


@dataclass
class MetricParams:
    """Parameters of the quality metrics (each one documented where it acts)."""

    n_features: int = 1000  # SIFT features kept per image (strongest)
    contrast_threshold: float = 0.02  # SIFT contrast threshold (OpenCV default 0.04; lower: more features at low res)
    max_side: int = 320  # describe images resized so the long side is at most this (0: full resolution)
    ratio: float = 0.75  # Lowe ratio test
    ransac_px: float = 3.0  # RANSAC reprojection threshold, full-resolution px
    min_matches: int = 20  # fewer ratio-test matches: the homography "cannot be estimated"
    min_inliers: int = 12  # fewer RANSAC inliers: likewise
    min_scale: float = 0.1  # input-output scale outside [min_scale, max_scale]: degenerate fit (failure)
    max_scale: float = 10.0
    max_pair_turn_deg: float = 30.0  # a consecutive pair fitted as turning more than this: taken as unmatched
    black_level: int = 10  # grey level at or below which a pixel counts as black
    max_black_fraction: float = 0.9  # output frame blacker than this: "mapped out of view" (failure)
    low_bins: int = 5  # stability: bins 2..(low_bins+1) of the spectrum (DC excluded)
    jitter_sigma_frames: float | None = None  # Gaussian sigma of the jitter high-pass; None: fps / 6

    def validate(self) -> None:
        if self.n_features < 10 or not 0 < self.ratio < 1:
            raise ValueError("metrics n_features must be >= 10 and ratio in (0, 1)")
        if self.min_inliers < 4 or self.min_matches < self.min_inliers:
            raise ValueError("metrics need min_matches >= min_inliers >= 4")
        if not 0 < self.max_black_fraction <= 1 or self.low_bins < 1:
            raise ValueError("metrics max_black_fraction must be in (0, 1] and low_bins >= 1")


@dataclass
class Features:
    """One image described: centred full-resolution keypoints, SIFT descriptors, black fraction."""

    points: np.ndarray  # (N, 2) float32, pixel minus image centre
    descriptors: np.ndarray | None  # (N, 128) float32
    black_fraction: float


@dataclass
class PairFit:
    """Homography from image a to image b (centred coordinates), or why there is none."""

    H: np.ndarray | None
    matches: int
    inliers: int
    problem: str = ""


@dataclass
class FrameMetrics:
    """Per-frame details: input-output fit, and the motion to the next output/input frame."""

    index: int
    cropping: float = 0.0  # scale of the output->input homography (nan when not fitted)
    distortion: float = 0.0  # sigma_min / sigma_max of its affine part
    matches: int = 0
    inliers: int = 0
    black_fraction: float = 0.0
    problem: str = ""
    motion_to_next: tuple[float, float, float] | None = None  # output (tx px, ty px, angle deg)
    input_motion_to_next: tuple[float, float, float] | None = None


@dataclass
class SequenceMetrics:
    """Liu et al. metrics and residual jitter of one stabilised sequence (see the module docstring)."""

    frames: int
    cropping: float
    distortion: float
    stability: float  # published: mean of the two path scores below
    stability_translation: float
    stability_rotation: float
    stability_pairs: float  # earlier per-pair definition: min of the two below
    stability_pairs_translation: float
    stability_pairs_rotation: float
    jitter_px: float
    jitter_deg: float
    input_jitter_px: float
    input_jitter_deg: float
    input_stability: float  # published, of the input frames
    input_stability_pairs: float
    failed: bool
    failure_reason: str
    per_frame: list[FrameMetrics] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    seconds: float = 0.0  # wall time spent computing the metrics

    def as_dict(self, per_frame: bool = False) -> dict:
        """Plain dict for JSON; per-frame details only when asked (they are long)."""
        d = asdict(self)
        if not per_frame:
            d.pop("per_frame")
        return d


class FeatureMatcher:
    """SIFT description (once per image) and ratio-test + RANSAC homography between two descriptions."""

    def __init__(self, params: MetricParams | None = None) -> None:
        self.params = params or MetricParams()
        self.params.validate()
        self._sift = cv2.SIFT_create(nfeatures=self.params.n_features,
                                     contrastThreshold=self.params.contrast_threshold)
        self._bf = cv2.BFMatcher(cv2.NORM_L2)

    def describe(self, image: np.ndarray) -> Features:
        p = self.params
        grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
        if grey.dtype != np.uint8:
            grey = np.clip(grey, 0, 255).astype(np.uint8)
        black = float(np.count_nonzero(grey <= p.black_level)) / grey.size
        h, w = grey.shape
        s = min(1.0, p.max_side / max(h, w)) if p.max_side > 0 else 1.0
        small = cv2.resize(grey, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA) if s < 1 else grey
        kps, desc = self._sift.detectAndCompute(small, None)
        sx, sy = w / small.shape[1], h / small.shape[0]
        pts = np.array([k.pt for k in kps], np.float32).reshape(-1, 2)
        # keypoint (x, y) in the small image is at pixel centre (x + 0.5) * s_x - 0.5 in the full one
        pts = (pts + 0.5) * np.float32([sx, sy]) - 0.5 - np.float32([(w - 1) / 2, (h - 1) / 2])
        return Features(pts, desc, black)

    def fit(self, a: Features, b: Features) -> PairFit:
        """Homography H with b ~ H a (centred coordinates, H[2, 2] = 1)."""
        p = self.params
        if a.descriptors is None or b.descriptors is None or len(a.points) < 2 or len(b.points) < 2:
            return PairFit(None, 0, 0, "no features")
        knn = self._bf.knnMatch(a.descriptors, b.descriptors, k=2)
        good = [m[0] for m in knn if len(m) == 2 and m[0].distance < p.ratio * m[1].distance]
        if len(good) < p.min_matches:
            return PairFit(None, len(good), 0, f"only {len(good)} matches (< {p.min_matches})")
        src = a.points[[m.queryIdx for m in good]]
        dst = b.points[[m.trainIdx for m in good]]
        H, mask = cv2.findHomography(src, dst, cv2.RANSAC, p.ransac_px, maxIters=2000, confidence=0.995)
        inl = int(mask.sum()) if mask is not None else 0
        if H is None or inl < p.min_inliers or not np.all(np.isfinite(H)) or abs(H[2, 2]) < 1e-12:
            return PairFit(None, len(good), inl, f"only {inl} RANSAC inliers (< {p.min_inliers})")
        return PairFit(H / H[2, 2], len(good), inl)


def scale_and_distortion(H: np.ndarray) -> tuple[float, float, float]:
    """(scale, distortion, det) of the affine part: sqrt|det|, sigma_min / sigma_max, det."""
    A = H[:2, :2] / H[2, 2]
    sv = np.linalg.svd(A, compute_uv=False)
    det = float(np.linalg.det(A))
    return math.sqrt(abs(det)), float(sv[1] / sv[0]) if sv[0] > 0 else 0.0, det


def sound(H: np.ndarray, p: MetricParams) -> bool:
    """Whether a fitted homography can be a view of the same scene: its affine part keeps orientation (det > 0)
    and its scale is within [min_scale, max_scale]. Else it is a RANSAC accident (a blurred frame's matches
    along one streak): an input-output fit is a failure, a consecutive pair's is taken as unmatched."""
    scale, _, det = scale_and_distortion(H)
    return det > 0 and p.min_scale <= scale <= p.max_scale


def _fill(motions: list[tuple[float, float, float] | None]) -> tuple[np.ndarray, int]:
    """(N, 3) motion array with missing pairs linearly interpolated; returns it and the number filled."""
    n = len(motions)
    out = np.zeros((n, 3))
    ok = np.array([m is not None for m in motions], bool)
    if not ok.any():
        return out, n
    idx = np.flatnonzero(ok)
    vals = np.array([motions[i] for i in idx], float)
    for k in range(3):
        out[:, k] = np.interp(np.arange(n), idx, vals[:, k])
    return out, int(n - ok.sum())


def _fill_homographies(hs: list[np.ndarray | None]) -> np.ndarray:
    """(L, 3, 3) homographies (normalised to [2, 2] = 1) with missing pairs linearly interpolated
    entry by entry between the nearest fitted ones (held constant beyond the ends; identity if none)."""
    n = len(hs)
    out = np.tile(np.eye(3), (n, 1, 1))
    ok = [i for i, h in enumerate(hs) if h is not None]
    if not ok:
        return out
    vals = np.array([hs[i] / hs[i][2, 2] for i in ok]).reshape(len(ok), 9)
    flat = out.reshape(n, 9)
    for k in range(9):
        flat[:, k] = np.interp(np.arange(n), ok, vals[:, k])
    return out


def _pairs_stability(motions: np.ndarray, low_bins: int) -> tuple[float, float]:
    """(translation, rotation) per-pair stability of (L, 3) motions: the ``stability_pairs`` components."""
    st_x, st_y, st_r = (low_frequency_ratio(motions[:, k], low_bins) for k in range(3))
    return 0.5 * (st_x + st_y), st_r


class MetricsAccumulator:
    """Streaming form of :func:`evaluate_sequence`: ``add`` (input, output) frame by frame, then ``result``.

    Only the previous frame's descriptions are kept, plus a few numbers per frame
    (and each consecutive pair's 3x3 homography, for the accumulated path).
    """

    def __init__(self, fps: float = 30.0, params: MetricParams | None = None) -> None:
        self.fps = float(fps)
        self.params = params or MetricParams()
        self.matcher = FeatureMatcher(self.params)
        self.frames: list[FrameMetrics] = []
        self._prev: tuple[Features, Features] | None = None
        self._pair_h: dict[str, list[np.ndarray | None]] = {"output": [], "input": []}  # centred, frame t -> t+1
        self._centre: dict[str, tuple[float, float]] = {}
        self._seconds = 0.0
        self._failure = ""
        self.last_homography: np.ndarray | None = None  # output -> input of the last frame added, if sound

    def add(self, input_frame: np.ndarray, output_frame: np.ndarray) -> FrameMetrics:
        t0 = time.perf_counter()
        p = self.params
        fin = self.matcher.describe(input_frame)
        # the input scored as its own output (the benchmarks' input row): one description, one pair fit
        fout = fin if output_frame is input_frame else self.matcher.describe(output_frame)
        for name, img in (("input", input_frame), ("output", output_frame)):
            self._centre.setdefault(name, ((img.shape[1] - 1) / 2.0, (img.shape[0] - 1) / 2.0))
        fm = FrameMetrics(len(self.frames), black_fraction=fout.black_fraction)
        self.last_homography = None
        if fout.black_fraction > p.max_black_fraction:
            fm.problem = f"output is {100 * fout.black_fraction:.0f}% black (mapped out of view)"
            fm.cropping = fm.distortion = float("nan")
        else:
            fit = self.matcher.fit(fout, fin)  # output -> input: the cropping direction
            fm.matches, fm.inliers = fit.matches, fit.inliers
            if fit.H is None:
                fm.problem = f"input-output homography cannot be estimated: {fit.problem}"
                fm.cropping = fm.distortion = float("nan")
            else:
                fm.cropping, fm.distortion, det = scale_and_distortion(fit.H)
                if not sound(fit.H, p):
                    fm.problem = f"degenerate input-output homography (scale {fm.cropping:.3g}, det {det:.3g})"
                else:
                    self.last_homography = fit.H  # centred coordinates (module docstring)
        if fm.problem and not self._failure:
            self._failure = f"frame {fm.index}: {fm.problem}"
        if self._prev is not None:
            prev_fm = self.frames[-1]
            out_fit = self.matcher.fit(self._prev[1], fout)
            same = self._prev[0] is self._prev[1] and fin is fout
            in_fit = out_fit if same else self.matcher.fit(self._prev[0], fin)
            for name, attr, fit in (("output", "motion_to_next", out_fit), ("input", "input_motion_to_next", in_fit)):
                H = fit.H if fit.H is not None and sound(fit.H, p) else None  # degenerate: as if unmatched
                if H is not None and abs(motion_of(H)[2]) > p.max_pair_turn_deg:
                    H = None  # no camera turns that far in a frame: repeated texture matched a shifted copy
                setattr(prev_fm, attr, None if H is None else motion_of(H))
                self._pair_h[name].append(H)
        self._prev = (fin, fout)
        self.frames.append(fm)
        self._seconds += time.perf_counter() - t0
        return fm

    @property
    def jitter_sigma(self) -> float:
        """Gaussian sigma (frames) of the jitter high-pass."""
        p = self.params
        return p.jitter_sigma_frames if p.jitter_sigma_frames is not None else self.fps / 6.0

    def input_motions(self) -> np.ndarray:
        """(N - 1, 3) per-pair input motions (tx px, ty px, angle deg), missing pairs interpolated as for jitter."""
        return _fill([f.input_motion_to_next for f in self.frames[:-1]])[0]

    def result(self) -> SequenceMetrics:
        p = self.params
        n = len(self.frames)
        if n < 2:
            raise ValueError(f"metrics need at least 2 frames, got {n}")
        sigma = self.jitter_sigma
        warnings: list[str] = []
        pairs = self.frames[:-1]
        out_m, out_missing = _fill([f.motion_to_next for f in pairs])
        in_m, in_missing = _fill([f.input_motion_to_next for f in pairs])
        for name, missing in (("output", out_missing), ("input", in_missing)):
            if missing:
                warnings.append(f"{missing} of {n - 1} consecutive {name} pairs had no homography (interpolated)")
        if n - 1 <= 2 * p.low_bins + 2:  # (L - 1) // 2 <= low_bins: every kept bin is a low one, score 1
            warnings.append(f"only {n - 1} frame pairs: stability needs more than {2 * p.low_bins + 2} to mean much")
        sp_t, sp_r = _pairs_stability(out_m, p.low_bins)
        in_sp = min(_pairs_stability(in_m, p.low_bins))
        st_t, st_r = path_stability(_fill_homographies(self._pair_h["output"]), self._centre["output"], p.low_bins)
        in_st = float(np.mean(path_stability(_fill_homographies(self._pair_h["input"]), self._centre["input"],
                                             p.low_bins)))
        if out_missing == n - 1:
            st_t = st_r = sp_t = sp_r = 0.0
            warnings.append("no consecutive output pair could be matched: stability 0")
        jit = trajectory_jitter(out_m, sigma) if out_missing < n - 1 else (float("nan"), float("nan"))
        in_jit = trajectory_jitter(in_m, sigma) if in_missing < n - 1 else (float("nan"), float("nan"))
        failed = bool(self._failure)
        crop = float(np.mean([f.cropping for f in self.frames])) if not failed else 0.0
        dist = float(np.min([f.distortion for f in self.frames])) if not failed else 0.0
        return SequenceMetrics(
            frames=n, cropping=crop, distortion=dist,
            stability=0.0 if failed else float(0.5 * (st_t + st_r)),
            stability_translation=0.0 if failed else float(st_t),
            stability_rotation=0.0 if failed else float(st_r),
            stability_pairs=0.0 if failed else float(min(sp_t, sp_r)),
            stability_pairs_translation=0.0 if failed else float(sp_t),
            stability_pairs_rotation=0.0 if failed else float(sp_r),
            jitter_px=jit[0], jitter_deg=jit[1], input_jitter_px=in_jit[0], input_jitter_deg=in_jit[1],
            input_stability=in_st, input_stability_pairs=float(in_sp), failed=failed, failure_reason=self._failure,
            per_frame=list(self.frames), warnings=warnings, seconds=self._seconds,
        )


def evaluate_sequence(inputs: list[np.ndarray], outputs: list[np.ndarray], fps: float = 30.0,
                      params: MetricParams | None = None) -> SequenceMetrics:
    """Cropping, distortion, stability and residual jitter of ``outputs`` (stabilised ``inputs``), BGR frames.

    docs/method.md section 6; definitions and choices in the module docstring.
    """
    if len(inputs) != len(outputs):
        raise ValueError(f"{len(inputs)} input frames but {len(outputs)} output frames")
    acc = MetricsAccumulator(fps, params)
    for a, b in zip(inputs, outputs):
        acc.add(a, b)
    return acc.result()

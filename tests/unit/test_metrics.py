"""Quality metrics (docs/method.md section 6) on synthetic textured sequences, and the FFmpeg baseline runner."""
from __future__ import annotations

import math
from functools import lru_cache

import cv2
import numpy as np
import pytest

from quick_stream.bench.ffmpeg_baselines import ensure_ffmpeg, run_baselines
from quick_stream.quality.metrics import MetricParams, evaluate_sequence
from quick_stream.quality.metrics_jitter import (
    accumulate_path, low_frequency_ratio, path_low_frequency_ratio, path_signals, path_stability, to_pixel_origin,
    trajectory_jitter,
)

W, H = 320, 240


@lru_cache(maxsize=4)
def texture(h: int = 700, w: int = 900, seed: int = 0) -> np.ndarray:
    """Multi-scale blurred noise (SIFT finds plenty of features), BGR uint8 (cached: do not modify)."""
    rng = np.random.default_rng(seed)
    acc = np.zeros((h, w), np.float32)
    for sigma, weight in ((1.5, 0.6), (4.0, 1.0), (12.0, 1.5)):
        acc += weight * cv2.GaussianBlur(rng.normal(0, 1, (h, w)).astype(np.float32), (0, 0), sigma) * sigma
    acc = (acc - acc.mean()) / acc.std()
    grey = np.clip(128 + 45 * acc, 0, 255).astype(np.uint8)
    return cv2.merge([grey, np.roll(grey, 7, axis=1), np.roll(grey, 5, axis=0)])


def view(tex: np.ndarray, x: float, y: float, deg: float) -> np.ndarray:
    """A WxH window of ``tex`` centred at (tex centre + (x, y)), rotated by ``deg`` (sub-pixel, bicubic)."""
    th, tw = tex.shape[:2]
    c = ((tw - 1) / 2 + x, (th - 1) / 2 + y)
    M = cv2.getRotationMatrix2D(c, deg, 1.0)
    M[:, 2] += np.array([(W - 1) / 2, (H - 1) / 2]) - np.array(c)
    return cv2.warpAffine(tex, M, (W, H), flags=cv2.INTER_CUBIC)


def sequence(n: int, shake_px: float = 0.0, shake_deg: float = 0.0, seed: int = 1) -> list[np.ndarray]:
    """Smooth pan + slow rotation, plus i.i.d. per-frame shake of the given amplitude.

    The intended motion is slow next to the jitter high-pass (sigma = 5 frames
    at 30 fps passes ~1 % of a 200-frame-period sway), so the smooth sequence's
    jitter is close to the estimation noise.
    """
    tex = texture()
    rng = np.random.default_rng(seed)
    t = np.arange(n)
    x = 2.5 * t + 15 * np.sin(2 * math.pi * t / 200)
    y = 10 * np.sin(2 * math.pi * t / 250)
    a = 1.5 * np.sin(2 * math.pi * t / 150)
    x = x + rng.uniform(-shake_px, shake_px, n)
    y = y + rng.uniform(-shake_px, shake_px, n)
    a = a + rng.uniform(-shake_deg, shake_deg, n)
    return [view(tex, x[i], y[i], a[i]) for i in range(n)]


def about_centre(frames: list[np.ndarray], sx: float, sy: float) -> list[np.ndarray]:
    """Each frame scaled by (sx, sy) about the image centre (cv2.warpAffine)."""
    cx, cy = (W - 1) / 2, (H - 1) / 2
    M = np.float32([[sx, 0, cx * (1 - sx)], [0, sy, cy * (1 - sy)]])
    return [cv2.warpAffine(f, M, (W, H), flags=cv2.INTER_LINEAR) for f in frames]


@pytest.fixture(scope="module")
def smooth12() -> list[np.ndarray]:
    return sequence(12)


def test_identity_output_is_perfect_and_jitter_matches_input(smooth12):
    m = evaluate_sequence(smooth12, smooth12)
    assert not m.failed and m.failure_reason == ""
    assert m.cropping == pytest.approx(1.0, abs=2e-3)
    assert m.distortion == pytest.approx(1.0, abs=5e-3)
    assert m.jitter_px == pytest.approx(m.input_jitter_px, rel=1e-9, abs=1e-12)
    assert m.jitter_deg == pytest.approx(m.input_jitter_deg, rel=1e-9, abs=1e-12)
    assert m.stability == pytest.approx(m.input_stability, rel=1e-9)
    assert len(m.per_frame) == 12 and all(f.inliers >= 50 for f in m.per_frame)
    d = m.as_dict()
    assert d["cropping"] == m.cropping and "per_frame" not in d and len(m.as_dict(per_frame=True)["per_frame"]) == 12
    # the input scored as its own output shares its descriptions and pair fits: the same numbers as copies give
    apart = evaluate_sequence(smooth12, [f.copy() for f in smooth12]).as_dict(per_frame=True)
    same = m.as_dict(per_frame=True)
    apart.pop("seconds"), same.pop("seconds")
    assert same == apart


def test_zoom_in_125_gives_cropping_08(smooth12):
    m = evaluate_sequence(smooth12, about_centre(smooth12, 1.25, 1.25))
    assert not m.failed
    assert m.cropping == pytest.approx(0.8, abs=0.02)
    assert m.distortion > 0.98


def test_anisotropic_stretch_gives_distortion_09(smooth12):
    m = evaluate_sequence(smooth12, about_centre(smooth12, 1.1, 1.0))
    assert not m.failed
    assert m.distortion == pytest.approx(1 / 1.1, abs=0.015)
    assert m.cropping == pytest.approx(math.sqrt(1 / 1.1), abs=0.02)


def test_rotation_alone_is_not_distortion(smooth12):
    R = cv2.getRotationMatrix2D(((W - 1) / 2, (H - 1) / 2), 8.0, 1.0)
    m = evaluate_sequence(smooth12, [cv2.warpAffine(f, R, (W, H)) for f in smooth12])
    assert not m.failed and m.distortion > 0.98 and m.cropping == pytest.approx(1.0, abs=0.02)


def test_shaky_sequence_has_much_more_jitter_and_less_stability():
    smooth = sequence(32)
    shaky = sequence(32, shake_px=4.0, shake_deg=0.8)
    ms = evaluate_sequence(shaky, smooth)  # the shaky input stabilised into the smooth one
    mk = evaluate_sequence(smooth, shaky)  # and the reverse
    assert not ms.failed and not mk.failed
    assert mk.jitter_px > 1.0
    assert mk.jitter_px > 5 * ms.jitter_px
    assert mk.jitter_deg > 5 * ms.jitter_deg
    assert ms.stability > mk.stability + 0.2
    # (the published translation score of a panning camera is ~0.9 either way: the pan's ramp dominates the path)
    assert ms.stability_rotation > mk.stability_rotation + 0.3
    assert ms.stability_pairs > mk.stability_pairs + 0.2
    assert ms.stability_pairs_translation > mk.stability_pairs_translation
    assert ms.stability_pairs_rotation > mk.stability_pairs_rotation
    # input jitter is measured on the input frames alone: it is the other run's output jitter
    assert ms.input_jitter_px == pytest.approx(mk.jitter_px) and mk.input_jitter_px == pytest.approx(ms.jitter_px)
    assert ms.input_stability == pytest.approx(mk.stability)
    assert ms.input_stability_pairs == pytest.approx(mk.stability_pairs)
    assert ms.jitter_px < 0.2 * ms.input_jitter_px


def _still(n: int, seed: int) -> list[np.ndarray]:
    """A still camera: the same view every frame, with independent pixel noise (sigma 3 grey levels)."""
    rng = np.random.default_rng(seed)
    base = view(texture(), 0.0, 0.0, 0.0).astype(np.float32)
    return [np.clip(base + rng.normal(0.0, 3.0, base.shape), 0, 255).astype(np.uint8) for _ in range(n)]


def _shaken_still(n: int, seed: int) -> list[np.ndarray]:
    """A still camera with i.i.d. per-frame shake (+-2 px, +-0.4 deg)."""
    rng = np.random.default_rng(seed)
    return [view(texture(), *rng.uniform(-2.0, 2.0, 2), rng.uniform(-0.4, 0.4)) for _ in range(n)]


def test_still_camera_is_stable_and_a_shaken_one_is_not():
    """The published stability accumulates the path before the FFT (docs/method.md (15)-(17)).

    A still camera's per-pair motions are white estimation noise, which the per-pair score
    (``stability_pairs``, kept) calls unstable; accumulated, that noise is a slow random walk
    and the published score is high -- but not ~1: the score is scale-free, and a random
    walk puts ~85 % of its power in bins 2-6 (measured 0.77-0.87 over noise seeds at 40
    frames). I.i.d. shake of the still camera accumulates into white positions: low.
    """
    still_frames, shaken_frames = _still(40, 0), _shaken_still(40, 0)
    still = evaluate_sequence(still_frames, still_frames)
    shaken = evaluate_sequence(shaken_frames, shaken_frames)
    assert not still.failed and not shaken.failed
    assert still.stability >= 0.7 and shaken.stability <= 0.4
    assert still.stability > shaken.stability + 0.4
    assert still.stability == pytest.approx(0.5 * (still.stability_translation + still.stability_rotation))
    # the per-pair score stays available, and is what called the still camera unstable
    assert still.stability_pairs <= 0.2 and shaken.stability_pairs <= 0.1
    assert still.stability_pairs == pytest.approx(
        min(still.stability_pairs_translation, still.stability_pairs_rotation))
    d = still.as_dict()
    for k in ("stability", "stability_translation", "stability_rotation", "stability_pairs",
              "stability_pairs_translation", "stability_pairs_rotation", "input_stability", "input_stability_pairs"):
        assert k in d


def _moves(tx: float, ty: float, deg: float = 0.0) -> np.ndarray:
    """Centred homography: rotation by ``deg`` about the image centre, then a shift (tx, ty)."""
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, tx], [s, c, ty], [0.0, 0.0, 1.0]])


def test_published_stability_steps_on_known_paths():
    """docs/method.md (15)-(17) step by step on homography sequences whose scores are known in closed form."""
    L, centre = 40, (159.5, 119.5)
    t = np.arange(1, L + 1)

    def pairs_for(path_x: np.ndarray) -> np.ndarray:  # per-pair shifts whose accumulated path is path_x (from 0)
        return np.array([_moves(dx, 0.0) for dx in np.diff(np.concatenate(([0.0], path_x)))])

    # translation path 100 + 20 cos(2 pi 2 t / L): all its varying power in the 3rd bin (a kept low bin)
    st_t, st_r = path_stability(pairs_for(100 + 20 * np.cos(2 * np.pi * 2 * t / L)), centre)
    assert st_t == pytest.approx(1.0, abs=1e-9) and st_r == 1.0  # no rotation at all: scores 1
    # the same amplitude at bin 15 (high frequency): nothing in bins 2-6
    st_t, _ = path_stability(pairs_for(100 + 20 * np.cos(2 * np.pi * 15 * t / L)), centre)
    assert st_t < 1e-9
    # the path is accumulated P_t = P_{t-1} M_t (right multiplication), in pixel coordinates
    rng = np.random.default_rng(0)
    Ms = np.array([_moves(*rng.normal(0, 3, 2), rng.normal(0, 1.0)) for _ in range(12)])
    P = accumulate_path(to_pixel_origin(Ms, centre))
    C = np.array([[1.0, 0.0, centre[0]], [0.0, 1.0, centre[1]], [0.0, 0.0, 1.0]])
    expect = C @ np.linalg.multi_dot(list(Ms[:7])) @ np.linalg.inv(C)
    assert np.allclose(P[6], expect)
    assert not np.allclose(P[6], C @ np.linalg.multi_dot(list(Ms[:7][::-1])) @ np.linalg.inv(C))
    # translation and rotation of a pixel-coordinate path element: a rotation by 3 deg about the centre
    # moves the top-left origin by |(I - R) c|
    tr, rot = path_signals(to_pixel_origin(_moves(0.0, 0.0, 3.0), centre)[None])
    R = _moves(0.0, 0.0, 3.0)[:2, :2]
    assert rot[0] == pytest.approx(3.0) and tr[0] == pytest.approx(np.linalg.norm((np.eye(2) - R) @ centre))
    # bins: full FFT, DC deleted, the first (L-1)//2 kept (Nyquist of an even length excluded), first 5 over all
    n = 20
    k = np.arange(n)
    assert path_low_frequency_ratio(np.cos(np.pi * k) + 0.1 * np.cos(2 * np.pi * k / n)) == pytest.approx(1.0)
    x = np.cos(2 * np.pi * 3 * k / n) + np.cos(2 * np.pi * 8 * k / n)  # bins 3 (low) and 8 (kept, high)
    assert path_low_frequency_ratio(x) == pytest.approx(0.5)
    assert path_low_frequency_ratio(np.full(n, 7.0)) == 1.0  # no variation: nothing to stabilise


def test_black_output_frame_fails_the_sequence(smooth12):
    out = [f.copy() for f in smooth12]
    out[7][:] = 0
    m = evaluate_sequence(smooth12, out)
    assert m.failed
    assert m.cropping == m.distortion == m.stability == m.stability_pairs == 0.0
    assert m.stability_translation == m.stability_rotation == 0.0
    assert m.stability_pairs_translation == m.stability_pairs_rotation == 0.0
    assert "frame 7" in m.failure_reason and "black" in m.failure_reason


def test_unmatchable_output_frame_fails_the_sequence(smooth12):
    out = [f.copy() for f in smooth12]
    out[3] = texture(H, W, seed=99)  # unrelated content: no input-output homography
    m = evaluate_sequence(smooth12, out)
    assert m.failed and "frame 3" in m.failure_reason and "homography" in m.failure_reason
    assert m.cropping == 0.0


def test_mismatched_lengths_rejected(smooth12):
    with pytest.raises(ValueError):
        evaluate_sequence(smooth12, smooth12[:-1])


def test_low_frequency_ratio_and_jitter_signals():
    n = 60
    t = np.arange(n)
    assert low_frequency_ratio(np.sin(2 * math.pi * 2 * t / n)) == pytest.approx(1.0, abs=1e-9)
    assert low_frequency_ratio(np.sin(2 * math.pi * 20 * t / n)) < 1e-9
    assert low_frequency_ratio(np.full(n, 3.0)) == 1.0  # no variation: nothing to stabilise
    steady = np.tile([2.0, -1.0, 0.1], (n, 1))  # constant-velocity pan: no jitter (odd-reflect padding)
    assert max(trajectory_jitter(steady, 5.0)) < 1e-9
    alt = steady + np.outer((-1.0) ** t, [1.0, 0.0, 0.0])  # +-1 px alternating velocity: zig-zag of 0.5 px
    assert trajectory_jitter(alt, 5.0)[0] == pytest.approx(0.5, abs=0.05)


def test_params_validate():
    with pytest.raises(ValueError):
        MetricParams(min_inliers=2).validate()


def test_ffmpeg_baselines_frame_count_and_shape(tmp_path):
    # like the benchmark, installs Debian's ffmpeg (with libvidstab) when it is missing
    ffmpeg = ensure_ffmpeg()
    frames = sequence(20, shake_px=3.0, shake_deg=0.5)
    out = run_baselines(frames, fps=30, workdir=tmp_path, ffmpeg=ffmpeg)
    assert set(out) == {"vidstab", "deshake"}
    for name, fr in out.items():
        assert len(fr) == 20, name
        assert all(f.shape == (H, W, 3) and f.dtype == np.uint8 for f in fr), name
    assert (tmp_path / "transforms.trf").stat().st_size > 0
    assert any("vidstabtransform=" in " ".join(c) for c in out.commands.values())
    m = evaluate_sequence(frames, out["vidstab"])
    assert not m.failed and m.cropping < 1.0  # optzoom=1 zooms in


def test_a_degenerate_pair_homography_counts_as_unmatched_not_as_a_huge_jitter(smooth12, monkeypatch):
    """RANSAC on a motion-blurred frame can return a homography that flips orientation (matches along one
    streak); a consecutive pair's is then taken as unmatched and interpolated (docs/method.md 6.1), as the
    input-output fit already refused one (``sound``)."""
    from quick_stream.quality import metrics as mm

    flipped = np.array([[-217.4, -197.4, -222.9], [277.0, 251.9, 292.8], [1.89, 1.72, 1.0]])  # the measured one
    p = MetricParams()
    assert not mm.sound(flipped, p) and mm.sound(np.eye(3), p)
    assert not mm.sound(np.diag([20.0, 20.0, 1.0]), p) and not mm.sound(np.diag([1.0, -1.0, 1.0]), p)
    clean = evaluate_sequence(smooth12, smooth12)
    fit = mm.FeatureMatcher.fit
    calls = {"n": 0}

    def one_flipped_pair(self, a, b):
        r = fit(self, a, b)
        calls["n"] += 1
        if calls["n"] == 15:  # frame k >= 1 makes calls 3k - 1 (input-output), 3k (output pair k-1 -> k), 3k + 1
            # (the input pair; an output that IS its input shares the input's description and pair fit)
            return mm.PairFit(flipped, r.matches, r.inliers)
        return r

    monkeypatch.setattr(mm.FeatureMatcher, "fit", one_flipped_pair)
    m = evaluate_sequence(smooth12, [f.copy() for f in smooth12])  # copies: input and output fitted apart
    assert not m.failed and m.per_frame[4].motion_to_next is None
    assert any("1 of 11 consecutive output pairs had no homography" in w for w in m.warnings)
    assert m.jitter_px < 2 * clean.jitter_px + 0.05 and m.jitter_deg < 2 * clean.jitter_deg + 0.05


def test_a_consecutive_pair_fitted_as_a_turn_beyond_reach_counts_as_unmatched(smooth12, monkeypatch):
    """Repeated texture under motion blur (a striped carpet) can give a sound homography for the wrong copy:
    measured, a 67 deg turn with 291 inliers between two stabilized frames that are 1 px apart, which put
    the clip's jitter at 16 px. A consecutive pair fitted as turning more than max_pair_turn_deg is taken
    as unmatched and interpolated; a real turn below it is kept."""
    from quick_stream.quality import metrics as mm

    def turned(deg: float) -> np.ndarray:
        c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
        return np.array([[c, -s, -113.8], [s, c, 139.6], [0.0, 0.0, 1.0]])

    p = MetricParams()
    assert mm.sound(turned(67.3), p) and mm.motion_of(turned(67.3))[2] > p.max_pair_turn_deg
    clean = evaluate_sequence(smooth12, smooth12)
    fit = mm.FeatureMatcher.fit

    def with_pair(H):
        calls = {"n": 0}

        def one_pair(self, a, b):
            r = fit(self, a, b)
            calls["n"] += 1
            return mm.PairFit(H, r.matches, r.inliers) if calls["n"] == 15 else r
        return one_pair

    copies = [f.copy() for f in smooth12]  # input and output fitted apart: three fits a frame
    monkeypatch.setattr(mm.FeatureMatcher, "fit", with_pair(turned(67.3)))
    m = evaluate_sequence(smooth12, copies)
    assert not m.failed and m.per_frame[4].motion_to_next is None
    assert m.jitter_px < 2 * clean.jitter_px + 0.05 and m.jitter_deg < 2 * clean.jitter_deg + 0.05
    monkeypatch.setattr(mm.FeatureMatcher, "fit", with_pair(turned(20.0)))
    m = evaluate_sequence(smooth12, copies)
    assert m.per_frame[4].motion_to_next is not None and m.jitter_deg > 1.0

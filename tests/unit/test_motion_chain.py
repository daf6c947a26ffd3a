"""The motion fallback chain (docs/method.md 2.4): the pair's own noise (3i), the rotation-only fit (3j),
the covariance (3k) and the constant-velocity bridge.

Synthetic scene flow with the noise model of the tests of 2.3: pixels over the image, depths 1-4 m,
flow noise in frame t+1 and depth noise k z^2 in both frames.
"""
from __future__ import annotations

import numpy as np
import pytest

from quick_stream.core.frame import Intrinsics
from quick_stream.core.lie import get_group
from quick_stream.core.motion import MotionEstimator, MotionParams, invalid_motion, rotation_projector
from quick_stream.core.motion.chain import MotionBridge
from quick_stream.core.motion.exact import ExactParams, noise_scale
from quick_stream.core.motion.rotation import fit_rotation
from quick_stream.core.sceneflow import SceneFlowResult

K = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
SE3 = get_group("se3")


def _pixels(x):
    return np.column_stack((K.fx * x[:, 0] / x[:, 2] + K.cx, K.fy * x[:, 1] / x[:, 2] + K.cy))


def _unproject(p, z):
    return np.column_stack(((p[:, 0] - K.cx) / K.fx * z, (p[:, 1] - K.cy) / K.fy * z, z))


def flow_of(rng, M, n=2000, sigma_px=0.5, depth_noise=0.0015, seq=0):
    """Scene flow of a 3D scene (depths 1-4 m) under point motion M, with flow and depth noise."""
    p0 = np.column_stack((rng.uniform(0, 640, n), rng.uniform(0, 480, n)))
    x = _unproject(p0, rng.uniform(1.0, 4.0, n))
    y = x @ M[:3, :3].T + M[:3, 3]
    x_obs = _unproject(p0, x[:, 2] * (1 + rng.normal(0, depth_noise, n) * x[:, 2]))
    p1 = _pixels(y) + rng.normal(0, sigma_px, (n, 2))
    y_obs = _unproject(p1, y[:, 2] * (1 + rng.normal(0, depth_noise, n) * y[:, 2]))
    return SceneFlowResult(seq, seq + 1, x_obs, y_obs - x_obs, np.ones(n), p0, p1, K, K)


def point_motion(rng, rot=0.01, trans=0.01):
    return SE3.exp(np.concatenate((rng.normal(0, trans, 3), rng.normal(0, rot, 3))))


def rotation_error(R_est, R_true):
    D = R_est.T @ R_true
    return float(np.arccos(np.clip((np.trace(D) - 1) / 2, -1, 1)))


def test_noise_scale_measures_the_pairs_own_noise():
    """(3i): the lower quartile over normal noise's, 1 for expected noise, the noise's size above, capped."""
    rng = np.random.default_rng(0)
    r2 = np.linalg.norm(rng.normal(0, 1, (20000, 2)), axis=1)
    assert noise_scale(r2, 2, 10) == pytest.approx(1.0, abs=0.03)
    assert noise_scale(4 * r2, 2, 10) == pytest.approx(4.0, rel=0.03)
    assert noise_scale(0.3 * r2, 2, 10) == 1.0  # never tighter than expected
    assert noise_scale(50 * r2, 2, 10) == 10.0
    r1 = np.abs(rng.normal(0, 3, 20000))
    assert noise_scale(r1, 1, 10, 0.5) == pytest.approx(3.0, rel=0.03)
    # half the pairs off by a lot (movers): the lower quartile reads the noise's median, 1.55 x
    moved = np.concatenate((r2[:10000], 40 + r2[10000:]))
    assert noise_scale(moved, 2, 10) == pytest.approx(1.55, rel=0.05)


def test_noisier_pairs_than_expected_stay_fitted_and_accurate():
    """Blur-like flow noise (2 px against the expected 0.5) and stereo-like depth noise (0.012 z^2):
    before (3i) most pairs fell under the 25 % inlier share (invalid); now the fit holds."""
    est = MotionEstimator()
    errs = []
    for s in range(10):
        rng = np.random.default_rng(100 + s)
        M = point_motion(rng)
        m = est.estimate(flow_of(rng, M, sigma_px=2.0, depth_noise=0.012))
        assert m.valid and m.kind == "fit", m.reason
        assert m.inlier_ratio > 0.5
        errs.append(rotation_error(m.matrix[:3, :3], np.linalg.inv(M)[:3, :3]))
    assert np.degrees(np.median(errs)) < 0.05


def test_the_covariance_predicts_the_fits_error():
    """(3k): the camera twist's error, normalised by the covariance, is chi-squared with 6 degrees of
    freedom (mean 6) over many pairs, for expected and for larger-than-expected noise."""
    est = MotionEstimator()
    for sigma_px, dn in ((0.5, 0.0015), (2.0, 0.006)):
        chi = []
        for s in range(40):
            rng = np.random.default_rng(200 + s)
            M = point_motion(rng)
            m = est.estimate(flow_of(rng, M, sigma_px=sigma_px, depth_noise=dn))
            e = SE3.log(np.linalg.inv(M)) - m.twist
            chi.append(float(e @ np.linalg.solve(m.covariance, e)))
        assert 2.5 < np.mean(chi) < 15, (sigma_px, np.mean(chi))
        assert m.rotation_sigma < 0.005  # a fit is trusted fully by the path (8a)


def test_rotation_only_fit_is_exact_for_a_turning_camera_and_ignores_depth():
    """(3j): a pure rotation is recovered from the pixels alone, whatever the depth says (here: none of
    it right), to the flow noise; its covariance predicts the error."""
    chi = []
    for s in range(30):
        rng = np.random.default_rng(300 + s)
        M = point_motion(rng, rot=0.02, trans=0.0)
        fl = flow_of(rng, M, depth_noise=0.0)
        fl.points[:, 2] *= rng.uniform(0.3, 3.0, len(fl))  # depth garbage: unused
        r = fit_rotation(fl.pixels, fl.pixels_next, K.K, K.K, fl.weights, ExactParams())
        w = SE3.log(np.vstack([np.hstack([r.R @ M[:3, :3].T, np.zeros((3, 1))]), [0, 0, 0, 1]]))[3:]
        chi.append(float(w @ np.linalg.solve(r.covariance, w)))
        assert rotation_error(r.R, M[:3, :3]) < 2e-4
        assert r.inlier_ratio > 0.8
    assert 1.0 < np.mean(chi) < 8, np.mean(chi)


def test_a_fit_that_does_not_hold_falls_back_to_the_rotation_only_fit():
    """Too few pairs agree with one rigid motion (half of them garbage beyond the lower quartile's
    reach is not enough; here the scene flow's depths are scrambled): the fit is not taken, the
    rotation-only fit is, named, with translation 0 and a covariance saying the translation is unknown."""
    rng = np.random.default_rng(7)
    M = point_motion(rng, trans=0.003)
    fl = flow_of(rng, M)
    fl.points[:, 2] *= rng.uniform(0.2, 5.0, len(fl))  # depth unrelated to the flow
    fl.displacements = fl.displacements * 0.0 + rng.normal(0, 0.3, fl.displacements.shape)
    m = MotionEstimator().estimate(fl)
    assert m.valid and m.kind == "rotation", m.reason
    assert "rotation-only fit of the same flow used" in m.reason
    np.testing.assert_array_equal(m.matrix[:3, 3], 0.0)
    assert rotation_error(m.matrix[:3, :3], np.linalg.inv(M)[:3, :3]) < np.radians(0.1)
    assert np.all(np.diag(m.covariance)[:3] == 1.0)  # translation: not estimated
    P = rotation_projector(SE3)
    assert np.trace(P @ m.covariance @ P.T) < 1e-5
    off = MotionEstimator(MotionParams(rotation_fallback=False)).estimate(fl)
    assert not off.valid and off.kind == "none"


def test_bridge_repeats_the_last_known_motion_for_a_few_frames_then_gives_up():
    rng = np.random.default_rng(9)
    est = MotionEstimator()
    known = est.estimate(flow_of(rng, point_motion(rng), seq=0))
    bridge = MotionBridge(3)
    assert bridge.take(known) is known
    none = [invalid_motion(i, i + 1, "se3", "exact", "too little image contrast") for i in (1, 2, 3, 4)]
    out = [bridge.take(m) for m in none]
    for k, b in enumerate(out[:3], 1):
        assert b.valid and b.kind == "bridge" and "contrast" in b.reason and f"({k} of at most 3" in b.reason
        np.testing.assert_allclose(b.matrix, known.matrix, atol=1e-12)
        assert b.rotation_sigma > known.rotation_sigma
    assert out[1].rotation_sigma > out[0].rotation_sigma  # less certain the longer the hole
    assert not out[3].valid and out[3].kind == "none"  # beyond the bridge: the path restarts
    assert bridge.bridges == 3
    # after a restart nothing is known: the next hole is not bridged until a motion is known again
    assert not bridge.take(invalid_motion(5, 6, "se3", "exact", "x")).valid
    bridge.take(known)
    gap = bridge.take(invalid_motion(6, 8, "se3", "exact", "frames skipped upstream"), steps=2)
    assert gap.kind == "bridge"
    np.testing.assert_allclose(gap.twist, 2 * known.twist, atol=1e-12)  # two frame steps at that velocity
    assert not MotionBridge(0).take(invalid_motion(0, 1, "se3", "exact", "x")).valid

"""Observability of the exact estimator's fit (docs/method.md section 2.3).

Synthetic RGB-D scene flow with the estimator's own noise model: 0.5 px optical-flow noise in
frame t+1, depth noise 0.0015 z^2 in both frames. A wall (points on one plane) does not determine
the out-of-plane column of a GA(3)/SA(3) linear part; collinear points do not determine a rotation.
Such motions must not be reported as valid fits of the requested group.
"""
import numpy as np
import pytest

from quick_stream.core.frame import Intrinsics
from quick_stream.core.lie import get_group
from quick_stream.core.motion import MotionEstimator, MotionParams
from quick_stream.core.motion.exact import ExactParams
from quick_stream.core.sceneflow import SceneFlowResult
from quick_stream.quality.evaluation.rpe import relative_pose_error

K = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
SIGMA_PX, DEPTH_NOISE = 0.5, 0.0015  # ExactParams' noise model
MAX_MM, MAX_DEG = 5.0, 0.1  # the accuracy a motion marked valid must have here
FALLBACK = {"ga3": "sim3", "sa3": "se3"}  # docs/method.md 2.3


def _pixels(x):
    return np.column_stack((K.fx * x[:, 0] / x[:, 2] + K.cx, K.fy * x[:, 1] / x[:, 2] + K.cy))


def _unproject(p, z):
    return np.column_stack(((p[:, 0] - K.cx) / K.fx * z, (p[:, 1] - K.cy) / K.fy * z, z))


def plane(rng, n=3000, z0=2.0, relief=0.0):
    """A textured wall: pixels all over the image on a plane ~z0 m away, tilted by up to 0.3,
    plus uniform relief (m, peak to peak) off the plane."""
    p = np.column_stack((rng.uniform(0, 640, n), rng.uniform(0, 480, n)))
    a, b = rng.uniform(-0.3, 0.3, 2)
    z = z0 / (1 - a * (p[:, 0] - K.cx) / K.fx - b * (p[:, 1] - K.cy) / K.fy)
    return _unproject(p, z + relief * (rng.uniform(size=n) - 0.5))


def box(rng, n=3000):
    """A full 3D scene: pixels all over the image, depths 1-4 m."""
    p = np.column_stack((rng.uniform(0, 640, n), rng.uniform(0, 480, n)))
    return _unproject(p, rng.uniform(1.0, 4.0, n))


def line(rng, n=3000):
    """Points along one 2 m line segment (a pole, an edge) about 2 m away."""
    d = np.array([0.3, 1.0, 0.4]) / np.linalg.norm([0.3, 1.0, 0.4])
    return np.array([0.1, 0.0, 2.0]) + rng.uniform(-1, 1, n)[:, None] * d


def camera_motion(rng):
    """Point motion of a hand-held camera between two frames: ~1 cm, ~0.6 deg."""
    return get_group("se3").exp(np.concatenate((rng.normal(0, 0.01, 3), rng.normal(0, 0.01, 3))))


def noisy_flow(x, M, rng):
    """Scene flow of true points x under point motion M with flow and depth noise."""
    y = x @ M[:3, :3].T + M[:3, 3]
    p0 = _pixels(x)
    x_obs = _unproject(p0, x[:, 2] + rng.normal(0, 1, len(x)) * DEPTH_NOISE * x[:, 2] ** 2)
    p1 = _pixels(y) + rng.normal(0, SIGMA_PX, (len(y), 2))
    y_obs = _unproject(p1, y[:, 2] + rng.normal(0, 1, len(y)) * DEPTH_NOISE * y[:, 2] ** 2)
    return SceneFlowResult(0, 1, x_obs, y_obs - x_obs, np.ones(len(x)), p0, p1, K, K)


def estimates(group, scene, seeds=range(10), rotation_fallback=True, **kw):
    """(estimate, true camera motion) for each seed."""
    est = MotionEstimator(MotionParams(group=group, rotation_fallback=rotation_fallback))
    out = []
    for s in seeds:
        rng = np.random.default_rng(1000 + s)
        x = scene(rng, **kw)
        M = camera_motion(rng)
        out.append((est.estimate(noisy_flow(x, M, rng)), np.linalg.inv(M)))
    return out


def off(m, truth):
    rot, mm = relative_pose_error(m.matrix, truth)
    return rot > MAX_DEG or mm > MAX_MM


def bad_fits(results):
    """Motions marked valid as fits of the requested group (no fallback) but off by more than the bounds."""
    return [(relative_pose_error(m.matrix, t), m.reason) for m, t in results
            if m.valid and m.kind == "fit" and not m.fallback and off(m, t)]


@pytest.mark.parametrize("relief", [0.002, 0.05], ids=["textured_plane", "5cm_relief"])
@pytest.mark.parametrize("group", ["ga3", "sa3"])
def test_affine_fit_of_a_wall_falls_back_to_the_rigid_fit(group, relief):
    res = estimates(group, plane, relief=relief)
    assert not bad_fits(res)
    G = get_group(group)
    for m, truth in res:
        assert m.valid, m.reason
        assert m.fallback == FALLBACK[group] and "not determined" in m.reason
        assert not off(m, truth), relative_pose_error(m.matrix, truth)
        # the fallback is an element of the requested group, in its chart
        np.testing.assert_allclose(G.exp(m.twist), m.matrix, atol=1e-9)
        np.testing.assert_allclose(G.exp(m.zeta_bar), np.linalg.inv(m.matrix), atol=1e-9)
        if group == "sa3":
            assert np.linalg.det(m.matrix[:3, :3]) == pytest.approx(1.0, abs=1e-9)


@pytest.mark.parametrize("group", ["ga3", "sa3"])
def test_affine_fit_is_kept_where_the_points_determine_it(group):
    """A 3D scene and a wall with 1 m of relief (rho_3 ~ 1000 at 2 m) keep the group's own fit."""
    for m, truth in estimates(group, box) + estimates(group, plane, relief=1.0):
        assert m.valid and not getattr(m, "fallback", "") and m.reason == ""
        assert not off(m, truth), relative_pose_error(m.matrix, truth)


def rotation_error_deg(m, truth):
    R = m.matrix[:3, :3].T @ truth[:3, :3]
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


@pytest.mark.parametrize("group", ["se3", "sim3", "sa3", "ga3"])
def test_collinear_points_fall_back_to_the_rotation_only_fit(group):
    """A line does not determine the rigid fit's rotation about it, but its pixels' flow still says how
    the camera turned (docs/method.md 2.4): the rotation-only fit, named, with no translation, off
    by no more than the parallax of the camera's translation (|t| / z, here ~1 cm at 2 m)."""
    res = estimates(group, line)
    assert not bad_fits(res)
    for m, truth in res:
        assert m.valid and m.kind == "rotation", m.reason
        assert "rotation not determined" in m.reason and "rotation-only fit" in m.reason, m.reason
        np.testing.assert_array_equal(m.matrix[:3, 3], 0.0)
        parallax = np.degrees(np.linalg.norm(truth[:3, 3]) / 2.0)
        assert rotation_error_deg(m, truth) < 1.5 * parallax + 0.05
        assert 0 < m.rotation_sigma < np.inf


def test_collinear_points_give_an_invalid_motion_without_the_rotation_fallback():
    for m, _ in estimates("se3", line, rotation_fallback=False):
        assert not m.valid and m.kind == "none" and "rotation not determined" in m.reason, m.reason
        np.testing.assert_array_equal(m.matrix, np.eye(4))


def test_too_few_distinct_points_leave_the_rotation_only():
    """Many pairs, but only two distinct points: nothing fixes the rigid rotation about their line;
    two bearings still fix the camera's rotation (docs/method.md (3j))."""
    rng = np.random.default_rng(3)
    x = np.repeat(box(rng, 2), 100, axis=0)
    M = camera_motion(rng)
    y = x @ M[:3, :3].T + M[:3, 3]
    flow = SceneFlowResult(0, 1, x, y - x, np.ones(len(x)), _pixels(x), _pixels(y), K, K)
    for group in ("se3", "ga3"):
        m = MotionEstimator(MotionParams(group=group)).estimate(flow)
        assert m.valid and m.kind == "rotation" and "rotation not determined" in m.reason, m.reason
        m = MotionEstimator(MotionParams(group=group, rotation_fallback=False)).estimate(flow)
        assert not m.valid and "rotation not determined" in m.reason, m.reason


def test_spread_test_is_in_units_of_the_point_noise():
    """docs/method.md (3b): rho = eig(C) / s^2 and eps(r) = 1/r + 1/sqrt(n_eff r)."""
    from quick_stream.core.motion.observability import RIGID_FALLBACK, observability

    assert RIGID_FALLBACK == FALLBACK
    p = ExactParams()
    rng = np.random.default_rng(4)
    x = box(rng, 500)
    w = rng.uniform(0.5, 1.0, len(x))
    o = observability(x, w, K.fx, p)
    wn = w / w.sum()
    xc = x - wn @ x
    z = x[:, 2]
    s2 = wn @ ((p.depth_noise * z * z) ** 2 + (z * p.sigma_px / K.fx) ** 2)
    rho = np.sort(np.linalg.eigvalsh((xc * wn[:, None]).T @ xc))[::-1] / s2
    np.testing.assert_allclose(o.rho, rho, rtol=1e-9)
    assert o.n_eff == pytest.approx(w.sum() ** 2 / (w @ w))
    assert o.affine_error == pytest.approx(1 / rho[2] + 1 / np.sqrt(o.n_eff * rho[2]))
    assert o.rigid_error == pytest.approx(1 / (rho[1] + rho[2]) + 1 / np.sqrt(o.n_eff * (rho[1] + rho[2])))
    assert o.error("ga3") == o.error("sa3") == o.affine_error
    assert o.error("se3") == o.error("sim3") == o.rigid_error
    # noise-free points on a plane: the affine part has no support at all, the rigid part does
    flat = plane(rng, 500)
    flat = flat / flat[:, 2:] * 2.0  # exactly z = 2
    o = observability(flat, np.ones(len(flat)), K.fx, p)
    assert o.affine_error > 1e6 and o.rigid_error < p.max_spread_error
    # collinear points support neither
    assert observability(line(rng, 500), np.ones(500), K.fx, p).rigid_error > 1e6
    assert observability(x, np.zeros(len(x)), K.fx, p).rigid_error == np.inf

"""An object moving in front of the background (docs/method.md 2.2, 2.3, (3l)).

Synthetic RGB-D scene flow with the estimator's own noise model (as in test_motion_observability.py):
0.5 px flow noise in frame t+1, depth noise 0.0015 z^2 in both frames, a hand-held camera (~1 cm,
~0.6 deg). Two backgrounds:

* a wall ~2 m away (tilted, 1 cm relief) with a rectangle of the view replaced by an object 1-1.5 m
  away that translates 2-5 cm between the frames: the object's depth gives the points the
  out-of-plane spread (3b) asks of GA(3)/SA(3), and an affine map fits wall and object at once (its
  out-of-plane column carries the object's translation), so before (3l) both groups took the
  object's motion as a determined fit, 50-180 mm / 0.6-2 deg off;
* a 3D scene 1-4 m deep with the left part of the view moving with an object (3 cm + 1.7 deg):
  SIM(3), SA(3) and GA(3) ended up between camera and object (0.7 deg off at 45 %), SE(3) did not.

And a motion with a real scale or affine part stays fitted in full: keeping to the rigid fit's
consensus (3m) is only taken when the group's own fit explains that consensus worse (3l).
"""
import numpy as np
import pytest

from quick_stream.core.lie import get_group
from quick_stream.core.motion import MotionEstimator, MotionParams
from quick_stream.core.sceneflow import SceneFlowResult
from quick_stream.quality.evaluation.rpe import relative_pose_error

from .test_motion_observability import DEPTH_NOISE, FALLBACK, K, SIGMA_PX, _pixels, _unproject, camera_motion, off

SEEDS = range(10)


def wall_with_object(rng, share, n=3000):
    """A wall ~2 m away (tilted by up to 0.3, 1 cm relief) and, over a rectangle of ``share`` of the
    view, an object 1-1.5 m away (5 cm relief) translating 2-5 cm in a random direction.
    Returns the points, the object's mask and its translation (m, camera t+1 axes)."""
    p = np.column_stack((rng.uniform(0, 640, n), rng.uniform(0, 480, n)))
    a, b = rng.uniform(-0.3, 0.3, 2)
    z = 2.0 / (1 - a * (p[:, 0] - K.cx) / K.fx - b * (p[:, 1] - K.cy) / K.fy) + 0.01 * (rng.uniform(size=n) - 0.5)
    fw = min(np.sqrt(share) * rng.uniform(0.8, 1.25), 1.0)
    fh = min(share / fw, 1.0)
    x0, y0 = rng.uniform(0, 1 - fw) * 640, rng.uniform(0, 1 - fh) * 480
    obj = (p[:, 0] >= x0) & (p[:, 0] < x0 + fw * 640) & (p[:, 1] >= y0) & (p[:, 1] < y0 + fh * 480)
    z[obj] = rng.uniform(1.0, 1.5) + 0.05 * (rng.uniform(size=obj.sum()) - 0.5)
    d = rng.normal(size=3)
    return _unproject(p, z), obj, d / np.linalg.norm(d) * rng.uniform(0.02, 0.05)


def box_with_object(rng, share, n=3000):
    """A 3D scene (depths 1-4 m) with the left ``share`` of the view on an object that moves by 3 cm and
    turns 1.7 deg. Returns the points, the object's mask and its point motion (camera t+1 axes)."""
    p = np.column_stack((rng.uniform(0, 640, n), rng.uniform(0, 480, n)))
    obj = p[:, 0] < np.quantile(p[:, 0], share)
    return _unproject(p, rng.uniform(1.0, 4.0, n)), obj, get_group("se3").exp(np.array([0.03, 0, -0.012, 0, 0.03, 0]))


def flow_with_object(x, M, obj, obj_motion, rng):
    """Noisy scene flow of the points ``x`` under the camera's point motion ``M``; the object's points
    move on by ``obj_motion`` (a translation, or a 4x4 point motion)."""
    y = x @ M[:3, :3].T + M[:3, 3]
    if np.shape(obj_motion) == (4, 4):
        y[obj] = y[obj] @ obj_motion[:3, :3].T + obj_motion[:3, 3]
    else:
        y[obj] += obj_motion
    p0 = _pixels(x)
    x_obs = _unproject(p0, x[:, 2] + rng.normal(0, 1, len(x)) * DEPTH_NOISE * x[:, 2] ** 2)
    p1 = _pixels(y) + rng.normal(0, SIGMA_PX, (len(y), 2))
    y_obs = _unproject(p1, y[:, 2] + rng.normal(0, 1, len(y)) * DEPTH_NOISE * y[:, 2] ** 2)
    return SceneFlowResult(0, 1, x_obs, y_obs - x_obs, np.ones(len(x)), p0, p1, K, K)


def flows(scene, share):
    """(flow, true camera motion) for each seed."""
    for s in SEEDS:
        rng = np.random.default_rng(7000 + s)
        x, obj, motion = scene(rng, share)
        M = camera_motion(rng)
        yield flow_with_object(x, M, obj, motion, rng), np.linalg.inv(M)


@pytest.mark.parametrize("group", ["ga3", "sa3"])
def test_an_object_in_front_of_a_wall_does_not_determine_the_affine_fit(group):
    """10 % of the view 1-1.5 m away, moving 2-5 cm, in front of a wall: the affine part is determined
    only by pairs the rigid fit rejects, so the fit falls back (2.3, (3l)) and stays with the wall."""
    for flow, truth in flows(wall_with_object, 0.1):
        m = MotionEstimator(MotionParams(group=group)).estimate(flow)
        assert m.valid and m.kind == "fit", m.reason
        assert m.fallback == FALLBACK[group] and "not determined" in m.reason, (m.reason, relative_pose_error(
            m.matrix, truth))
        assert not off(m, truth), relative_pose_error(m.matrix, truth)


@pytest.mark.parametrize("group", ["ga3", "sa3"])
def test_with_an_object_over_30_percent_of_a_wall_the_affine_fit_falls_back_wherever_the_rigid_fit_rejects_it(group):
    """30 % of the view on the object: wherever the SE(3) fit leaves the object out (its inliers: the
    wall's 70 %), the affine group falls back to its rigid fit, the very motion that group gives. Where the
    SE(3) fit itself takes the object in (its measured noise (3i) widened by the object's pull, a limit
    docs/method.md 2.3 states), nothing gates the affine fit; not asserted here."""
    gated = 0
    for flow, _ in flows(wall_with_object, 0.3):
        if MotionEstimator(MotionParams(group="se3")).estimate(flow).inlier_ratio > 0.8:
            continue  # the rigid fit took the object in
        gated += 1
        m = MotionEstimator(MotionParams(group=group)).estimate(flow)
        assert m.valid and m.kind == "fit", m.reason
        assert m.fallback == FALLBACK[group] and "not determined" in m.reason, m.reason
        rigid = MotionEstimator(MotionParams(group=FALLBACK[group])).estimate(flow)
        np.testing.assert_allclose(m.matrix, rigid.matrix, atol=1e-9)
    assert gated >= 8


@pytest.mark.parametrize("share", [0.3, 0.45])
@pytest.mark.parametrize("group", ["se3", "sim3", "sa3", "ga3"])
def test_every_group_stays_with_a_3d_background_when_an_object_moves_across_it(group, share):
    """An object over 30 % / 45 % of a 3D scene: each group's own fit (no fallback) stays with the
    background; the larger groups start from and keep to the SE(3) fit's consensus (3l)."""
    for flow, truth in flows(box_with_object, share):
        m = MotionEstimator(MotionParams(group=group)).estimate(flow)
        assert m.valid and m.kind == "fit" and not m.fallback, m.reason
        assert not off(m, truth), relative_pose_error(m.matrix, truth)
        assert m.inlier_ratio < 1 - 0.8 * share  # the object's pairs are not counted as agreeing


@pytest.mark.parametrize("group", ["sim3", "sa3", "ga3"])
def test_a_motion_with_a_real_scale_or_affine_part_is_fitted_in_full(group):
    """A 3 % scale / affine part that the whole (static) scene shows: the group's fit from the SE(3) fit
    explains the rigid fit's consensus better than the rigid fit (3l), so it keeps every pair's own
    weight; fitted on the rigid fit's weights alone (3m), SA(3) was 5e-2 / 8 mm off."""
    from .test_motion_observability import box, noisy_flow

    G = get_group(group)
    for s in range(5):
        rng = np.random.default_rng(900 + s)
        x = box(rng)
        xi = rng.normal(0, 0.03, G.dim)
        xi[:6] = rng.normal(0, 0.01, 6)
        M = G.exp(xi)
        m = MotionEstimator(MotionParams(group=group)).estimate(noisy_flow(x, M, rng))
        assert m.valid and m.kind == "fit" and not m.fallback, m.reason
        err = np.abs(m.matrix - np.linalg.inv(M))
        assert err[:3, :3].max() < 1e-3 and err[:3, 3].max() < 1e-3, err
        assert m.inlier_ratio > 0.9

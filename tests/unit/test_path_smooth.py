"""Smoothed path with a crop budget: the smoother, the budget, the zoom track and the release pattern."""
import numpy as np
import pytest

from quick_stream.core.frame import Intrinsics
from quick_stream.core.lie import get_group
from quick_stream.core.motion import MotionEstimate
from quick_stream.core.path.budget import BudgetParams
from quick_stream.core.path.frame_model import FrameModel, SegmentMeshes
from quick_stream.core.path.keyframes import KeyframeParams
from quick_stream.core.path.planner import PathPlanner, PlannerParams
from quick_stream.core.path.smoother import cutoff_of_smoothness, segment_system, smoothness_for_cutoff
from quick_stream.core.render.shape_term import rotation_reference
from quick_stream.core.render.warp import WarpParams, grid_geometry, solve_mesh

SE3 = get_group("se3")
K = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)


def scene_model(rng, n=300) -> FrameModel:
    """3D points 1-4 m in front of the camera over the whole image, as a frame model."""
    px = np.column_stack((rng.uniform(0, 639, n), rng.uniform(0, 479, n)))
    z = rng.uniform(1.0, 4.0, n)
    pts = np.column_stack(((px[:, 0] - K.cx) * z / K.fx, (px[:, 1] - K.cy) * z / K.fy, z))
    return FrameModel.from_points(640, 480, K, px, pts, 256)


def shaky_motions(rng, frames, shake_deg, pan_deg=0.2):
    """Camera motions: a steady pan plus white rotational shake (degrees per frame, RMS per axis)."""
    out = []
    for i in range(frames):
        xi = np.zeros(6)
        xi[:3] = [0.004, 0.0, 0.001]
        xi[3:] = np.radians(rng.normal(0, shake_deg, 3) + [0, pan_deg, 0])
        g = SE3.exp(xi)
        out.append(MotionEstimate(i, i + 1, "se3", "truth", g, xi, True))
    return out


def run(motions, params, models=None):
    pl = PathPlanner(params)
    released = [pl.start(0)]
    for i, m in enumerate(motions):
        released.append(pl.push(m, None if models is None else models[i]))
    released.append(pl.finish())
    return pl, released


def test_smoothness_cutoff_formula_is_the_interior_gain():
    lam = smoothness_for_cutoff(1.0, 30.0)
    assert cutoff_of_smoothness(lam, 30.0) == pytest.approx(1.0)
    N = 600
    sysm = segment_system(N, 1, lam)
    for f_hz, gain in ((1.0, 0.5), (0.3, None), (3.0, None)):
        w = 2 * np.pi * f_hz / 30.0
        x = np.sin(w * np.arange(1, N + 1))[:, None]
        p = sysm.unconstrained(x, np.zeros((1, 1)))[:, 0]
        mid = slice(200, 400)
        measured = np.sqrt(np.mean(p[mid] ** 2) / np.mean(x[mid, 0] ** 2))
        expected = 1.0 / (1.0 + 4.0 * lam * (1.0 - np.cos(w)) ** 2)
        assert measured == pytest.approx(expected, rel=0.02, abs=2e-3)
        if gain is not None:
            assert expected == pytest.approx(gain)


def test_segments_join_with_continuous_position_and_velocity():
    rng = np.random.default_rng(1)
    motions = shaky_motions(rng, 150, 0.5)
    params = PlannerParams(budget=BudgetParams(max_zoom=0))
    pl, released = run(motions, params)
    corr = {c.seq: c.matrix for b in released for c in b}
    assert sorted(corr) == list(range(151))
    gc = [np.eye(4)]
    for m in motions:
        gc.append(gc[-1] @ m.matrix)
    P = np.array(gc) @ np.array([corr[s] for s in range(151)])  # the stabilized camera
    angles = SE3.log(np.linalg.inv(P[:-1]) @ P[1:])[:, 3:]  # its velocity
    acc = np.linalg.norm(np.diff(angles, axis=0), axis=1)
    ends = [s.end_seq for s in pl.segments[:-1]]
    raw_acc = np.linalg.norm(np.diff(np.array([m.twist[3:] for m in motions]), axis=0), axis=1)
    # at the joins the stabilized camera accelerates no more than anywhere else, and far less than the shake
    assert max(acc[e - 1] for e in ends) < 4 * np.median(acc) and acc.max() < 0.05 * np.median(raw_acc)


def test_release_pattern_with_lookahead_covers_every_frame_once_within_the_window():
    rng = np.random.default_rng(2)
    motions = shaky_motions(rng, 95, 0.3)
    params = PlannerParams(keyframes=KeyframeParams(interval=30, min_interval=10), lookahead=20,
                           budget=BudgetParams(max_zoom=0))
    pl = PathPlanner(params)
    out = [(0, c) for c in pl.start(0)]
    for i, m in enumerate(motions):
        out += [(m.seq_next, c) for c in pl.push(m)]  # released when frame m.seq_next arrived
    out += [(95, c) for c in pl.finish()]
    assert [c.seq for _, c in out] == list(range(96))
    waits = [now - c.seq for now, c in out]
    # released 10 at a time, each once >= 20 frames after it were seen, none waiting longer than the window
    assert max(waits) == 29 and min(waits[:-20]) == 20
    assert [c.seq for _, c in out if c.keyframe] == [9, 19, 29, 39, 49, 59, 69, 95]


def test_model_mesh_is_the_renderers_mesh():
    rng = np.random.default_rng(3)
    m = scene_model(rng)
    C = SE3.exp(np.array([0.02, -0.01, 0.01, 0.03, -0.02, 0.01]))
    T = np.linalg.inv(C)
    y = m.points @ T[:3, :3].T + T[:3, 3]
    tgt = np.column_stack((K.fx * y[:, 0] / y[:, 2] + K.cx, K.fy * y[:, 1] / y[:, 2] + K.cy))
    for reference in ("rotation", "input"):
        w = WarpParams(shape_reference=reference)
        ref = rotation_reference(K, T, grid_geometry(640, 480, 2, 2).src) if reference == "rotation" else None
        mesh = solve_mesh(m.pixels, tgt, 640, 480, w, ref)
        V = SegmentMeshes([m], w).vertices(np.array([0]), T[None, None])[0, 0]
        np.testing.assert_allclose(V, mesh.dst, atol=1e-9)


def budget_run(max_zoom, seed=4, crop_weight=1.0):
    rng = np.random.default_rng(seed)
    motions = shaky_motions(rng, 60, 1.2)
    models = [scene_model(rng) for _ in motions]
    params = PlannerParams(budget=BudgetParams(max_zoom=max_zoom, crop_weight=crop_weight, fill=0.0))
    pl, released = run(motions, params, models)
    corr = {c.seq: c for b in released for c in b}
    worst = []
    for s in range(1, 61):
        mesh = SegmentMeshes([models[s - 1]], WarpParams())
        m = mesh.margins(np.array([0]), corr[s].matrix[None, None], 1.1, 0.0)[0, 0] * mesh.half(0)
        worst.append(float(m.min()))  # px between the zoom-1.1 crop and the border (< 0: a border shows)
    return pl, corr, np.array(worst)


def test_crop_budget_holds_on_every_frame_and_segments_meet_their_end_constraints():
    _, _, free = budget_run(0)
    assert free.min() < -10  # without a budget this shake needs far more than zoom 1.1
    pl, corr, worst = budget_run(1.1)
    assert worst.min() >= 0.5  # the budget's 1 px margin, up to the margins' linearisation
    assert all(s.converged and s.residual < 1e-9 for s in pl.segments)
    assert all(c.zoom is not None and 1.0 <= c.zoom <= 1.1 + 1e-9 for c in corr.values())


def test_a_budget_far_away_reproduces_the_unconstrained_path():
    _, free, _ = budget_run(0)
    _, far, _ = budget_run(3.0)
    for s in free:
        np.testing.assert_array_equal(free[s].matrix, far[s].matrix)
    assert all(c.zoom is None for c in free.values()) and all(c.zoom is not None for c in far.values())


def test_zoom_track_is_smooth_border_free_and_within_the_budget():
    rng = np.random.default_rng(5)
    motions = shaky_motions(rng, 90, 0.8)
    models = [scene_model(rng) for _ in motions]
    pl, released = run(motions, PlannerParams(budget=BudgetParams(max_zoom=1.12, fill=0.0)), models)
    corr = {c.seq: c for b in released for c in b}
    z = np.array([corr[s].zoom for s in range(91)])
    assert np.all(z >= 1.0) and np.all(z <= 1.12 + 1e-9) and z.max() > 1.03  # the shake needs zoom, within Z
    for s in range(1, 91):  # border-free at the planned zoom (on the model, with its 1 px margin)
        mesh = SegmentMeshes([models[s - 1]], WarpParams())
        m = mesh.margins(np.array([0]), corr[s].matrix[None, None], corr[s].zoom, 0.0)[0, 0] * mesh.half(0)
        assert m.min() >= 0.5, s
    dz = np.diff(z)
    moving = dz[np.abs(dz) > 1e-4]
    flips = np.count_nonzero(np.diff(np.sign(moving)))
    assert flips <= len(dz) // 6, flips  # rises and falls over several frames each: no per-frame zoom jitter
    assert np.abs(dz).max() < 0.04 and np.abs(np.diff(z, 2)).max() < 0.04
    # the zoom continues across windows: steps at the joins are no larger than elsewhere
    joins = [s.end_seq for s in pl.segments[:-1]]
    assert max(abs(dz[j]) for j in joins) <= np.abs(dz).max()



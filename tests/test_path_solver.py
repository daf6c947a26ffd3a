"""Optimal path per segment: end-constraints, closed forms, reference optimiser, composition order."""
import numpy as np
import pytest
from scipy.optimize import NonlinearConstraint, minimize

from quick_stream.lie import GROUPS, get_group
from quick_stream.path import PathParams, integrate, path_cost, solve_segment, zeta_bar


def random_segment(group, rng, n_frames=12, rot=0.03, trans=0.01):
    xi = rng.normal(0, rot, (n_frames, group.dim))
    xi[:, :3] = rng.normal(0, trans, (n_frames, 3))
    C1 = group.exp(np.concatenate([rng.normal(0, trans, 3), rng.normal(0, rot, group.dim - 3)]))
    return group.exp(xi), C1


def reference_cost(group, motions, C0, C1, w=None):
    """A generic constrained optimiser (SLSQP) on the same discrete problem."""
    zb = zeta_bar(group, motions)
    N, n = zb.shape
    w = np.ones(n) if w is None else np.asarray(w)

    def cons(z):
        return group.vee(np.linalg.inv(C1) @ integrate(group, C0, z.reshape(N, n))[-1] - np.eye(4))

    def cost(z):
        return path_cost(z.reshape(N, n), zb, w)

    def grad(z):
        return ((z.reshape(N, n) - zb) * w).ravel()

    res = minimize(cost, zb.ravel(), jac=grad, constraints=[{"type": "eq", "fun": cons}], method="SLSQP",
                   options={"ftol": 1e-15, "maxiter": 500})
    if not res.success:  # SLSQP's subproblem can go rank-deficient: a second generic method
        res = minimize(cost, zb.ravel(), jac=grad, method="trust-constr",
                       constraints=[NonlinearConstraint(cons, 0.0, 0.0)],
                       options={"gtol": 1e-12, "xtol": 1e-14, "maxiter": 3000})
    assert res.success, res.message
    assert np.linalg.norm(cons(res.x)) < 1e-8
    return res.fun


@pytest.mark.parametrize("name", sorted(GROUPS))
def test_meets_end_constraints_and_matches_reference_optimiser(name):
    g = get_group(name)
    rng = np.random.default_rng(sorted(GROUPS).index(name))
    for trial in range(2):
        motions, C1 = random_segment(g, rng)
        C0 = g.exp(rng.normal(0, 0.01, g.dim))
        sol = solve_segment(g, motions, C0, C1)
        assert sol.converged, sol.reason
        assert sol.residual < 1e-9
        np.testing.assert_allclose(sol.corrections[0], C0)
        np.testing.assert_allclose(sol.corrections[-1], C1, atol=1e-9)
        ref = reference_cost(g, motions, C0, C1)
        assert abs(sol.cost - ref) <= 1e-3 * ref, (sol.cost, ref)
        assert sol.cost <= ref * (1 + 1e-6)  # never worse than the generic optimiser


def test_weights_change_the_optimum_and_still_match_reference():
    g = get_group("se3")
    rng = np.random.default_rng(3)
    motions, C1 = random_segment(g, rng)
    w = (1.0, 1.0, 1.0, 10.0, 10.0, 10.0)
    sol_w = solve_segment(g, motions, None, C1, PathParams(weights=w))
    sol_1 = solve_segment(g, motions, None, C1)
    assert np.abs(sol_w.zeta - sol_1.zeta).max() > 1e-5
    ref = reference_cost(g, motions, np.eye(4), C1, w)
    assert abs(sol_w.cost - ref) <= 1e-3 * ref
    with pytest.raises(ValueError, match="6 positive numbers"):
        solve_segment(g, motions, None, C1, PathParams(weights=(1.0, 2.0)))


def test_commuting_case_pure_translation_is_the_closed_form():
    """Pure translations commute: zeta = zeta_bar + c with c spreading the end-constraint evenly.

    In SE(3) the optimum may still trade a tiny rotation for translation (a rotation
    at frame t swings every later translation: the ad coupling), a second-order
    effect |c| |sum of translations|; with rotations weighted out it vanishes and
    the closed form is exact.
    """
    g = get_group("se3")
    rng = np.random.default_rng(4)
    xi = np.zeros((20, 6))
    xi[:, :3] = rng.normal(0, 0.01, (20, 3))
    C1 = g.exp(np.array([0.02, -0.01, 0.005, 0, 0, 0]))
    zb = zeta_bar(g, g.exp(xi))
    closed = zb + (g.log(C1) - zb.sum(0)) / 20
    sol = solve_segment(g, g.exp(xi), None, C1)
    np.testing.assert_allclose(sol.zeta, closed, atol=2e-4)
    stiff = solve_segment(g, g.exp(xi), None, C1, PathParams(weights=(1, 1, 1, 1e8, 1e8, 1e8)))
    np.testing.assert_allclose(stiff.zeta, closed, atol=1e-9)


@pytest.mark.parametrize("name", ["se3", "sim3"])
def test_commuting_case_one_rotation_axis_is_the_closed_form(name):
    g = get_group(name)
    rng = np.random.default_rng(5)
    xi = np.zeros((15, g.dim))
    xi[:, 5] = rng.normal(0, 0.02, 15)  # rotations about z only
    target = np.zeros(g.dim)
    target[5] = 0.03
    sol = solve_segment(g, g.exp(xi), None, g.exp(target))
    zb = zeta_bar(g, g.exp(xi))
    np.testing.assert_allclose(sol.zeta, zb + (target - zb.sum(0)) / 15, atol=1e-12)


def test_composition_order_full_undo_keeps_the_first_pose():
    """With zeta = zeta_bar, the stabilized camera g_c(t) g_s(t) stays at the first pose to first order."""
    g = get_group("se3")
    rng = np.random.default_rng(6)
    xi = rng.normal(0, 1.0, (10, 6))

    def worst_deviation(scale):
        motions = g.exp(scale * xi)
        gs = integrate(g, np.eye(4), zeta_bar(g, motions))
        gc, dev = np.eye(4), 0.0
        for t in range(11):
            dev = max(dev, np.abs(g.log(gc @ gs[t])).max())
            if t < 10:
                gc = gc @ motions[t]
        return dev

    d1, d2 = worst_deviation(1e-3), worst_deviation(1e-4)
    assert 70 < d1 / d2 < 130  # shrinks with the square of the motion: no first-order drift
    motions = g.exp(1e-3 * xi)
    # and with identity end-constraints the optimum returns exactly to the keyframe pose
    sol = solve_segment(g, motions)
    np.testing.assert_allclose(sol.corrections[-1], np.eye(4), atol=1e-10)


def test_non_convergence_is_reported_not_hidden():
    g = get_group("se3")
    motions, C1 = random_segment(g, np.random.default_rng(7))
    sol = solve_segment(g, motions, None, C1, PathParams(max_iters=1, tol=1e-30))
    assert not sol.converged
    assert "residual" in sol.reason

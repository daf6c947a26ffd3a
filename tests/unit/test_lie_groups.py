"""One property-test suite for every Lie group (manif/Sophus style).

Each property is parametrised over ``GROUPS`` (se3, sim3, sa3, ga3); group-specific closed-form
checks follow. Seeded RNGs; tolerances are tight enough to catch sign/ordering/convention errors.
"""
from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg

from quick_stream.core.lie import GA3, GROUPS, LieGroup, SA3, SE3, SIM3, get_group, so3
from quick_stream.core.lie.affine import phi

ALL = pytest.mark.parametrize("G", list(GROUPS.values()), ids=list(GROUPS))
PHI = pytest.mark.parametrize("G", [GROUPS["sa3"], GROUPS["ga3"]], ids=["sa3", "ga3"])
RIGID = pytest.mark.parametrize("G", [GROUPS["se3"], GROUPS["sim3"]], ids=["se3", "sim3"])


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20240607)


def twists(G: LieGroup, rng: np.random.Generator, shape: tuple[int, ...], scale: float) -> np.ndarray:
    return scale * rng.standard_normal(shape + (G.dim,))


def comm(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    return X @ Y - Y @ X


# ----------------------------------------------------------------------------- registry / basis
def test_registry() -> None:
    assert list(GROUPS) == ["se3", "sim3", "sa3", "ga3"]
    assert [G.dim for G in GROUPS.values()] == [6, 7, 11, 12]
    assert isinstance(GROUPS["se3"], SE3) and isinstance(GROUPS["sim3"], SIM3)
    assert isinstance(GROUPS["sa3"], SA3) and isinstance(GROUPS["ga3"], GA3)
    assert get_group("SE3") is GROUPS["se3"]
    with pytest.raises(ValueError, match="se3, sim3, sa3, ga3"):
        get_group("so3")


@ALL
def test_basis(G: LieGroup) -> None:
    n = G.dim
    assert G.basis.shape == (n, 4, 4)
    assert np.linalg.matrix_rank(G.basis.reshape(n, 16)) == n
    assert np.all(G.basis[:, 3, :] == 0.0)
    for k in range(3):  # translation generators first
        expected = np.zeros((4, 4))
        expected[k, 3] = 1.0
        np.testing.assert_array_equal(G.basis[k], expected)
    assert np.all(G.basis[3:, :3, 3] == 0.0)
    if G.name != "ga3":  # hat(e1..3) come next
        for k in range(3):
            np.testing.assert_array_equal(G.basis[3 + k, :3, :3], so3.hat(np.eye(3)[k]))


def test_basis_specifics() -> None:
    np.testing.assert_array_equal(GROUPS["sim3"].basis[6, :3, :3], np.eye(3))
    sa = GROUPS["sa3"].basis[3:, :3, :3]
    np.testing.assert_allclose(np.trace(sa, axis1=1, axis2=2), 0.0)
    e = np.eye(3)
    np.testing.assert_array_equal(sa[3], np.outer(e[1], e[2]) + np.outer(e[2], e[1]))
    np.testing.assert_array_equal(sa[4], np.outer(e[0], e[2]) + np.outer(e[2], e[0]))
    np.testing.assert_array_equal(sa[5], np.outer(e[0], e[1]) + np.outer(e[1], e[0]))
    np.testing.assert_array_equal(sa[6], np.diag([1.0, -1.0, 0.0]))
    np.testing.assert_array_equal(sa[7], np.diag([0.0, 1.0, -1.0]))
    ga = GROUPS["ga3"]
    U = np.arange(9.0).reshape(3, 3)
    # column-major: u = vec(U), k = 3(n-1) + m
    np.testing.assert_array_equal(ga.hat(np.r_[0, 0, 0, U.T.ravel()])[:3, :3], U)


# ----------------------------------------------------------------------------- hat / vee
@ALL
def test_hat_vee(G: LieGroup, rng: np.random.Generator) -> None:
    xi = twists(G, rng, (4, 5), 1.0)
    X = G.hat(xi)
    assert X.shape == (4, 5, 4, 4)
    assert np.all(X[..., 3, :] == 0.0)
    np.testing.assert_allclose(G.vee(X), xi, atol=1e-14)
    np.testing.assert_allclose(G.hat(G.vee(X)), X, atol=1e-14)
    # vee is the least-squares (Frobenius) projection: a component orthogonal to the algebra is ignored
    N = rng.standard_normal((4, 4))
    N_perp = N - G.hat(G.vee(N))
    np.testing.assert_allclose(np.einsum("ij,kij->k", N_perp, G.basis), 0.0, atol=1e-13)
    np.testing.assert_allclose(G.vee(X[0, 0] + N_perp), xi[0, 0], atol=1e-13)
    with pytest.raises(ValueError):
        G.hat(np.zeros(G.dim + 1))


def test_sa3_vee_non_orthonormal_basis() -> None:
    G = GROUPS["sa3"]
    # The trace part (identity) is orthogonal to sl(3): it must not leak into the coordinates.
    xi = np.arange(1.0, 12.0)
    X = G.hat(xi)
    X[:3, :3] += 0.7 * np.eye(3)
    np.testing.assert_allclose(G.vee(X), xi, atol=1e-13)


# ----------------------------------------------------------------------------- exp / log
def _moderate_twists(G: LieGroup, rng: np.random.Generator, count: int) -> np.ndarray:
    xi = twists(G, rng, (count,), 0.4)
    if G.name in ("se3", "sim3"):  # rotation angles spread over [0, 2.5] rad
        axis = rng.standard_normal((count, 3))
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        xi[:, 3:6] = axis * np.linspace(0.0, 2.5, count)[:, None]
    return xi


@ALL
def test_log_exp_roundtrip(G: LieGroup, rng: np.random.Generator) -> None:
    xi = _moderate_twists(G, rng, 20)
    g = G.exp(xi)
    assert g.shape == (20, 4, 4)
    np.testing.assert_allclose(G.log(g), xi, atol=1e-10)
    for k in range(3):  # single elements agree with the batch
        np.testing.assert_allclose(G.log(G.exp(xi[k])), xi[k], atol=1e-10)


@ALL
def test_exp_log_roundtrip(G: LieGroup, rng: np.random.Generator) -> None:
    g = np.stack([G.random(rng, scale=1.0) for _ in range(10)])
    np.testing.assert_allclose(G.exp(G.log(g)), g, atol=1e-10)


@ALL
def test_exp_log_tiny(G: LieGroup, rng: np.random.Generator) -> None:
    xi = twists(G, rng, (6,), 1e-10)
    g = G.exp(xi)
    np.testing.assert_allclose(g[:, :3, :3], np.eye(3) + G.hat(xi)[:, :3, :3], atol=1e-18)
    np.testing.assert_allclose(G.log(g), xi, rtol=1e-5, atol=1e-15)
    np.testing.assert_array_equal(G.exp(np.zeros(G.dim)), np.eye(4))
    np.testing.assert_allclose(G.log(np.eye(4)), 0.0, atol=1e-15)


@ALL
def test_batch_shapes(G: LieGroup, rng: np.random.Generator) -> None:
    xi = twists(G, rng, (2, 3), 0.3)
    g = G.exp(xi)
    assert g.shape == (2, 3, 4, 4)
    np.testing.assert_allclose(g[1, 2], G.exp(xi[1, 2]), atol=1e-15)
    assert G.log(g).shape == (2, 3, G.dim)
    np.testing.assert_allclose(G.log(g), xi, atol=1e-10)
    assert G.exp(xi[0, 0]).shape == (4, 4) and G.log(g[0, 0]).shape == (G.dim,)
    assert G.inverse(g).shape == g.shape
    assert G.Ad(g).shape == (2, 3, G.dim, G.dim)
    assert G.ad(xi).shape == (2, 3, G.dim, G.dim)
    assert G.right_jacobian(xi).shape == (2, 3, G.dim, G.dim)
    np.testing.assert_allclose(G.left_jacobian(xi)[1, 0], G.left_jacobian(xi[1, 0]), atol=1e-14)


# ----------------------------------------------------------------------------- group axioms
@ALL
def test_compose_inverse(G: LieGroup, rng: np.random.Generator) -> None:
    a, b, c = (G.random(rng, 0.7) for _ in range(3))
    np.testing.assert_allclose(G.compose(a, G.inverse(a)), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(G.compose(G.inverse(a), a), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(
        G.compose(G.compose(a, b), c), G.compose(a, G.compose(b, c)), atol=1e-12
    )
    np.testing.assert_allclose(G.inverse(G.compose(a, b)), G.inverse(b) @ G.inverse(a), atol=1e-12)
    np.testing.assert_array_equal(G.identity(), np.eye(4))
    # the product stays in the group: log succeeds and round-trips
    ab = G.compose(a, b)
    np.testing.assert_allclose(G.exp(G.log(ab)), ab, atol=1e-10)


# ----------------------------------------------------------------------------- adjoints
@ALL
def test_Ad_conjugation_and_homomorphism(G: LieGroup, rng: np.random.Generator) -> None:
    g, h = G.random(rng, 0.8), G.random(rng, 0.8)
    xi = twists(G, rng, (5,), 1.0)
    lhs = xi @ G.Ad(g).T
    rhs = G.vee(g @ G.hat(xi) @ G.inverse(g))
    np.testing.assert_allclose(lhs, rhs, atol=1e-12)
    np.testing.assert_allclose(G.Ad(g @ h), G.Ad(g) @ G.Ad(h), atol=1e-11)
    np.testing.assert_allclose(G.Ad(G.inverse(g)), np.linalg.inv(G.Ad(g)), atol=1e-10)


@ALL
def test_ad_commutator_jacobi(G: LieGroup, rng: np.random.Generator) -> None:
    a, b, c = twists(G, rng, (3,), 1.0)
    np.testing.assert_allclose(G.ad(a) @ b, G.vee(comm(G.hat(a), G.hat(b))), atol=1e-13)
    for k in range(G.dim):  # the paper's definition, column by column
        np.testing.assert_allclose(G.ad(a)[:, k], G.vee(comm(G.hat(a), G.basis[k])), atol=1e-13)
    np.testing.assert_allclose(G.ad(a) @ a, 0.0, atol=1e-13)
    jac = G.ad(a) @ G.ad(b) @ c + G.ad(b) @ G.ad(c) @ a + G.ad(c) @ G.ad(a) @ b
    np.testing.assert_allclose(jac, 0.0, atol=1e-12)
    np.testing.assert_allclose(G.ad(a) @ b, -G.ad(b) @ a, atol=1e-13)


@ALL
def test_ad_is_derivative_of_Ad(G: LieGroup, rng: np.random.Generator) -> None:
    a = twists(G, rng, (), 1.0)
    s = 1e-5
    fd = (G.Ad(scipy.linalg.expm(s * G.hat(a))) - G.Ad(scipy.linalg.expm(-s * G.hat(a)))) / (2 * s)
    np.testing.assert_allclose(fd, G.ad(a), atol=1e-8)


# ----------------------------------------------------------------------------- Jacobians
def _fd_jacobians(G: LieGroup, xi: np.ndarray, h: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    gi = G.inverse(G.exp(xi))
    E = h * np.eye(G.dim)
    gp, gm = G.exp(xi + E), G.exp(xi - E)  # batched: row k perturbs coordinate k
    Jr = (G.log(gi @ gp) - G.log(gi @ gm)).T / (2 * h)
    Jl = (G.log(gp @ gi) - G.log(gm @ gi)).T / (2 * h)
    return Jr, Jl


@ALL
def test_jacobians_finite_differences(G: LieGroup, rng: np.random.Generator) -> None:
    for xi in (_moderate_twists(G, rng, 3)[-1], twists(G, rng, (), 0.5), np.zeros(G.dim)):
        Jr_fd, Jl_fd = _fd_jacobians(G, xi)
        Jr, Jl = G.right_jacobian(xi), G.left_jacobian(xi)
        np.testing.assert_allclose(Jr, Jr_fd, atol=1e-6)
        np.testing.assert_allclose(Jl, Jl_fd, atol=1e-6)
        np.testing.assert_allclose(Jl, G.Ad(G.exp(xi)) @ Jr, atol=1e-10)
    np.testing.assert_allclose(G.right_jacobian(np.zeros(G.dim)), np.eye(G.dim), atol=1e-15)


@RIGID
def test_rigid_closed_form_jacobians_match_generic(G: LieGroup, rng: np.random.Generator) -> None:
    xi = twists(G, rng, (4,), 0.8)
    np.testing.assert_allclose(G.right_jacobian(xi), LieGroup.right_jacobian(G, xi), atol=1e-13)
    np.testing.assert_allclose(G.left_jacobian(xi), LieGroup.left_jacobian(G, xi), atol=1e-13)


# ----------------------------------------------------------------------------- action on points
@ALL
def test_act_and_jacobian(G: LieGroup, rng: np.random.Generator) -> None:
    g = G.random(rng, 0.6)
    x = rng.uniform(-2.0, 2.0, (7, 3))
    y = G.act(g, x)
    np.testing.assert_allclose(y, (np.c_[x, np.ones(7)] @ g.T)[:, :3], atol=1e-14)
    J = G.act_jacobian(g, x)
    assert J.shape == (7, 3, G.dim)
    h = 1e-6
    E = h * np.eye(G.dim)
    fd = (G.act(G.exp(E) @ g, x[None]) - G.act(G.exp(-E) @ g, x[None])) / (2 * h)  # (n, 7, 3)
    np.testing.assert_allclose(J, np.moveaxis(fd, 0, -1), atol=1e-8)
    # batched g broadcasts over points
    gs = np.stack([g, G.inverse(g)])
    np.testing.assert_allclose(G.act(gs, x)[1], G.act(G.inverse(g), x), atol=1e-14)


# ----------------------------------------------------------------------------- linear-part structure
@ALL
def test_linear_part_structure(G: LieGroup, rng: np.random.Generator) -> None:
    xi = twists(G, rng, (8,), 0.7)
    g = G.exp(xi)
    A = g[:, :3, :3]
    np.testing.assert_allclose(g[:, :3, 3], xi[:, :3], atol=0)  # translation is decoupled
    np.testing.assert_array_equal(g[:, 3, :], np.tile([0.0, 0.0, 0.0, 1.0], (8, 1)))
    det = np.linalg.det(A)
    trU = np.trace(G.hat(xi)[:, :3, :3], axis1=1, axis2=2)
    np.testing.assert_allclose(det, np.exp(trU), rtol=1e-12)
    if G.name == "se3":
        np.testing.assert_allclose(np.swapaxes(A, 1, 2) @ A, np.tile(np.eye(3), (8, 1, 1)), atol=1e-14)
    if G.name == "sim3":
        s = np.exp(xi[:, 6])
        np.testing.assert_allclose(A / s[:, None, None], so3.exp(xi[:, 3:6]), atol=1e-14)
    if G.name == "sa3":
        np.testing.assert_allclose(det, 1.0, atol=1e-13)
    if G.name in ("sa3", "ga3"):
        U = G.hat(xi)[:, :3, :3]
        Ut = np.swapaxes(U, 1, 2)
        np.testing.assert_allclose(A, scipy.linalg.expm(Ut) @ scipy.linalg.expm(U - Ut), atol=1e-13)


def test_se3_closed_forms() -> None:
    G = GROUPS["se3"]
    t = np.array([0.3, -1.2, 2.0])
    np.testing.assert_array_equal(G.exp(np.r_[t, 0, 0, 0]), np.block([[np.eye(3), t[:, None]], [np.zeros((1, 3)), 1.0]]))
    th = 0.7
    Rz = np.array([[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0], [0, 0, 1]])
    g = G.exp([1.0, 2.0, 3.0, 0, 0, th])
    np.testing.assert_allclose(g[:3, :3], Rz, atol=1e-15)
    np.testing.assert_array_equal(g[:3, 3], [1.0, 2.0, 3.0])
    # hat convention: hat(a) b = a x b
    a, b = np.array([0.1, -0.4, 0.9]), np.array([2.0, 0.5, -1.0])
    np.testing.assert_allclose(so3.hat(a) @ b, np.cross(a, b), atol=1e-15)
    # decoupled chart != expm(hat(xi)) once rotation and translation are both present
    assert np.abs(G.exp([1.0, 0, 0, 0, 0, 1.0]) - scipy.linalg.expm(G.hat([1.0, 0, 0, 0, 0, 1.0]))).max() > 0.1


def test_sim3_closed_form() -> None:
    G = GROUPS["sim3"]
    g = G.exp([0, 0, 0, 0, 0, 0, np.log(2.0)])
    np.testing.assert_allclose(g[:3, :3], 2.0 * np.eye(3), atol=1e-15)
    np.testing.assert_allclose(G.log(np.diag([3.0, 3.0, 3.0, 1.0])), [0, 0, 0, 0, 0, 0, np.log(3.0)], atol=1e-15)


def test_phi_pure_rotation_and_symmetric() -> None:
    w = np.array([0.3, -0.5, 0.2])
    np.testing.assert_allclose(phi(so3.hat(w)), so3.exp(w), atol=1e-15)  # phi(W) = expm(W)
    S = np.array([[0.2, 0.1, 0.0], [0.1, -0.3, 0.4], [0.0, 0.4, 0.1]])
    np.testing.assert_allclose(phi(S), scipy.linalg.expm(S), atol=1e-14)  # phi(S) = expm(S)


# ----------------------------------------------------------------------------- SO(3) edge cases
def test_so3_log_near_pi_and_small() -> None:
    rng = np.random.default_rng(3)
    axes = rng.standard_normal((6, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    for ang in (np.pi, np.pi - 1e-9, np.pi - 1e-4, np.pi - 0.05, np.pi - 0.2, 1e-12, 1e-6, 0.0):
        R = so3.exp(ang * axes)
        w = so3.log(R)
        np.testing.assert_allclose(so3.exp(w), R, atol=1e-13)
        np.testing.assert_allclose(np.linalg.norm(w, axis=1), ang, atol=1e-12)
        if ang < np.pi - 1e-6:
            np.testing.assert_allclose(w, ang * axes, atol=1e-10)
    R = so3.exp(np.array([0.0, 0.0, np.pi + 0.3]))  # beyond pi wraps to the other side
    np.testing.assert_allclose(so3.log(R), [0.0, 0.0, -(np.pi - 0.3)], atol=1e-12)
    # Taylor branch is continuous with the closed form
    for th in (0.99e-4, 1.01e-4):
        w = th * axes[0]
        W = so3.hat(w)
        np.testing.assert_allclose(so3.exp(w), scipy.linalg.expm(W), atol=1e-16)
        np.testing.assert_allclose(so3.right_jacobian(w), np.eye(3) - W / 2 + W @ W / 6, atol=1e-14)


def test_se3_log_near_pi_batch() -> None:
    G = GROUPS["se3"]
    xi = np.array([[0.1, 0.2, 0.3, 0.0, np.pi - 1e-8, 0.0], [0, 0, 0, 0, 0, 0], [1, 1, 1, 1e-12, 0, 0]])
    np.testing.assert_allclose(G.log(G.exp(xi)), xi, atol=1e-9)


# ----------------------------------------------------------------------------- errors / projection
def test_log_rejects_elements_outside_group() -> None:
    flip = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(ValueError, match="det"):
        GROUPS["ga3"].log(flip)
    with pytest.raises(ValueError, match="det"):
        GROUPS["ga3"].log(np.diag([1.0, 0.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="SL"):
        GROUPS["sa3"].log(np.diag([2.0, 1.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="det"):
        GROUPS["se3"].log(flip)
    with pytest.raises(ValueError, match="det"):
        GROUPS["sim3"].log(flip)
    with pytest.raises(ValueError, match="orthonormal"):
        GROUPS["se3"].log(GROUPS["sa3"].exp(np.r_[0, 0, 0, 0, 0, 0, 0.3, 0, 0, 0, 0]))
    with pytest.raises(ValueError, match="orthonormal"):
        GROUPS["sim3"].log(np.diag([2.0, 1.0, 0.5, 1.0]))
    bad_row = np.eye(4)
    bad_row[3, 0] = 0.5
    for G in GROUPS.values():
        with pytest.raises(ValueError, match="last row"):
            G.log(bad_row)
    # batch: one bad element spoils the batch with a clear error
    good = GROUPS["ga3"].exp(np.zeros(12))
    with pytest.raises(ValueError, match="GL"):
        GROUPS["ga3"].log(np.stack([good, flip]))


@ALL
def test_project(G: LieGroup, rng: np.random.Generator) -> None:
    g = G.random(rng, 0.5)
    np.testing.assert_allclose(G.project(g), g, atol=1e-12)
    noisy = g + 1e-4 * rng.standard_normal((4, 4))
    p = G.project(noisy)
    np.testing.assert_array_equal(p[3], [0.0, 0.0, 0.0, 1.0])
    np.testing.assert_allclose(p, g, atol=1e-3)
    np.testing.assert_allclose(G.exp(G.log(p)), p, atol=1e-10)  # projected element is in the group
    assert G.project(np.stack([noisy, noisy])).shape == (2, 4, 4)


def test_project_specifics() -> None:
    M = np.diag([2.0, 3.0, 4.0, 1.0])
    np.testing.assert_allclose(GROUPS["se3"].project(M), np.eye(4), atol=1e-15)
    np.testing.assert_allclose(GROUPS["sim3"].project(M)[:3, :3], 3.0 * np.eye(3), atol=1e-15)
    np.testing.assert_allclose(np.linalg.det(GROUPS["sa3"].project(M)[:3, :3]), 1.0, atol=1e-14)
    with pytest.raises(ValueError, match="det"):
        GROUPS["sa3"].project(np.diag([-1.0, 1.0, 1.0, 1.0]))


# ----------------------------------------------------------------------------- phi inverse robustness
@PHI
def test_phi_log_large_elements(G: LieGroup, rng: np.random.Generator) -> None:
    """Far from the identity (large shears / rotations) log must still invert exp."""
    xi = twists(G, rng, (6,), 1.0)
    xi[:, 3:6] *= 2.0  # large skew part (rotations up to ~ pi)
    g = G.exp(xi)
    np.testing.assert_allclose(G.exp(G.log(g)), g, atol=1e-10)
    R = so3.exp(np.array([0.0, 0.0, 3.0]))  # a rotation by ~ pi plus strong anisotropic scaling
    A = np.diag([4.0, 0.5, 0.5]) @ R
    g = np.eye(4)
    g[:3, :3] = A
    np.testing.assert_allclose(G.exp(G.log(g)), g, atol=1e-10)


@PHI
def test_phi_log_continuation_fallback(G: LieGroup, rng: np.random.Generator, monkeypatch) -> None:
    """With a useless (overflowing) initial guess the damped Newton fails; the continuation fallback must rescue it."""
    import quick_stream.core.lie.affine as affine

    monkeypatch.setattr(affine, "_initial_guess", lambda A: np.tile(np.diag([800.0, -800.0, 0.0]), (A.shape[0], 1, 1)))
    xi = twists(G, rng, (2,), 0.5)
    g = G.exp(xi)
    np.testing.assert_allclose(G.log(g), xi, atol=1e-10)


def test_so3_jacobians_finite_differences() -> None:
    rng = np.random.default_rng(5)
    h = 1e-6
    for w in (rng.standard_normal(3), np.array([0.0, 2.9, 0.5]), np.array([1e-9, 0.0, 0.0])):
        R = so3.exp(w)
        E = h * np.eye(3)
        fd_r = (so3.log(R.T @ so3.exp(w + E)) - so3.log(R.T @ so3.exp(w - E))).T / (2 * h)
        fd_l = (so3.log(so3.exp(w + E) @ R.T) - so3.log(so3.exp(w - E) @ R.T)).T / (2 * h)
        np.testing.assert_allclose(so3.right_jacobian(w), fd_r, atol=1e-7)
        np.testing.assert_allclose(so3.left_jacobian(w), fd_l, atol=1e-7)


def test_nearest_rotation_is_the_closest_proper_rotation() -> None:
    rng = np.random.default_rng(11)
    R = so3.exp(rng.standard_normal((50, 3)))
    np.testing.assert_allclose(so3.nearest_rotation(R), R, atol=1e-14)  # a rotation stays itself
    np.testing.assert_allclose(so3.nearest_rotation(2.5 * R), R, atol=1e-14)  # SIM(3): the scale goes
    A = R @ (np.eye(3) + 0.2 * rng.standard_normal((50, 3, 3)))  # affine parts, batched
    P = so3.nearest_rotation(A)
    np.testing.assert_allclose(P @ np.swapaxes(P, -1, -2), np.broadcast_to(np.eye(3), P.shape), atol=1e-13)
    assert np.all(np.linalg.det(P) > 0)
    for a, p in zip(A, P):  # no nearby rotation is closer to A
        for _ in range(5):
            other = p @ so3.exp(0.05 * rng.standard_normal(3))
            assert np.linalg.norm(a - p) <= np.linalg.norm(a - other) + 1e-12
    assert np.linalg.det(so3.nearest_rotation(np.diag([1.0, 1.0, -1.0]))) > 0  # never a reflection

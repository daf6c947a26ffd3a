"""The tilt cap (docs/method.md 4.5, (19)): quick_stream/core/path/tilt.py."""
from __future__ import annotations

import numpy as np
import pytest

from quick_stream.core.lie import so3
from quick_stream.core.path.tilt import capped_angle, effective_rotation, limit_tilt, tilt
from quick_stream.core.render.shape_term import rotation_references
from quick_stream.quality.metrics import scale_and_distortion

K = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])
CAP, KNEE = np.radians(6.0), np.radians(2.0)


def _corrections(n: int, spread_deg: float, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    C = np.tile(np.eye(4), (n, 1, 1))
    C[:, :3, :3] = so3.exp(rng.normal(size=(n, 3)) * np.radians(spread_deg))
    C[:, :3, 3] = rng.normal(size=(n, 3)) * 0.02
    return C


def _pixel(L: np.ndarray, q: np.ndarray) -> np.ndarray:
    x = K @ L @ np.linalg.inv(K) @ np.array([q[0], q[1], 1.0])
    return x[:2] / x[2]


def test_corrections_below_the_knee_are_returned_bit_for_bit() -> None:
    C = _corrections(50, 1.0)
    assert np.all(np.degrees(tilt(C)) < 4.0)
    assert np.array_equal(limit_tilt(C, CAP, KNEE), C)
    assert np.array_equal(limit_tilt(_corrections(5, 20.0), 0.0, KNEE), _corrections(5, 20.0))


def test_the_capped_turn_stays_below_the_cap_and_the_centre_lands_where_the_whole_turn_puts_it() -> None:
    C = _corrections(200, 12.0, seed=1)
    D = limit_tilt(C, CAP, KNEE)
    over = np.degrees(tilt(C)) > 4.0
    assert over.sum() > 100
    centre = np.array([K[0, 2], K[1, 2]])
    for c, d in zip(C[over], D[over]):
        assert np.allclose(_pixel(c[:3, :3], centre), _pixel(d[:3, :3], centre), atol=1e-6)
        # the rotation of (19): the point transform S^-1 R'^T with rows 0 and 1 taken off along row 2
        Lt = np.linalg.inv(d)[:3, :3]
        r = np.concatenate([Lt[:2] - np.outer(Lt[:2] @ Lt[2], Lt[2]), Lt[2:]])
        assert np.allclose(r @ r.T, np.eye(3), atol=1e-9)
        assert np.degrees(np.arccos(np.clip(r[2, 2], -1, 1))) <= 6.0 + 1e-9
    assert np.array_equal(D[:, :3, 3], C[:, :3, 3])  # the translation is kept
    assert np.allclose(np.linalg.det(D[:, :3, :3]), 1.0)


@pytest.mark.parametrize("deg", [8.0, 12.0, 15.0, 25.0])
def test_a_capped_turn_scores_the_distortion_of_the_cap_not_of_the_turn(deg: float) -> None:
    Kc = np.diag([525.0, 525.0, 1.0])  # the scorer's centred coordinates
    for axis in ([1.0, 0, 0], [0, 1.0, 0], [0.6, 0.7, 0.4]):
        C = np.eye(4)
        C[:3, :3] = so3.exp(np.radians(deg) * np.asarray(axis) / np.linalg.norm(axis))
        D = limit_tilt(C[None], CAP, KNEE)[0]
        whole = scale_and_distortion(Kc @ C[:3, :3] @ np.linalg.inv(Kc))[1]
        capped = scale_and_distortion(Kc @ D[:3, :3] @ np.linalg.inv(Kc))[1]
        assert whole < np.cos(np.radians(deg)) + 0.02
        assert capped >= np.cos(CAP) - 1e-6 > whole


def test_the_capped_angle_and_its_slope_are_continuous() -> None:
    th = np.linspace(0, np.radians(40), 4001)
    c = capped_angle(th, CAP, KNEE)
    assert np.array_equal(c[th <= CAP - KNEE], th[th <= CAP - KNEE])
    assert np.all(c <= CAP) and np.all(np.diff(c) >= 0)
    slope = np.diff(c) / np.diff(th)
    assert np.max(np.abs(np.diff(slope))) < 1e-2  # no kink


def test_the_shape_reference_of_a_capped_correction_is_its_rotation() -> None:
    src = np.stack(np.meshgrid(np.linspace(0, 639, 3), np.linspace(0, 479, 3)), axis=-1)
    C = _corrections(30, 12.0, seed=2)
    D = limit_tilt(C, CAP, KNEE)
    ref, ok = rotation_references(K, np.linalg.inv(D), src)
    assert ok.all()
    for d, r in zip(D, ref):
        Lt = np.linalg.inv(d)[:3, :3]
        R = np.concatenate([Lt[:2] - np.outer(Lt[:2] @ Lt[2], Lt[2]), Lt[2:]])
        H = K @ R @ np.linalg.inv(K)
        h = np.einsum("ij,mj->mi", H[:, :2], src.reshape(-1, 2)) + H[:, 2]
        assert np.allclose(r.reshape(-1, 2), h[:, :2] / h[:, 2:], atol=1e-6)
    # an uncapped rigid correction: its rotation, as before
    ref0, _ = rotation_references(K, np.linalg.inv(C), src)
    for c, r in zip(C, ref0):
        H = K @ c[:3, :3].T @ np.linalg.inv(K)
        h = np.einsum("ij,mj->mi", H[:, :2], src.reshape(-1, 2)) + H[:, 2]
        assert np.allclose(r.reshape(-1, 2), h[:, :2] / h[:, 2:], atol=1e-8)


def _rotation_tilt_deg(correction: np.ndarray) -> float:
    """The tilt of (19)'s rotation R' of a released correction (its point transform with the shift taken out)."""
    Lt = np.linalg.inv(correction)[:3, :3]
    r = np.concatenate([Lt[:2] - np.outer(Lt[:2] @ Lt[2], Lt[2]), Lt[2:]])
    return float(np.degrees(np.arccos(np.clip(r[2, 2] / np.linalg.norm(r[2]), -1, 1))))


def test_the_stabilizer_releases_capped_corrections_and_renders_them_border_free() -> None:
    from dataclasses import replace

    from quick_stream.core.stabilizer import StabilizerParams
    from quick_stream.io.sources.synthetic import SyntheticSource
    from tests.helpers import stabilize

    frames = list(SyntheticSource(width=320, height=240, frames=60, seed=3, shake=5))
    base = StabilizerParams()
    _, free = stabilize(frames, base)
    capped_params = replace(base, planner=replace(base.planner, max_tilt_deg=1.0, tilt_knee_deg=0.5))
    st, capped = stabilize(frames, capped_params)
    before = [_rotation_tilt_deg(f.correction.matrix) for f in free]
    after = [_rotation_tilt_deg(f.correction.matrix) for f in capped]
    assert sum(t > 1.0 for t in before) >= 10  # the shake turns the axis past the cap
    assert max(after) <= 1.0 + 1e-6
    assert [f.seq for f in capped] == [f.seq for f in free]
    assert st.render.filler.bordered == 0
    for f in capped:  # the crop planned with the capped corrections is the crop rendered: no black edge
        edges = np.concatenate([f.image[0], f.image[-1], f.image[:, 0], f.image[:, -1]])
        assert np.mean(edges.max(axis=1) == 0) < 0.01, f.seq


def test_the_effective_rotation_of_a_capped_correction_is_the_whole_turn() -> None:
    C = _corrections(100, 12.0, seed=4)
    D = limit_tilt(C, CAP, KNEE)
    assert np.allclose(effective_rotation(D), C[:, :3, :3], atol=1e-9)  # the turn (19) capped, given back
    assert np.allclose(effective_rotation(C), C[:, :3, :3], atol=1e-12)  # no shift: the rotation itself
    assert np.allclose(effective_rotation(np.eye(4)), np.eye(3))

"""The translation prior of the exact fit (docs/method.md (3n)): what the flow cannot tell from a
rotation goes to the rotation; a translation the flow determines keeps its value."""
from __future__ import annotations

import numpy as np
import pytest

from quick_stream.core.lie import get_group
from quick_stream.core.motion import MotionEstimator, MotionParams, with_translation_prior
from tests.unit.test_motion_chain import SE3, flow_of, rotation_error


def _errors(prior_mm: float, M_of, seeds=range(12), **flow_kw) -> tuple[np.ndarray, np.ndarray, list]:
    est = MotionEstimator(MotionParams(translation_prior_mm=prior_mm))
    rot, trans, motions = [], [], []
    for s in seeds:
        rng = np.random.default_rng(s)
        M = M_of(rng)
        m = est.estimate(flow_of(rng, M, **flow_kw))
        assert m.valid and m.kind == "fit"
        truth = np.linalg.inv(M)  # the camera motion
        rot.append(rotation_error(m.matrix[:3, :3], truth[:3, :3]))
        trans.append(np.linalg.norm(m.matrix[:3, 3] - truth[:3, 3]))
        motions.append(m)
    return np.array(rot), np.array(trans), motions


def _shake(rng):
    """A hand-held shake: the camera turns ~0.6 deg and hardly moves (0.1 mm)."""
    return SE3.exp(np.concatenate((rng.normal(0, 1e-4, 3), rng.normal(0, 0.01, 3))))


def test_a_shake_seen_with_noisy_depth_is_taken_as_the_rotation_it_is():
    """Noisy stereo depth (k z^2 with k = 0.012) and half-pixel flow noise: the free fit trades some of the
    rotation for a sideways step; the prior gives it back (rotation error a fifth lower at least; ~a third)."""
    free, _, _ = _errors(0.0, _shake, depth_noise=0.012, sigma_px=1.0)
    prior, _, _ = _errors(0.2, _shake, depth_noise=0.012, sigma_px=1.0)
    assert prior.mean() < 0.8 * free.mean(), (prior.mean(), free.mean())


def test_a_translation_is_drawn_in_as_much_as_the_flow_leaves_it_open():
    """A camera stepping 1 cm per frame through a scene 1-4 m deep: the prior takes the share
    sigma_t^2 / (sigma_t^2 + prior^2) of the step (its image motion going to the rotation), so the better
    the flow determines it (more pairs), the less it moves: under a tenth with 8000 pairs (sigma_t about a
    quarter of the prior's 0.2 mm), about a fifth with 2000 (docs/method.md (3n))."""
    def step(rng):
        return SE3.exp(np.concatenate((rng.normal(0, 0.01, 3), rng.normal(0, 0.005, 3))))

    def shrink(n: int) -> np.ndarray:
        _, _, free = _errors(0.0, step, n=n)
        _, _, prior = _errors(0.2, step, n=n)
        return np.array([1 - np.linalg.norm(b.matrix[:3, 3]) / np.linalg.norm(a.matrix[:3, 3])
                         for a, b in zip(free, prior)])

    many, few = shrink(8000), shrink(2000)
    assert np.all(many < 0.1) and np.all(many >= 0) and np.mean(many) < 0.5 * np.mean(few), (many, few)


def test_the_update_is_the_conditional_of_the_twist_and_its_covariance():
    """A prior far wider than the fit's own spread changes nothing; a very narrow one leaves no translation
    and the covariance stays symmetric and positive (semi)definite."""
    rng = np.random.default_rng(3)
    m = MotionEstimator(MotionParams(translation_prior_mm=0.0)).estimate(flow_of(rng, _shake(rng), depth_noise=0.012))
    wide = with_translation_prior(m, SE3, 1e3)
    assert np.allclose(wide.twist, m.twist, atol=1e-12) and np.allclose(wide.covariance, m.covariance, atol=1e-15)
    narrow = with_translation_prior(m, SE3, 1e-9)
    assert np.linalg.norm(narrow.twist[:3]) < 1e-8
    assert np.allclose(narrow.covariance, narrow.covariance.T)
    assert np.linalg.eigvalsh(narrow.covariance).min() > -1e-15
    assert np.allclose(narrow.matrix, SE3.exp(narrow.twist)) and np.allclose(narrow.zeta_bar, SE3.log(np.linalg.inv(narrow.matrix)))


@pytest.mark.parametrize("group", ["sim3", "sa3", "ga3"])
def test_every_group_takes_the_prior_on_its_translation(group):
    m = MotionEstimator(MotionParams(group=group, translation_prior_mm=0.2)).estimate(
        flow_of(np.random.default_rng(5), _shake(np.random.default_rng(5)), depth_noise=0.012))
    assert m.valid and np.all(np.isfinite(m.matrix)) and np.allclose(m.matrix, get_group(group).exp(m.twist))


def test_a_negative_prior_is_refused():
    with pytest.raises(ValueError, match="translation_prior_mm"):
        MotionEstimator(MotionParams(translation_prior_mm=-1.0))


def test_the_stabilizer_runs_the_prior_and_the_estimator_alone_the_free_fit():
    from quick_stream.core.stabilizer import StabilizerParams
    from quick_stream.io.stabilizer_flags import default_settings

    assert MotionParams().translation_prior_mm == 0.0
    assert StabilizerParams().motion.translation_prior_mm == default_settings().motion.translation_prior_mm == 0.2

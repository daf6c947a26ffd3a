"""Accuracy of the estimators on the synthetic source (ground truth) and on real footage."""

import cv2
import numpy as np
import pytest

from quick_stream.bench import moving_objects, odometry
from quick_stream.motion import MotionParams
from quick_stream.motion_pipeline import MotionPipeline, run_motion
from quick_stream.sources.synthetic import SyntheticSource


@pytest.fixture(autouse=True)
def one_thread():
    cv2.setNumThreads(1)


def test_exact_se3_on_synthetic_640x480_meets_accuracy_bar():
    src = SyntheticSource(width=640, height=480, frames=40, seed=0)
    result = run_motion(src, MotionPipeline())
    stats = result.error_stats()
    assert stats.n == 39
    assert all(p.motion.valid for p in result.pairs)
    assert stats.rot_median < 0.03, stats
    assert stats.trans_median < 1.0, stats


@pytest.mark.parametrize("group", ["sim3", "sa3", "ga3"])
def test_exact_other_groups_on_synthetic(group):
    src = SyntheticSource(width=320, height=240, frames=15, seed=1)
    stats = run_motion(src, MotionPipeline(motion_params=MotionParams(group=group))).error_stats()
    assert stats.rot_median < 0.06, stats
    assert stats.trans_median < 2.0, stats


def test_redkitchen_exact_matches_opencv_odometry(shared_data):
    """On the clip's first 60 pairs (OpenCV's odometry costs 75 ms a pair; the whole clip's
    numbers are `quick-stream bench odometry`'s)."""
    r = odometry.run(f"tum:{shared_data / '7scenes_redkitchen'}", frames=61)["methods"]
    exact, induced, ocv = r["exact se3"], r["induced se3"], r["opencv rgbd odometry"]
    assert exact["n"] == 60
    assert exact["rot_median"] <= ocv["rot_median"] + 0.01, (exact, ocv)
    assert exact["rot_median"] < 0.7 * induced["rot_median"]
    assert exact["trans_median"] < 0.6 * induced["trans_median"]


def test_redkitchen_affine_groups_keep_their_own_fit(shared_data):
    """docs/method.md 2.3: a real room determines GA(3)/SA(3); the rigid fallback must not fire."""
    from quick_stream.frame import BadFrame
    from quick_stream.motion import MotionEstimator
    from quick_stream.sceneflow import SceneFlow
    from quick_stream.sources import open_source

    sf = SceneFlow()
    ests = {g: MotionEstimator(MotionParams(group=g)) for g in ("sa3", "ga3")}
    prev, n, used = None, 0, {g: [] for g in ests}
    for fr in open_source(f"tum:{shared_data / '7scenes_redkitchen'}"):
        if isinstance(fr, BadFrame):
            continue
        if prev is not None:
            flow = sf.compute(prev, fr)
            n += 1
            for g, est in ests.items():
                m = est.estimate(flow)
                if not m.valid or m.fallback:
                    used[g].append((m.seq, m.reason))
        prev = fr
    assert n == 249
    assert used == {"sa3": [], "ga3": []}


def test_jointvosf_robust_estimator_stays_with_background(shared_data):
    res = moving_objects.run(shared_data)
    assert set(res) == set(moving_objects.MOVING_BOXES)
    robust = np.array([r["exact (robust)"]["rot_dev_deg"] for r in res.values()])
    plain = np.array([r["exact, plain LS"]["rot_dev_deg"] for r in res.values()])
    mean = np.array([r["induced (mean)"]["rot_dev_deg"] for r in res.values()])
    assert np.all(robust < mean), res
    assert robust.mean() < 0.4 * mean.mean()
    assert robust.mean() < 0.4 * plain.mean()
    robust_t = np.mean([r["exact (robust)"]["trans_dev_mm"] for r in res.values()])
    mean_t = np.mean([r["induced (mean)"]["trans_dev_mm"] for r in res.values()])
    assert robust_t < 0.5 * mean_t

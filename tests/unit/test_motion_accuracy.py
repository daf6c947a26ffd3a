"""Accuracy of the estimators on the synthetic source (ground truth) and on real footage."""

import pytest

from quick_stream.core.motion import MotionParams
from quick_stream.core.motion_pipeline import MotionPipeline, run_motion
from quick_stream.io.sources.synthetic import SyntheticSource
from quick_stream.quality.evaluation.rpe import pair_error_stats


def test_exact_se3_on_synthetic_640x480_meets_accuracy_bar():
    src = SyntheticSource(width=640, height=480, frames=40, seed=0)
    result = run_motion(src, MotionPipeline())
    stats = pair_error_stats(result.pairs)
    assert stats.n == 39
    assert all(p.motion.valid for p in result.pairs)
    assert stats.rot_median < 0.03, stats
    assert stats.trans_median < 1.0, stats


@pytest.mark.parametrize("group", ["sim3", "sa3", "ga3"])
def test_exact_other_groups_on_synthetic(group):
    src = SyntheticSource(width=320, height=240, frames=15, seed=1)
    stats = pair_error_stats(run_motion(src, MotionPipeline(motion_params=MotionParams(group=group))).pairs)
    assert stats.rot_median < 0.06, stats
    assert stats.trans_median < 2.0, stats



"""Border fill (docs/method.md 5.4 and (10b)): missing output pixels taken from neighbouring frames.

Checked against ground truth on the synthetic source (rendered frames with known camera poses):
the filled pixels are what the virtual camera sees; end to end, shaky frames come out with no
border, at less zoom than without the fill, and with a zoom track the renderer never had to raise.
"""
from __future__ import annotations

import numpy as np
import pytest

from tests.helpers import stabilize

from quick_stream.bench.variants import parse_settings
from quick_stream.core.lie import get_group
from quick_stream.core.motion import MotionEstimate
from quick_stream.core.path.budget import BudgetParams
from quick_stream.core.path.planner import Correction, PathPlanner, PlannerParams
from quick_stream.core.render import FramingParams, ZoomSmoother
from quick_stream.core.render_stage import RenderStage
from quick_stream.core.render.fill import FillSource, covered_zoom, fill_border, nearest_depth, ordered_sources
from quick_stream.io.sources.synthetic import SyntheticSource
from quick_stream.quality.metrics_border import uncovered_mask
from quick_stream.stream.wire import decode, encode_correction

SE3 = get_group("se3")


@pytest.fixture(scope="module")
def scene():
    src = SyntheticSource(width=320, height=240, frames=40, seed=2, shake=2.0)
    return src, [src.frame(i) for i in range(40)]


def test_filled_pixels_are_what_the_virtual_camera_sees(scene):
    src, frames = scene
    t = 20
    K = src.intrinsics.K
    # a virtual camera turned 1.5 deg from frame t's: a band on one side is outside frame t
    V = frames[t].pose @ SE3.exp(np.array([0, 0, 0, 0.0, np.radians(1.5), 0.0]))
    truth, depth = src._renderer.render(V, K)
    band = np.zeros(truth.shape[:2], bool)
    band[:, :12] = True  # what the frame's own mesh would leave uncovered
    out = truth.copy()
    out[band] = 0
    own_depth = np.where(band, 0.0, depth)
    sources = [FillSource(f.seq, 0, f.pose, f.color, K) for f in frames]
    own = lambda ys, xs: own_depth[ys, xs]  # noqa: E731 - the output depth where the fill asks
    left = fill_border(out, band, own, K, 1.0, V, ordered_sources(t, 0, sources, 8))
    assert not left.any()  # the neighbours, shaken the other way, saw the whole band
    err = np.abs(out[band].astype(float) - truth[band].astype(float)).mean()
    assert err < 8.0, err  # resampling of a textured wall (a wrong pose convention gives > 30)
    wrong = truth.copy()
    wrong[band] = 0
    fill_border(wrong, band, own, K, 1.0, np.linalg.inv(V), ordered_sources(t, 0, sources, 8))
    assert np.abs(wrong[band].astype(float) - truth[band].astype(float)).mean() > 3 * err


def test_sources_are_the_nearest_of_the_same_chain():
    srcs = [FillSource(s, 0 if s < 10 else 1, np.eye(4), np.zeros((2, 2, 3), np.uint8), np.eye(3))
            for s in range(20)]
    assert [s.seq for s in ordered_sources(7, 0, srcs, 3)] == [6, 8, 5, 9, 4]
    assert [s.seq for s in ordered_sources(11, 1, srcs, 2)] == [10, 12, 13]  # 9 is another chain


def test_nearest_depth_extends_the_known_depth():
    d = np.zeros((5, 6))
    d[:, 3:] = 2.0
    d[0, 0] = 1.0
    full = nearest_depth(d)
    assert full[0, 1] == 1.0 and full[4, 2] == 2.0 and np.all(full[:, 3:] == 2.0)
    assert nearest_depth(np.zeros((3, 3))) is None


def test_shaky_frames_come_out_border_free_with_less_zoom_than_without_fill():
    frames = list(SyntheticSource(width=320, height=240, frames=75, seed=4, shake=3.0))
    st, out = stabilize(frames, parse_settings([]).params)  # the defaults of quick-stream stabilize
    assert [sf.seq for sf in out] == list(range(75))
    assert st.render.filler.filled > 0  # the shake uncovered bands the neighbours filled
    # the planned zoom track counted on what the fill could do (at the planner's median depth): the renderer
    # lifted the zoom beyond the plan on few frames, and little (docs/method.md (14a))
    assert st.render.filler.fill_raised <= 0.05 * len(out)
    assert max(sf.zoom - sf.correction.zoom for sf in out) < 0.03
    assert st.render.filler.bordered == 0  # the renderer's own account: no output pixel left without a source
    for sf in out:
        assert not uncovered_mask(sf.image).any(), sf.seq
    z = np.array([sf.zoom for sf in out])
    assert np.abs(np.diff(z)).max() < 0.02  # no zoom jumps
    _, without = stabilize(frames, parse_settings(["--fill-frames", "0"]).params)
    assert np.mean(1 / z) > np.mean([1 / sf.zoom for sf in without]) + 0.01


def test_covered_zoom_is_enough_for_the_renderer():
    frames = list(SyntheticSource(width=320, height=240, frames=45, seed=5, shake=3.0))
    st, out = stabilize(frames, parse_settings([]).params)
    by_seq = {f.seq: f for f in frames}
    srcs = [FillSource(sf.seq, sf.correction.chain, sf.correction.camera, by_seq[sf.seq].color,
                       by_seq[sf.seq].intrinsics.K) for sf in out]
    for sf in out[10:40:5]:
        f, c = by_seq[sf.seq], sf.correction
        z = covered_zoom(sf.mesh, f.depth, f.intrinsics.K, sf.zoom, c.camera @ c.matrix,
                         ordered_sources(sf.seq, c.chain, srcs, st.render.filler.framing.fill_frames))
        assert z == pytest.approx(sf.zoom)  # what was rendered needed no more


def test_a_frame_renders_once_its_lookahead_is_estimated(scene, monkeypatch):
    """The first frame of a batch waits for the estimates of the ``fill_lookahead`` frames after it
    only (docs/method.md (14a)), and each warp is solved once, when first needed; the zooms are the
    zoom track of the whole batch's estimates."""
    _, frames = scene
    framing = FramingParams(mode="auto", fill_lookahead=3)
    stage, batch = RenderStage(framing=framing), frames[:12]
    for f in batch:
        stage.add_frame(f.seq, f)
    # the virtual camera turned away at frame 8: more than the neighbours saw, the zoom rises early
    turn = {8: 4.0, 9: 2.0}
    corr = [Correction(f.seq, SE3.exp(np.array([0, 0, 0, 0, np.radians(turn.get(f.seq, 0.0)), 0])), 0, False,
                       zoom=1.0, camera=f.pose, chain=0) for f in batch]
    estimated, solved, needs, zooms = [], [], [], []
    need, solve, cover = RenderStage._need, RenderStage._solve, ZoomSmoother.cover_frames

    def counted_need(self, p, ahead):
        estimated.append(p.c.seq)
        needs.append(need(self, p, ahead))
        return needs[-1]

    def counted_solve(self, p):
        solved.extend([p.c.seq] if p.mesh is None else [])
        return solve(self, p)

    def recorded_cover(self, planned, required):
        for z in cover(self, planned, required):
            zooms.append(z)
            yield z

    monkeypatch.setattr(RenderStage, "_need", counted_need)
    monkeypatch.setattr(RenderStage, "_solve", counted_solve)
    monkeypatch.setattr(ZoomSmoother, "cover_frames", recorded_cover)
    out = []
    for sf in stage.iter_release(corr):
        ahead = list(range(batch[0].seq, min(sf.seq + framing.fill_lookahead, batch[-1].seq) + 1))
        assert estimated == ahead and solved == ahead, sf.seq
        out.append(sf)
    assert [sf.seq for sf in out] == [f.seq for f in batch]
    got = list(zooms)
    want = ZoomSmoother(framing).cover([c.zoom for c in corr], needs)
    assert np.array_equal(got, want)
    h, rate = framing.fill_lookahead, framing.fill_lift_rate
    assert want[8] > 1.1  # the turn needs more than the neighbours saw: the zoom rises h frames early, not earlier
    assert want[8 - h] == pytest.approx(want[8] - h * rate) and want[8 - h - 1] < want[8] - 0.1


def test_corrections_carry_the_camera_pose_and_its_chain_on_the_wire():
    g = SE3
    pl = PathPlanner(PlannerParams(budget=BudgetParams(max_zoom=0)))
    out = pl.start(0)
    rng = np.random.default_rng(0)

    def motion(i: int, valid: bool = True) -> MotionEstimate:
        tw = rng.normal(0, 0.01, 6)
        return MotionEstimate(i, i + 1, "se3", "exact", g.exp(tw), tw, valid, "" if valid else "test")

    for i in range(40):
        out += pl.push(motion(i, valid=i != 25))
    out += pl.finish()
    chains = {c.seq: c.chain for c in out}
    assert set(chains[s] for s in range(26)) == {0} and set(chains[s] for s in range(26, 41)) == {1}
    c = out[30]
    back = decode(encode_correction(c, "cam0")).obj
    np.testing.assert_array_equal(back.camera, c.camera)
    assert back.chain == c.chain == 1


def test_convex_exit_distance_agrees_with_the_general_one():
    """The planner's fast ray/quad test (docs/method.md (10b)) against the general polygon one, on
    perspective images of a rectangle of both orientations, with the centre inside and outside."""
    from quick_stream.core.path.coverage import convex_exit_distance, exit_distance, rim

    rng = np.random.default_rng(3)
    corners = np.array([[0, 0, 1], [640, 0, 1], [640, 480, 1], [0, 480, 1]], float).T
    rays = rim(8) * np.array([320.0, 240.0])  # (P, 2)
    outside = inside = 0
    for flip in (False, True):
        H = np.eye(3) + rng.normal(0, [[0.2, 0.2, 60], [0.2, 0.2, 60], [3e-4, 3e-4, 0.05]], (40, 3, 3))
        q = H @ corners
        q = q[np.all(q[:, 2] > 0, axis=1)]  # wholly in front: convex images
        quads = (q[:, :2] / q[:, 2:]).transpose(0, 2, 1)
        quads = quads[:, ::-1] if flip else quads
        centre = np.broadcast_to([320.0, 240.0], (len(quads), 2))
        fast = convex_exit_distance(quads, centre, rays[None])
        general = exit_distance(quads, centre, np.broadcast_to(rays, (len(quads),) + rays.shape))
        np.testing.assert_allclose(fast, general, rtol=1e-9, atol=1e-9)
        outside += int(np.sum(np.all(general == 0, axis=1)))
        inside += int(np.sum(np.all(general > 0, axis=1)))
    assert outside > 0 and inside > 0  # both cases were exercised

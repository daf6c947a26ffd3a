"""Scene flow: lifted pairs agree with ground truth; each mask removes what it should."""
import numpy as np
import pytest

from quick_stream.core.frame import RGBDFrame
from quick_stream.core.sceneflow import SceneFlow, SceneFlowParams, sample_depth
from quick_stream.io.sources.synthetic import SyntheticSource


@pytest.fixture(scope="module")
def pair():
    src = SyntheticSource(frames=3, seed=11)
    return src.frame(0), src.frame(1)


def point_motion(a: RGBDFrame, b: RGBDFrame) -> np.ndarray:
    return np.linalg.inv(b.pose) @ a.pose


def test_lifted_pairs_follow_ground_truth(pair):
    a, b = pair
    r = SceneFlow().compute(a, b)
    assert 1000 <= len(r) <= SceneFlowParams().max_points
    M = point_motion(a, b)
    pred = r.points @ M[:3, :3].T + M[:3, 3]
    err = np.linalg.norm(r.points + r.displacements - pred, axis=1)
    assert np.median(err) < 0.003  # metres; depth 0.8-5 m
    # pixels_next is where the flow put the point: it reprojects x + v (to float32 precision,
    # the wire's: about 1e-4 px at x = 640)
    y = r.points + r.displacements
    K = r.intrinsics_next
    np.testing.assert_allclose(K.fx * y[:, 0] / y[:, 2] + K.cx, r.pixels_next[:, 0], atol=2e-4)
    for a in (r.points, r.displacements, r.pixels, r.pixels_next):
        assert np.array_equal(a, a.astype(np.float32))


def test_subsampling_is_bounded_and_deterministic(pair):
    a, b = pair
    p = SceneFlowParams(max_points=500)
    r1 = SceneFlow(p).compute(a, b)
    r2 = SceneFlow(p).compute(a, b)
    assert len(r1) == 500
    np.testing.assert_array_equal(r1.points, r2.points)
    np.testing.assert_array_equal(r1.displacements, r2.displacements)


def test_invalid_depth_is_masked_in_both_frames(pair):
    a, b = pair
    a2 = a.with_(depth=a.depth.copy())
    a2.depth[:, :320] = 0  # left half of frame t invalid
    b2 = b.with_(depth=b.depth.copy())
    b2.depth[240:, :] = 0  # bottom half of frame t+1 invalid
    r = SceneFlow(SceneFlowParams(max_points=100000)).compute(a2, b2)
    assert r.pixels[:, 0].min() >= 320
    assert r.pixels_next[:, 1].max() < 240
    assert r.counts["invalid_depth"] > 0 and r.counts["invalid_depth_next"] > 0


def test_flow_leaving_the_image_is_masked():
    src = SyntheticSource(frames=2, seed=3)
    a = src.frame(0)
    # frame t+1 = frame t shifted 40 px left: points near the left edge leave the image
    shift = 40
    col = np.zeros_like(a.color)
    col[:, :-shift] = a.color[:, shift:]
    dep = np.zeros_like(a.depth)
    dep[:, :-shift] = a.depth[:, shift:]
    b = a.with_(color=col, depth=dep, seq=1)
    r = SceneFlow(SceneFlowParams(max_points=100000)).compute(a, b)
    assert r.counts["out_of_image"] > 0
    assert r.pixels[:, 0].min() >= shift - 2
    assert np.median(r.pixels_next[:, 0] - r.pixels[:, 0]) == pytest.approx(-shift, abs=0.5)


def test_occluding_object_is_caught_by_forward_backward_check(pair):
    a, b = pair
    rng = np.random.default_rng(0)
    col = b.color.copy()
    # an object appears in frame t+1: a noise patch that has no counterpart in frame t
    col[150:300, 250:420] = rng.integers(0, 255, (150, 170, 3), dtype=np.uint8)
    b2 = b.with_(color=col)
    on = SceneFlow(SceneFlowParams(max_points=100000)).compute(a, b2)
    off = SceneFlow(SceneFlowParams(max_points=100000, fb_check=False)).compute(a, b2)

    def in_patch(r):
        u, v = r.pixels_next[:, 0], r.pixels_next[:, 1]
        return np.count_nonzero((u > 260) & (u < 410) & (v > 160) & (v < 290))

    assert on.counts["fb_inconsistent"] > 0
    assert in_patch(on) < 0.5 * in_patch(off)


def test_velocity_outliers_are_removed(pair):
    a, b = pair
    dep = b.depth.copy()
    dep[:60, :80] += 1.5  # a corner of frame t+1 jumps 1.5 m back: unnaturally large velocities
    r = SceneFlow(SceneFlowParams(max_points=100000, depth_edge=1.0)).compute(a, b.with_(depth=dep))
    speeds = np.linalg.norm(r.displacements, axis=1)
    assert r.counts["velocity_outlier"] > 50
    assert speeds.max() < 0.5


def test_depth_is_not_blended_across_edges():
    d = np.ones((4, 4), np.float32)
    d[:, 2:] = 3.0
    z = sample_depth(d, np.array([0.5, 1.5, 2.5]), np.array([1.0, 1.0, 1.0]), 0.05)
    np.testing.assert_allclose(z, [1.0, 0.0, 3.0])


def flow_error(pair, **params) -> float:
    """Median distance (px) from where the flow puts the samples in frame t+1 to where they really are."""
    a, b = pair
    M = point_motion(a, b)
    K = b.intrinsics
    r = SceneFlow(SceneFlowParams(**params)).compute(a, b)
    y = r.points @ M[:3, :3].T + M[:3, 3]  # where the sample's 3D point really is in frame t+1
    truth = np.column_stack((K.fx * y[:, 0] / y[:, 2] + K.cx, K.fy * y[:, 1] / y[:, 2] + K.cy))
    return float(np.median(np.linalg.norm(r.pixels_next - truth, axis=1)))


def test_lk_refinement_brings_sample_flow_closer_to_the_truth(pair):
    errs = {refine: flow_error(pair, refine=refine) for refine in ("none", "lk")}
    assert errs["lk"] < 0.75 * errs["none"], errs
    with pytest.raises(ValueError, match="refine"):
        SceneFlowParams(refine="sift").validate()


def test_lk_makes_up_for_a_sparser_dis_patch_grid(pair):
    """DIS with its patches further apart is coarser (it is only LK's start); refined, the flow is as good."""
    dis = {s: flow_error(pair, dis_stride=s, refine="none") for s in (4, 6, 8)}
    lk = {s: flow_error(pair, dis_stride=s) for s in (4, 6, 8)}
    assert dis[4] < dis[6] < dis[8], dis
    assert max(lk.values()) < 1.1 * min(lk.values()) < 0.5 * dis[4], (lk, dis)
    assert flow_error(pair, dis_stride=0) == lk[4]  # 0: the preset's own stride (ultrafast: 4)
    for bad in (-1, 9):
        with pytest.raises(ValueError, match="dis_stride"):
            SceneFlowParams(dis_stride=bad).validate()


def test_the_flow_reads_the_luma_a_decoder_gave(pair):
    """A frame decoded with its JPEG's own grey (RGBDFrame.luma) is flowed on that grey, exactly as a frame whose
    colour is that grey (BGR2GRAY gives back a grey replicated into B, G, R) and not as its colour's conversion."""
    import cv2

    def luma(f: RGBDFrame) -> np.ndarray:
        return cv2.imdecode(cv2.imencode(".jpg", f.color, [cv2.IMWRITE_JPEG_QUALITY, 70])[1], cv2.IMREAD_GRAYSCALE)

    a, b = pair
    given = SceneFlow(SceneFlowParams()).compute(a.with_(luma=luma(a)), b.with_(luma=luma(b)))
    grey = SceneFlow(SceneFlowParams()).compute(*(f.with_(color=cv2.merge([luma(f)] * 3)) for f in pair))
    own = SceneFlow(SceneFlowParams()).compute(a, b)
    assert np.array_equal(given.pixels_next, grey.pixels_next) and np.array_equal(given.points, grey.points)
    assert not np.array_equal(given.pixels_next, own.pixels_next)


def test_noisy_stereo_depth_is_not_taken_for_depth_edges(pair):
    """docs/method.md (1b): depth noise of a few percent (stereo, 0.012 z^2) would make most candidates
    'edges' at the fixed 3 %; the threshold follows the frame's own noise, so the flow keeps its samples,
    while a clean frame keeps 3 % (the same samples as before) and a real edge is still an edge."""
    from quick_stream.core.sceneflow.lift import candidate_grid, edge_threshold

    a, b = pair
    rng = np.random.default_rng(5)
    noisy = [f.with_(depth=(f.depth * (1 + 0.012 * f.depth * rng.standard_normal(f.depth.shape))).astype(np.float32))
             for f in (a, b)]
    fixed = SceneFlowParams(depth_edge_k=0.0)
    clean, noise_fixed, noise_adapt = (SceneFlow(p).compute(*fs) for p, fs in
                                       ((SceneFlowParams(), (a, b)), (fixed, noisy), (SceneFlowParams(), noisy)))
    assert noise_fixed.counts["depth_edge"] > 5 * clean.counts["depth_edge"]
    assert noise_adapt.counts["depth_edge"] < 0.4 * noise_fixed.counts["depth_edge"]
    assert len(noise_adapt) > 1.3 * len(noise_fixed)
    np.testing.assert_array_equal(SceneFlow(fixed).compute(a, b).points, clean.points)  # clean: 3 %
    g = candidate_grid(*a.depth.shape, 4)
    assert edge_threshold(a.depth, g.index, g.neighbours[0], SceneFlowParams()) == 0.03
    step = np.where(np.arange(a.depth.shape[1]) < 320, 1.0, 2.0).astype(np.float32)
    wall = np.broadcast_to(step, a.depth.shape) * (1 + 0.01 * rng.standard_normal(a.depth.shape))
    t = edge_threshold(wall.astype(np.float32), g.index, g.neighbours[0], SceneFlowParams())
    assert 0.03 < t < 0.5  # the noise raised it, the 100 % jump at the middle is still far above it


def test_forward_backward_limit_grows_with_the_flow():
    """docs/method.md (1a): a frame and its copy turned by a known rotation (the exact flow K R K^-1, about
    55 px here) and motion-blurred: the half-resolution backward flow disagrees with the forward one by
    more than the fixed 1.5 px on many good samples; the limit of 5 % of the flow keeps them, and what
    it keeps is still accurate."""
    import cv2

    from quick_stream.core.lie import so3

    a = SyntheticSource(frames=1, seed=4).frame(0)
    K = a.intrinsics.K
    H = K @ so3.exp(np.array([0.02, 0.1, 0.02])) @ np.linalg.inv(K)
    h, w = a.depth.shape
    ker = np.full((1, 21), 1 / 21, np.float32)  # horizontal blur over ~40 % of the motion
    c1 = cv2.filter2D(cv2.warpPerspective(a.color, H, (w, h)), -1, ker)
    d1 = cv2.warpPerspective(a.depth, H, (w, h), flags=cv2.INTER_NEAREST)
    f0 = a.with_(color=cv2.filter2D(a.color, -1, ker))
    f1 = a.with_(color=c1, depth=d1, seq=1, timestamp_ns=a.timestamp_ns + 33_000_000)
    grown = SceneFlow(SceneFlowParams(fb_scale=0.5)).compute(f0, f1)  # at 0.75 (the default) fewer disagree
    fixed = SceneFlow(SceneFlowParams(fb_scale=0.5, fb_rel=0.0)).compute(f0, f1)
    q = np.c_[grown.pixels, np.ones(len(grown))] @ H.T
    assert np.median(np.linalg.norm(grown.pixels_next - q[:, :2] / q[:, 2:], axis=1)) < 0.5
    assert np.median(np.linalg.norm(grown.pixels_next - grown.pixels, axis=1)) > 40
    assert grown.counts["fb_inconsistent"] < 0.8 * fixed.counts["fb_inconsistent"]
    assert len(grown) > 1.1 * len(fixed)
    with pytest.raises(ValueError, match="fb_rel"):
        SceneFlowParams(fb_rel=1.5).validate()


def test_flow_runs_at_a_scale_that_keeps_its_longer_side_within_the_limit():
    p = SceneFlowParams()
    assert p.flow_scale_for(480, 640) == 1.0  # 640x480 as it is: the default changes nothing there
    assert p.flow_scale_for(720, 1280) == 0.5
    assert p.flow_scale_for(1080, 1920) == pytest.approx(1 / 3)
    assert SceneFlowParams(flow_scale=0.5).flow_scale_for(480, 640) == 0.5  # the smaller of the two
    assert SceneFlowParams(flow_scale=0.25).flow_scale_for(720, 1280) == 0.25
    assert SceneFlowParams(flow_max_side=0).flow_scale_for(1080, 1920) == 1.0  # no limit
    for bad in (-1, 10, 63, 640.5):
        with pytest.raises(ValueError, match="flow_max_side"):
            SceneFlowParams(flow_max_side=bad).validate()


def test_a_720p_pair_flows_at_half_scale_and_its_samples_still_follow_ground_truth():
    src = SyntheticSource(frames=3, seed=11, width=1280, height=720)
    a, b = src.frame(0), src.frame(1)
    fwd, _ = SceneFlow(SceneFlowParams()).optical_flow(a, b)
    full, _ = SceneFlow(SceneFlowParams(flow_max_side=0)).optical_flow(a, b)
    assert full.shape[0] == 2 * fwd.shape[0] and full.shape[1] == 2 * fwd.shape[1]
    r = SceneFlow().compute(a, b)
    assert 1000 <= len(r) <= SceneFlowParams().max_points
    M = point_motion(a, b)
    err = np.linalg.norm(r.points + r.displacements - (r.points @ M[:3, :3].T + M[:3, 3]), axis=1)
    assert np.median(err) < 0.003  # metres, as at 640x480 and full scale (test_lifted_pairs_follow_ground_truth)
    assert r.pixels[:, 0].max() > 700  # the samples are the frame's own pixels, in its full-size units


def _turned_and_smeared(blur_px: int):
    """A synthetic frame, its copy turned by a known rotation and smeared by a horizontal motion blur of
    ``blur_px``, and the exact flow K R K^-1 between them."""
    import cv2

    from quick_stream.core.lie import so3

    a = SyntheticSource(frames=1, seed=4).frame(0)
    K = a.intrinsics.K
    H = K @ so3.exp(np.array([0.005, 0.03, 0.01])) @ np.linalg.inv(K)
    h, w = a.depth.shape
    c1 = cv2.filter2D(cv2.warpPerspective(a.color, H, (w, h)), -1, np.full((1, blur_px), 1 / blur_px, np.float32))
    d1 = cv2.warpPerspective(a.depth, H, (w, h), flags=cv2.INTER_NEAREST)
    return a, a.with_(color=c1, depth=d1, seq=1, timestamp_ns=a.timestamp_ns + 33_000_000), H


def test_a_flow_the_strict_tests_starve_under_motion_blur_is_lifted_loose():
    """docs/method.md (1c): a frame and its copy turned by a known rotation and smeared by a 61 px motion blur:
    LK and the 1.5 px forward-backward limit keep fewer than loose_below (50) samples; the same flow
    fields lifted loose keep thousands, marked ``loose``, and still follow the exact flow K R K^-1 to
    a few pixels. A sharp pair keeps its strict flow, bit for bit."""
    import cv2

    a, f1, H = _turned_and_smeared(61)
    h, w = a.depth.shape
    d1 = f1.depth
    strict = SceneFlow(SceneFlowParams(loose_below=0, loose_try_below=0)).compute(a, f1)
    loose = SceneFlow().compute(a, f1)
    assert len(strict) < 50 and "loose" not in strict.counts
    assert len(loose) > 1000 and loose.counts["loose"] == 1
    q = np.c_[loose.pixels, np.ones(len(loose))] @ H.T
    assert np.median(np.linalg.norm(loose.pixels_next - q[:, :2] / q[:, 2:], axis=1)) < 3.0
    sharp = a.with_(color=cv2.warpPerspective(a.color, H, (w, h)), depth=d1, seq=1,
                    timestamp_ns=a.timestamp_ns + 33_000_000)
    r0, r1 = SceneFlow(SceneFlowParams(loose_below=0, loose_try_below=0)).compute(a, sharp), SceneFlow().compute(a, sharp)
    assert "loose" not in r1.counts and np.array_equal(r0.pixels_next, r1.pixels_next) and len(r1) >= 50
    with pytest.raises(ValueError, match="loose_below"):
        SceneFlowParams(loose_below=-1).validate()


def test_a_flow_left_with_few_strict_pairs_takes_the_loose_lift_only_when_it_keeps_many_more():
    """docs/method.md (1c): below ``loose_try_below`` strict pairs the same fields are lifted loose too, and the
    loose flow is taken only when it keeps ``loose_gain`` times as many pairs (a few LK-exact pairs beat a
    few more DIS ones). A 41 px blur leaves a pair with more strict pairs than loose_below but far fewer
    than loose_try_below: the loose lift keeps several times as many, still on the exact flow K R K^-1."""
    a, f1, H = _turned_and_smeared(41)
    strict = SceneFlow(SceneFlowParams(loose_try_below=0)).compute(a, f1)
    assert 50 <= len(strict) < 400 and "loose" not in strict.counts
    taken = SceneFlow().compute(a, f1)
    assert taken.counts["loose"] == 1 and len(taken) >= 4 * len(strict)
    q = np.c_[taken.pixels, np.ones(len(taken))] @ H.T
    assert np.median(np.linalg.norm(taken.pixels_next - q[:, :2] / q[:, 2:], axis=1)) < 3.0
    kept = SceneFlow(SceneFlowParams(loose_gain=len(taken) / len(strict) + 0.01)).compute(a, f1)
    assert "loose" not in kept.counts and np.array_equal(kept.pixels_next, strict.pixels_next)
    with pytest.raises(ValueError, match="loose_gain"):
        SceneFlowParams(loose_gain=0.5).validate()

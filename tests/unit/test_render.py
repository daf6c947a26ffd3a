"""Rendering stage (docs/method.md section 5): content-preserving warp, one-remap render, framing."""
import cv2
import numpy as np
import pytest

from quick_stream.core.frame import Intrinsics, RGBDFrame
from quick_stream.core.render import (
    Framing, FramingParams, MeshWarp, WarpParams, ZoomSmoother, border_free_zoom, coverage,
    inverse_map, map_points, render, segment_zooms, solve_mesh, solve_warp, valid_mask,
)
from quick_stream.core.render.mapping import map_samples, rezoom_samples
from quick_stream.core.render.warp import bilinear_weights, control_pixels, grid_geometry

W, H = 640, 480


def texture(seed: int, w: int = W, h: int = H) -> np.ndarray:
    """Smooth random BGR texture (values 20..235, so black means 'no source')."""
    rng = np.random.default_rng(seed)
    small = rng.integers(20, 236, (h // 8, w // 8, 3), dtype=np.uint8)
    return cv2.GaussianBlur(cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC), (0, 0), 2.0)


def make_frame(seed: int = 0, depth: np.ndarray | None = None, cx: float = 318.6, cy: float = 255.3) -> RGBDFrame:
    rng = np.random.default_rng(seed + 100)
    if depth is None:
        depth = rng.uniform(1.0, 4.0, (H, W)).astype(np.float32)
    return RGBDFrame(texture(seed), depth, Intrinsics(520.0, 520.0, cx, cy, W, H), 0, seed)


def rigid(rotvec=(0.0, 0.0, 0.0), t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rotvec, float))[0]
    T[:3, 3] = t
    return T


def roll_affine(deg: float, cx: float, cy: float) -> np.ndarray:
    """2x3 image map of a camera-axis point rotation by ``deg`` (fx = fy) about (cx, cy)."""
    c, s = np.cos(np.deg2rad(deg)), np.sin(np.deg2rad(deg))
    A = np.array([[c, -s], [s, c]])
    return np.hstack((A, (np.array([cx, cy]) - A @ [cx, cy])[:, None]))


def similarity_fit_rms(src: np.ndarray, dst: np.ndarray) -> float:
    """RMS residual of the best 2D similarity src -> dst (complex least squares z' = a z + b)."""
    z = src[..., 0].ravel() + 1j * src[..., 1].ravel()
    zp = dst[..., 0].ravel() + 1j * dst[..., 1].ravel()
    A = np.column_stack((z, np.ones_like(z)))
    coef = np.linalg.lstsq(A, zp, rcond=None)[0]
    return float(np.sqrt(np.mean(np.abs(A @ coef - zp) ** 2)))


def test_identity_transform_gives_identity_mesh_and_image():
    f = make_frame(0)
    mesh = solve_warp(f, np.eye(4))
    assert mesh.ok and mesh.reason == ""
    assert mesh.dst.shape == (3, 3, 2) and mesh.n_controls > 1000
    assert np.abs(mesh.dst - mesh.src).max() < 1e-9
    assert mesh.residual_px < 1e-9
    out = render(f.color, mesh)
    diff = np.abs(out.astype(int) - f.color.astype(int))[2:-2, 2:-2]
    assert diff.max() <= 1


def test_roll_matches_warp_affine():
    f = make_frame(1)
    deg = 2.0
    mesh = solve_warp(f, rigid((0, 0, np.deg2rad(deg))))
    assert mesh.ok and mesh.residual_px < 1e-6
    M = roll_affine(deg, f.intrinsics.cx, f.intrinsics.cy)
    expect_dst = mesh.src @ M[:, :2].T + M[:, 2]
    assert np.abs(mesh.dst - expect_dst).max() < 1e-6
    out = render(f.color, mesh)
    ref = cv2.warpAffine(f.color, M, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    src_ok = np.zeros((H, W), np.uint8)
    src_ok[3:-3, 3:-3] = 255  # interior: away from the source border, where both blend with black
    inside = cv2.warpAffine(src_ok, M, (W, H), flags=cv2.INTER_NEAREST) > 0
    diff = np.abs(out.astype(float) - ref.astype(float))[inside]
    assert inside.mean() > 0.9 and diff.mean() < 0.2 and diff.max() <= 1
    # and the corners the rotation uncovers are black in both
    assert np.all(out[0, 0] == 0) and np.all(ref[0, 0] == 0)


def test_fronto_parallel_translation_is_an_image_shift():
    f = make_frame(2, depth=np.full((H, W), 2.0, np.float32))
    # shift = fx * t / Z: choose t so it is (+5, -3) px exactly
    tx, ty = 5 * 2.0 / 520.0, -3 * 2.0 / 520.0
    mesh = solve_warp(f, rigid(t=(tx, ty, 0.0)))
    assert mesh.ok and mesh.residual_px < 1e-6
    assert np.allclose(mesh.dst - mesh.src, [5.0, -3.0], atol=1e-6)
    out = render(f.color, mesh)
    # out[y, x] = in[y + 3, x - 5]
    diff = np.abs(out[2:H - 5, 7:W - 2].astype(int) - f.color[5:H - 2, 2:W - 7].astype(int))
    assert diff.max() <= 1
    assert np.all(out[:, :5] == 0) and np.all(out[H - 3:, :] == 0)
    assert coverage(mesh) == pytest.approx((W - 5) * (H - 3) / (W * H), abs=0.01)
    mask = valid_mask(inverse_map(mesh), W, H)
    assert not mask[:, :5].any() and mask[:H - 3, 5:].all()


def _bilinear_targets(pixels: np.ndarray, dst: np.ndarray) -> np.ndarray:
    geo = grid_geometry(W, H, dst.shape[1] - 1, dst.shape[0] - 1)
    ks, ws = bilinear_weights(pixels, geo)
    flat = dst.reshape(-1, 2)
    return np.einsum("nk,nkd->nd", ws, flat[ks])


def test_similarity_term_weight():
    rng = np.random.default_rng(3)
    geo = grid_geometry(W, H, 2, 2)
    bent = geo.src + rng.normal(0.0, 8.0, geo.src.shape)  # a mesh far from any similarity
    pixels = np.column_stack((rng.uniform(0, W - 1, 1500), rng.uniform(0, H - 1, 1500)))
    targets = _bilinear_targets(pixels, bent)
    exact = solve_mesh(pixels, targets, W, H, WarpParams(alpha=0.0))
    assert exact.ok and np.abs(exact.dst - bent).max() < 1e-6 and exact.residual_px < 1e-6
    stiff = solve_mesh(pixels, targets, W, H, WarpParams(alpha=1e6))
    assert stiff.ok and similarity_fit_rms(stiff.src, stiff.dst) < 1e-3
    assert stiff.residual_px > 3.0
    mid = solve_mesh(pixels, targets, W, H, WarpParams(alpha=0.1))
    assert exact.residual_px < mid.residual_px < stiff.residual_px
    assert similarity_fit_rms(mid.src, mid.dst) < similarity_fit_rms(exact.src, exact.dst)


def test_similarity_term_through_solve_warp():
    """A strongly non-similar (sheared, affine) point transform: alpha decides how much of it the mesh follows."""
    f = make_frame(4)
    T = np.eye(4)
    T[0, 1] = 0.05  # shear: not a rotation, so the image motion is not a similarity
    free = solve_warp(f, T, WarpParams(alpha=0.0))
    stiff = solve_warp(f, T, WarpParams(alpha=1e6))
    assert free.ok and stiff.ok
    assert free.residual_px < 0.5 * stiff.residual_px
    assert similarity_fit_rms(stiff.src, stiff.dst) < 1e-3 < similarity_fit_rms(free.src, free.dst)


def test_data_term_is_a_mean_so_alpha_is_resolution_free():
    """4x the control points must not change the data/shape balance (a summed data term would act like alpha / 4)."""
    f = make_frame(4)
    T = np.eye(4)
    T[0, 1] = 0.05
    few = solve_warp(f, T, WarpParams(max_control_points=500))
    many = solve_warp(f, T, WarpParams(max_control_points=2000))
    quarter_alpha = solve_warp(f, T, WarpParams(max_control_points=2000, alpha=0.025))
    assert many.n_controls > 3 * few.n_controls
    moved = np.abs(few.dst - many.dst).max()
    assert moved < 0.25 * np.abs(quarter_alpha.dst - many.dst).max()


def test_shape_term_does_not_resist_a_camera_rotation():
    """A rotation moves every pixel by K R K^-1 whatever its depth: the similarity term must not fight it.

    With the input grid as the shape reference (Liu et al. 2009, and this warp before), the default
    alpha held a 1.5/2/1 degree rotation back to 2.3 px of residual; the mesh can follow it to the
    bilinear cells' own limit (0.55 px, the alpha = 0 fit), at any stiffness. docs/method.md (13).
    """
    f = make_frame(22)  # random depth 1..4 m per pixel: only a rotation is parallax-free here
    T = rigid((np.deg2rad(1.5), np.deg2rad(2.0), np.deg2rad(1.0)))
    free = solve_warp(f, T, WarpParams(alpha=0.0))
    default = solve_warp(f, T)
    stiff = solve_warp(f, T, WarpParams(alpha=1e6))
    assert free.ok and default.ok and stiff.ok
    assert default.residual_px < free.residual_px + 1e-3
    assert stiff.residual_px < free.residual_px + 1e-2
    old = solve_warp(f, T, WarpParams(shape_reference="input"))  # the similarity-to-input term
    assert old.residual_px > 3 * default.residual_px
    with pytest.raises(ValueError, match="shape_reference"):
        WarpParams(shape_reference="homography").validate()


def test_the_mesh_never_shears_below_its_floor():
    """docs/method.md (13c): a correction with centimetres of translation over a scene whose depth runs
    from 0.5 m to 4 m shears the mesh at alpha = 0.1 (a cell's singular-value ratio well below 0.975);
    the solve raises alpha until no cell is below the floor. A large rotation's own perspective is no
    shear: it keeps alpha as it is. A clean small correction never meets the floor (bit for bit)."""
    depth = np.tile(np.linspace(0.5, 4.0, W, dtype=np.float32), (H, 1))
    f = make_frame(5, depth=depth)
    T = rigid((0.0, np.deg2rad(3.0), 0.0), (0.06, 0.03, 0.0))
    sheared = solve_warp(f, T, WarpParams(min_cell_ratio=0.0))
    held = solve_warp(f, T)
    assert sheared.cell_distortion().min() < 0.97
    assert held.cell_distortion().min() >= 0.975 and held.alpha > 0.1
    assert held.residual_px > sheared.residual_px  # it fits less rather than shear
    turn = rigid((np.deg2rad(2.0), np.deg2rad(14.0), 0.0))
    m = solve_warp(f, turn)
    assert m.alpha == 0.1 and m.cell_distortion().min() < 0.975  # the rotation's perspective, allowed
    small = rigid((0.001, 0.002, 0.0), (0.002, 0.0, 0.0))
    a, b = solve_warp(f, small), solve_warp(f, small, WarpParams(min_cell_ratio=0.0))
    assert a.alpha == 0.1 and np.array_equal(a.dst, b.dst)
    with pytest.raises(ValueError, match="min_cell_ratio"):
        WarpParams(min_cell_ratio=1.5).validate()


def test_border_free_zoom_identity_is_one():
    f = make_frame(5)
    assert border_free_zoom(solve_warp(f, np.eye(4))) == 1.0
    assert border_free_zoom(MeshWarp.identity(W, H), W, H) == 1.0
    with pytest.raises(ValueError):
        border_free_zoom(MeshWarp.identity(W, H), 320, 240)


def test_border_free_zoom_roll_is_analytic_and_exact():
    cx, cy = (W - 1) / 2, (H - 1) / 2  # rotation about the zoom centre: closed form below
    f = make_frame(6, cx=cx, cy=cy)
    th = np.deg2rad(3.0)
    mesh = solve_warp(f, rigid((0, 0, th)))
    s = border_free_zoom(mesh)
    expected = np.cos(th) + (cx / cy) * np.sin(th)  # the rotated-back rectangle's corner touches top/bottom
    assert s == pytest.approx(expected, rel=0.01)
    assert s == pytest.approx(expected, rel=1e-6)
    flat = np.full((H, W, 3), 200, np.uint8)
    assert render(flat, mesh, s).min() >= 190  # no black (at most a 1/32-pixel blend at the very corner)
    assert valid_mask(inverse_map(mesh, s), W, H).all()
    assert (render(flat, mesh, 0.97 * s) == 0).any()
    assert coverage(mesh, s) == 1.0 and coverage(mesh, 0.97 * s) < 1.0


def _boundary(n: int = 64) -> np.ndarray:
    t = np.linspace(0.0, 1.0, n)
    xs, ys = t * (W - 1), t * (H - 1)
    return np.concatenate([
        np.column_stack((xs, np.zeros(n))), np.column_stack((xs, np.full(n, H - 1.0))),
        np.column_stack((np.zeros(n), ys)), np.column_stack((np.full(n, W - 1.0), ys)),
    ])


def _inside(pts: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    return (pts[:, 0] >= -tol) & (pts[:, 0] <= W - 1 + tol) & (pts[:, 1] >= -tol) & (pts[:, 1] <= H - 1 + tol)


@pytest.mark.parametrize("seed", [7, 8, 9])
def test_border_free_zoom_agrees_with_the_inverse_map(seed):
    """Closed form vs. bisection on the output boundary mapped through the (exact) inverse map."""
    rng = np.random.default_rng(seed)
    f = make_frame(seed)
    T = rigid(rng.normal(0, 0.02, 3), rng.normal(0, 0.03, 3))
    mesh = solve_warp(f, T)
    assert mesh.ok
    s = border_free_zoom(mesh)
    assert s > 1.003
    bd = _boundary(256)
    assert _inside(map_points(mesh, bd, s)).all()
    lo, hi = 1.0, 3.0
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if _inside(map_points(mesh, bd, mid)).all() else (mid, hi)
    assert s == pytest.approx(hi, rel=2e-3)
    assert not _inside(map_points(mesh, bd, 0.99 * s)).all()


@pytest.mark.parametrize("seed", [7, 8])
def test_samples_zoomed_in_from_those_of_a_lower_zoom_agree_with_solving_again(seed):
    """docs/method.md 5.2: the border fill raises a frame's zoom after its samples were made."""
    rng = np.random.default_rng(seed)
    mesh = solve_warp(make_frame(seed), rigid(rng.normal(0, 0.02, 3), rng.normal(0, 0.03, 3)))
    low = map_samples(mesh, 1.02)
    for z, tol in ((1.02, 1e-6), (1.05, 0.05), (1.3, 0.05)):  # near a cell edge (a kink of the map) the most
        got = rezoom_samples(low, W, H, 1.02, z)
        want = map_samples(mesh, z)
        assert got.shape == want.shape and got.dtype == np.float32
        assert np.abs(got - want).max() < tol, z
    assert np.abs(rezoom_samples(low, W, H, 1.02, 1.3) - map_samples(mesh, 1.02)).max() > 10  # it did zoom
    assert rezoom_samples(low, W, H, 1.02, 1.01) is None  # zooming out would leave the grid


def _sample_map(inv_map: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Bilinear interpolation (float64) of an (H, W, 2) inverse map at float output points q (N, 2)."""
    x0 = np.clip(np.floor(q[:, 0]).astype(int), 0, inv_map.shape[1] - 2)
    y0 = np.clip(np.floor(q[:, 1]).astype(int), 0, inv_map.shape[0] - 2)
    ax = (q[:, 0] - x0)[:, None]
    ay = (q[:, 1] - y0)[:, None]
    m = inv_map.astype(np.float64)
    return ((1 - ax) * (1 - ay) * m[y0, x0] + ax * (1 - ay) * m[y0, x0 + 1]
            + (1 - ax) * ay * m[y0 + 1, x0] + ax * ay * m[y0 + 1, x0 + 1])


def test_render_shows_each_control_point_where_the_fit_put_it():
    """Fit and render share the bilinear cell model: the rendered map sends B @ X back to the control pixel.

    A slanted, bumpy depth and a realistic correction (2 deg yaw + 3 cm) bend the cells away from
    parallelograms; a per-cell homography renderer disagreed with the fit by 0.58 px here.
    """
    from quick_stream.core.render.warp import prepare_warp

    yy, xx = np.mgrid[0:H, 0:W]
    depth = (1.2 + 1.6 * yy / H + 0.6 * xx / W + 0.4 * np.sin(xx / 60.0) * np.cos(yy / 45.0)).astype(np.float32)
    f = make_frame(21, depth=depth)
    mesh = solve_warp(f, rigid((0.0, np.deg2rad(2.0), 0.0), (0.03, 0.01, 0.02)))
    assert mesh.ok and mesh.residual_px > 1.0  # parallax the mesh cannot follow: the cells really bend
    wi = prepare_warp(f)
    q = np.column_stack((wi.B @ mesh.dst[..., 0].ravel(), wi.B @ mesh.dst[..., 1].ravel()))  # fitted outputs
    inside = (q[:, 0] >= 0) & (q[:, 0] <= W - 1) & (q[:, 1] >= 0) & (q[:, 1] <= H - 1)
    assert inside.mean() > 0.9
    q, pix = q[inside], wi.pixels[inside]
    assert np.abs(map_points(mesh, q) - pix).max() < 1e-6  # the exact inverse map
    for step in (1, 4):  # 4: render's default
        err = np.linalg.norm(_sample_map(inverse_map(mesh, step=step), q) - pix, axis=1)
        assert err.max() < 0.05, (step, err.max())


def test_zoom_smoother():
    p = FramingParams(mode="auto", max_zoom=1.5, fall_per_frame=0.005, rise_per_frame=0.01)
    sm = ZoomSmoother(p)
    rng = np.random.default_rng(10)
    segs = [1.0 + np.abs(rng.normal(0, 0.05, 30)) for _ in range(4)]
    segs[1][10] = 1.3  # a spike to anticipate
    segs.append(np.ones(30))  # requirement drops to 1: must ramp down, not jump
    segs.append(np.full(5, np.inf))  # no border-free zoom: capped
    out = [sm.smooth(r) for r in segs]
    for r, z in zip(segs, out):
        assert np.all(z >= np.minimum(r, p.max_zoom) - 1e-12) and np.all(z <= p.max_zoom)
        assert np.all(np.diff(z) <= p.rise_per_frame + 1e-12)  # rises are anticipated within a segment
    z = np.concatenate(out)
    assert np.all(np.diff(z) >= -p.fall_per_frame - 1e-12)  # bounded falls, across segments too
    assert out[1][10] == pytest.approx(1.3) and out[1][0] < 1.3  # ramped up ahead of the spike
    assert out[4][0] == pytest.approx(out[3][-1] - p.fall_per_frame)  # continues from the last zoom
    assert np.all(out[5] == p.max_zoom)
    assert sm.last == p.max_zoom
    sm.reset()
    assert sm.smooth([1.0, 1.0])[0] == 1.0


def _cover_whole_segment(p: FramingParams, last_lift: float, planned, required) -> tuple[np.ndarray, float]:
    """The zoom track with every frame of the segment ahead (docs/method.md (14a) with no look-ahead
    bound): one backward pass over the segment, then the slow fall forward; and its last raise."""
    z = np.asarray(planned, float)
    lift = np.maximum(np.clip(np.nan_to_num(np.asarray(required, float), nan=np.inf), 1.0,
                              max(p.fill_zoom_max, z.max())) - z, 0.0)
    for i in range(len(lift) - 2, -1, -1):
        lift[i] = max(lift[i], lift[i + 1] - p.fill_lift_rate)
    for i in range(len(lift)):
        lift[i] = last_lift = max(lift[i], last_lift - p.fill_lift_rate)
    return z + lift, last_lift


def test_cover_with_the_whole_segment_ahead_is_one_backward_pass():
    rng = np.random.default_rng(3)
    p = FramingParams(mode="auto", fill_lookahead=1000)
    sm, lift = ZoomSmoother(p), 0.0
    for n in (1, 7, 30):
        planned = 1.0 + np.abs(rng.normal(0, 0.02, n))
        required = planned + np.where(rng.random(n) < 0.3, rng.uniform(0, 0.05, n), -0.01)
        required[rng.integers(n)] = np.nan  # no zoom covers it: capped at fill_zoom_max
        want, lift = _cover_whole_segment(p, lift, planned, required)
        got = sm.cover(planned, required)
        assert np.array_equal(got, want)  # bit for bit
        assert sm.last == want[-1] and sm.lift == lift


def test_cover_rises_start_at_most_the_lookahead_ahead_and_estimates_are_asked_lazily():
    p = FramingParams(mode="auto", fill_lookahead=4)
    planned, raise_at = np.ones(30), 20
    required = planned.copy()
    required[raise_at] = 1.05
    asked: list[int] = []

    def need(j: int) -> float:
        asked.append(j)
        return float(required[j])

    zooms = ZoomSmoother(p).cover_frames(planned, need)
    got = []
    for i in range(30):
        got.append(next(zooms))
        assert asked == list(range(min(i + p.fill_lookahead, 29) + 1))  # each once, in order, no further
    got = np.array(got)
    start = raise_at - p.fill_lookahead
    assert np.all(got[:start] == 1.0)  # nothing before the look-ahead sees the rise
    ramp = 1.05 - p.fill_lift_rate * (raise_at - np.arange(start, raise_at + 1))
    assert got[start:raise_at + 1] == pytest.approx(ramp, abs=1e-12)
    assert np.all(np.diff(got[raise_at:]) == pytest.approx(-p.fill_lift_rate, abs=1e-12))  # falls slowly
    assert np.array_equal(ZoomSmoother(p).cover(planned, required), got)
    with pytest.raises(ValueError, match="fill_lookahead"):
        FramingParams(fill_lookahead=-1).validate()


def test_framing_modes_and_validation():
    assert Framing.parse("auto") is Framing.AUTO and Framing.parse(Framing.CROP) is Framing.CROP
    with pytest.raises(ValueError, match="framing must be one of"):
        Framing.parse("zoom")
    with pytest.raises(ValueError):
        FramingParams(mode="zoom").validate()
    with pytest.raises(ValueError):
        FramingParams(crop_zoom=0.9).validate()
    meshes = [MeshWarp.identity(W, H), solve_warp(make_frame(11), rigid((0, 0, 0.03)))]
    assert np.all(segment_zooms(meshes, FramingParams(mode="black")) == 1.0)
    assert np.all(segment_zooms(meshes, FramingParams(mode="crop", crop_zoom=1.2)) == 1.2)
    with pytest.raises(ValueError, match="ZoomSmoother"):
        segment_zooms(meshes, FramingParams(mode="auto"))
    p = FramingParams(mode="auto")
    z = segment_zooms(meshes, p, ZoomSmoother(p))
    assert z[1] >= border_free_zoom(meshes[1]) and z[0] >= z[1] - p.rise_per_frame - 1e-12


def test_too_few_control_points_gives_flagged_identity():
    depth = np.zeros((H, W), np.float32)
    depth[100:102, 200:203] = 2.0  # 6 valid pixels
    f = make_frame(12, depth=depth)
    mesh = solve_warp(f, rigid((0, 0, 0.05), (0.1, 0, 0)))
    assert not mesh.ok and "too few control points" in mesh.reason
    assert np.array_equal(mesh.dst, mesh.src) and mesh.n_controls == 6
    out = render(f.color, mesh)
    assert np.abs(out.astype(int) - f.color.astype(int))[2:-2, 2:-2].max() <= 1


def test_singular_and_folded_systems_are_flagged():
    rng = np.random.default_rng(13)
    pixels = np.column_stack((rng.uniform(0, 300, 200), rng.uniform(0, 200, 200)))  # top-left cell only
    bad = solve_mesh(pixels, pixels + 1.0, W, H, WarpParams(alpha=0.0))
    assert not bad.ok and "singular" in bad.reason and np.array_equal(bad.dst, bad.src)
    good = solve_mesh(pixels, pixels + 1.0, W, H, WarpParams(alpha=0.1))  # the similarity term fills in
    assert good.ok and np.allclose(good.dst - good.src, 1.0, atol=1e-6)
    pixels = np.column_stack((rng.uniform(0, W - 1, 500), rng.uniform(0, H - 1, 500)))
    mirrored = np.column_stack((W - 1 - pixels[:, 0], pixels[:, 1]))
    folded = solve_mesh(pixels, mirrored, W, H, WarpParams(alpha=0.0))
    assert not folded.ok and "fold" in folded.reason


def test_control_points_behind_camera_are_dropped_and_sampling_is_bounded():
    f = make_frame(14)
    idx, z = control_pixels(f.depth, 2000)
    assert 1000 < idx.size <= 2000 and np.all(z > 0)
    sparse = f.depth.copy()
    sparse[:, : W * 3 // 4] = 0  # a quarter valid: a finer grid keeps about as many points
    idx2, _ = control_pixels(sparse, 2000)
    assert 1000 < idx2.size <= 2000 and np.all(idx2 % W >= W * 3 // 4)
    ahead = solve_warp(f, rigid(t=(0, 0, -2.5)), WarpParams(alpha=0.1))  # depths 1..4 m: most land behind
    full = solve_warp(f, np.eye(4))
    assert 0 < ahead.n_controls < 0.6 * full.n_controls


def test_determinism():
    f = make_frame(15)
    T = rigid((0.01, -0.02, 0.015), (0.02, 0.01, -0.03))
    a = solve_warp(f, T)
    b = solve_warp(make_frame(15), T.copy())
    assert np.array_equal(a.dst, b.dst) and a.residual_px == b.residual_px
    ra = render(f.color, a, 1.07)
    rb = render(f.color.copy(), b, 1.07)
    assert np.array_equal(ra, rb)
    assert np.array_equal(inverse_map(a, 1.07), inverse_map(b, 1.07))


def test_prepared_warp_inputs_give_the_same_mesh_bit_for_bit():
    """A renderer prepares each frame's warp inputs on arrival (prepare_warp); the mesh must not change."""
    from quick_stream.core.render.warp import prepare_warp

    f = make_frame(16)
    prep = prepare_warp(f)
    for T in (rigid((0.01, -0.02, 0.015), (0.02, 0.01, -0.03)), rigid(t=(0, 0, -2.5)), np.eye(4)):
        a, b = solve_warp(f, T), solve_warp(f, T, prepared=prep)
        assert np.array_equal(a.dst, b.dst) and a.residual_px == b.residual_px
        assert a.ok == b.ok and a.n_controls == b.n_controls

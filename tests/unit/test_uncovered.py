"""The border band of a render (docs/method.md 5.2, 5.4): found and filled without full-frame passes,
with exactly the full-frame passes' results."""
import cv2
import numpy as np
import pytest

from quick_stream.core.render import MeshWarp, inverse_map, map_points, render, valid_mask
from quick_stream.core.render.fill import FillSource, border_pixels, fill_border, nearest_depth
from quick_stream.core.render.mapping import map_samples, render_covered
from quick_stream.core.render.uncovered import MERGE_GAP, depth_lookup, lookup, patches
from tests.unit.test_render import H, W, texture


def shaken_mesh(seed: int, shift: float = 12.0) -> MeshWarp:
    """A 2x2 mesh whose vertices moved up to ``shift`` px: its outer edges leave bands uncovered."""
    mesh = MeshWarp.identity(W, H)
    mesh.dst = mesh.src + np.random.default_rng(seed).uniform(-shift, shift, mesh.src.shape)
    return mesh


def full_frame_border(uncovered: np.ndarray, feather: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What :func:`border_pixels` measures on patches, over the whole frame (the renderer's former pass)."""
    dist = cv2.distanceTransform((~uncovered).astype(np.uint8), cv2.DIST_L2, 3)
    ys, xs = np.nonzero(uncovered | ((dist > 0) & (dist <= feather)))
    return ys, xs, dist[ys, xs]


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("zoom", [1.0, 1.04, 1.12])
def test_uncovered_pixels_are_exactly_the_full_maps(seed, zoom):
    mesh = shaken_mesh(seed)
    img = texture(seed)
    depth = np.random.default_rng(seed).uniform(0.5, 4.0, (H, W)).astype(np.float32)
    out, uncovered, depth_at = render_covered(img, depth, mesh, zoom)
    inv = inverse_map(mesh, zoom)
    want = ~valid_mask(inv, W, H)
    assert np.array_equal(out, render(img, mesh, zoom))
    if not want.any():
        assert uncovered is None and depth_at is None
        return
    assert np.array_equal(uncovered, want)
    ys, xs = np.nonzero(want | (np.random.default_rng(seed).random((H, W)) < 0.01))
    nearest = cv2.remap(depth, inv, None, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    assert np.array_equal(depth_at(ys, xs), nearest[ys, xs])
    every = slice(None, None, 4)
    assert np.array_equal(depth_at(every, every), nearest[::4, ::4].ravel())


def test_the_renderer_reuses_the_cover_estimates_samples_bit_for_bit():
    mesh = shaken_mesh(3)
    img = texture(3)
    assert np.array_equal(render(img, mesh, 1.07, samples=map_samples(mesh, 1.07)), render(img, mesh, 1.07))


def bands(seed: int) -> np.ndarray:
    """Uncovered-looking masks: bands of random depth along random edges, blobs, and a stray pixel."""
    rng = np.random.default_rng(seed)
    m = np.zeros((H, W), bool)
    for edge in rng.choice(4, rng.integers(1, 5), replace=False):
        depth = rng.integers(1, 40, W if edge < 2 else H)
        depth = np.maximum(depth - rng.integers(0, 40), 0)
        for i, d in enumerate(depth):
            if edge == 0:
                m[:d, i] = True
            elif edge == 1:
                m[H - d:, i] = True
            elif edge == 2:
                m[i, :d] = True
            else:
                m[i, W - d:] = True
    m[rng.integers(0, H), rng.integers(0, W)] = True
    if seed % 3 == 0:
        y, x = rng.integers(50, H - 50), rng.integers(50, W - 50)
        m[y - 20:y + 20, x - 30:x + 30] = True
    return m


@pytest.mark.parametrize("seed", range(12))
@pytest.mark.parametrize("feather", [0, 1, 4, 9])
def test_border_pixels_on_patches_are_the_full_frames(seed, feather):
    m = bands(seed)
    ys, xs, dist = border_pixels(m, feather)
    want = full_frame_border(m, feather) if feather else (*np.nonzero(m), np.zeros(int(m.sum()), np.float32))
    np.testing.assert_array_equal(ys, want[0])
    np.testing.assert_array_equal(xs, want[1])
    # the same distances, to the last bit or one off it: OpenCV sums a path's steps in float, and two step
    # paths of one length (through pixels a patch does not hold) can round apart
    np.testing.assert_allclose(dist, want[2], rtol=1e-6, atol=0)


@pytest.mark.parametrize("seed", range(8))
def test_patches_hold_every_pixel_near_a_marked_one_in_exactly_one_rectangle(seed):
    m = bands(seed)
    margin = 6
    near = cv2.dilate(m.view(np.uint8), np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)) > 0
    count = np.zeros((H, W), int)
    for t0, t1, a, b, c0, c1 in patches(m, margin):
        assert a <= t0 < t1 <= b and 0 <= c0 < c1 <= W
        count[t0:t1, c0:c1] += 1
    assert np.all(count[near] == 1)
    assert patches(np.zeros((H, W), bool), margin) == []


def strip_by_strip(mask: np.ndarray, margin: int, rows: int) -> list[tuple[int, int, int, int, int, int]]:
    """:func:`patches` written plainly, one strip at a time (the reference its vectorised strips must match)."""
    h, w = mask.shape
    ys, xs = np.nonzero(mask)
    if ys.size == 0:
        return []
    a, b = max(int(ys.min()) - margin, 0), min(int(ys.max()) + 1 + margin, h)
    c0, c1 = max(int(xs.min()) - margin, 0), min(int(xs.max()) + 1 + margin, w)
    if (b - a) * (c1 - c0) <= h * w // 8 or b - a <= rows + 2 * margin:
        return [(a, b, a, b, c0, c1)]
    marked = np.flatnonzero(mask.any(axis=1))
    out = []
    for r0 in range(a // rows * rows, b, rows):
        r1 = min(r0 + rows, h)
        near = marked[(marked >= r0 - margin) & (marked < r1 + margin)]
        if near.size == 0:
            continue
        t0, t1 = max(r0, int(near[0]) - margin), min(r1, int(near[-1]) + margin + 1)
        ra, rb = max(t0 - margin, 0), min(t1 + margin, h)
        cols = np.flatnonzero(mask[ra:rb].any(axis=0))
        run = [int(cols[0])]
        for c, prev in zip(cols[1:].tolist(), cols[:-1].tolist()):
            if c - prev > max(2 * margin + 1, MERGE_GAP):
                out.append((t0, t1, ra, rb, max(run[0] - margin, 0), min(prev + 1 + margin, w)))
                run = [c]
        out.append((t0, t1, ra, rb, max(run[0] - margin, 0), min(int(cols[-1]) + 1 + margin, w)))
    return out


@pytest.mark.parametrize("seed", range(4))
def test_patches_are_the_strip_by_strip_rectangles(seed):
    """Any mask (rows of whole 8-pixel words or not, strided, bands and specks), margin and strip height:
    the strips worked out together give the plain per-strip rectangles, in the same order."""
    rng = np.random.default_rng(seed)
    cases = [(bands(seed), 6, 32), (bands(seed + 10)[::-1], 0, 16)]
    for _ in range(400):
        h, w = int(rng.integers(1, 90)), int(rng.integers(1, 100))
        m = rng.random((h, w)) < rng.choice([0.002, 0.02, 0.2, 0.6])
        m = m[:, ::-1] if rng.random() < 0.3 else m
        cases.append((m, int(rng.integers(0, 8)), int(rng.integers(1, 40))))
    for m, margin, rows in cases:
        got = patches(m, margin, rows)
        assert got == strip_by_strip(m, margin, rows)
        assert all(type(v) is int for r in got for v in r)


def test_lookup_takes_any_number_of_points():
    img = texture(5)
    rng = np.random.default_rng(5)
    for n in (0, 1, 4096, 4097, 40000):  # cv2.remap alone refuses maps of 32767 columns or more
        pts = rng.uniform(-2, [W + 1, H + 1], (n, 2)).astype(np.float32)
        got = lookup(img, pts, cv2.INTER_LINEAR, cv2.BORDER_REPLICATE)
        assert got.shape == (n, 3)
        if n:
            want = cv2.remap(img, pts[None, :1000], None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)[0]
            np.testing.assert_array_equal(got[:1000], want)


def test_a_border_wider_than_a_remap_row_is_filled():
    """Over 32767 pixels to fill from one source (an 80 px band and its seam): once beyond cv2.remap's limit."""
    img = texture(6)
    K = np.array([[520.0, 0, W / 2], [0, 520.0, H / 2], [0, 0, 1]])
    band = np.zeros((H, W), bool)
    band[:, :80] = True
    out = np.where(band[..., None], 0, img).astype(np.uint8)
    depth = np.full((H, W), 2.0, np.float32)
    inv = inverse_map(MeshWarp.identity(W, H))
    left = fill_border(out, band, depth_lookup(np.where(band, 0, depth).astype(np.float32), inv), K, 1.0, np.eye(4),
                       [FillSource(1, 0, np.eye(4), img, K)])
    assert not left.any() and np.abs(out.astype(int) - img).max() <= 1


def test_opencv_labels_the_known_pixels_in_raster_order():
    """nearest_depth takes each label's depth in raster order: DIST_LABEL_PIXEL's numbering."""
    rng = np.random.default_rng(7)
    known = rng.random((61, 83)) < 0.3
    _, labels = cv2.distanceTransformWithLabels((~known).astype(np.uint8), cv2.DIST_L2, 3,
                                                labelType=cv2.DIST_LABEL_PIXEL)
    np.testing.assert_array_equal(labels[known], np.arange(1, known.sum() + 1))
    depth = np.where(known, rng.uniform(1, 3, known.shape), 0.0)
    full = nearest_depth(depth)
    rows, cols = np.nonzero(~known)
    np.testing.assert_array_equal(nearest_depth(depth, (rows, cols)), full[rows, cols])


def test_map_points_and_the_samples_agree():
    mesh = shaken_mesh(8)
    low = map_samples(mesh, 1.05)
    q = np.array([[1.5, 1.5], [5.5, 9.5], [637.5, 477.5]])  # sample positions: step (j - 1) + 1.5
    j = ((q + 2.5) / 4).astype(int)
    np.testing.assert_allclose(low[j[:, 1], j[:, 0]], map_points(mesh, q, 1.05), atol=1e-3)

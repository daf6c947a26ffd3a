"""Border-free cropping (quick_stream.quality.metrics_border) on synthetic frames with known borders, and
on frames with dark scene content at their edge (synthetic, and a real TUM fr1/rpy frame when
../shared/data is present)."""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from quick_stream.quality.metrics import MetricsAccumulator
from quick_stream.quality.metrics_border import (DEFAULT_MARGIN, BorderFreeAccumulator, border_free_cropping,
                                                 border_free_scale, content_mask, scale_from_mask,
                                                 sequence_border_free_scale, uncovered_mask)

W, H = 200, 150


def bright(w: int = W, h: int = H, seed: int = 0) -> np.ndarray:
    """Textured BGR frame with no pixel at or below the black level."""
    rng = np.random.default_rng(seed)
    return rng.integers(60, 255, (h, w, 3), dtype=np.uint8)


def test_no_border_is_scale_one():
    f = bright()
    assert not uncovered_mask(f).any()
    assert border_free_scale(f) == 1.0
    assert border_free_cropping(0.9, 1.0) == pytest.approx(0.9)


@pytest.mark.parametrize("side", ["left", "right", "top", "bottom"])
def test_black_band_gives_its_exact_scale(side):
    f = bright()
    k = 10
    if side == "left":
        f[:, :k] = 0
        expect = 1 - 2 * k / W
    elif side == "right":
        f[:, -k:] = 0
        expect = 1 - 2 * k / W
    elif side == "top":
        f[:k] = 0
        expect = 1 - 2 * k / H
    else:
        f[-k:] = 0
        expect = 1 - 2 * k / H
    assert uncovered_mask(f).sum() == k * (H if side in ("left", "right") else W)
    assert border_free_scale(f) == pytest.approx(expect)


def test_near_black_level_and_greyscale_input():
    f = bright()
    f[:, :6] = 10  # at the level: uncovered
    f[:, 6:12] = (10, 10, 11)  # one channel above it: covered
    assert border_free_scale(f) == pytest.approx(1 - 2 * 6 / W)
    assert border_free_scale(f, level=11) == pytest.approx(1 - 2 * 12 / W)
    g = cv2.cvtColor(f, cv2.COLOR_BGR2GRAY)
    g[:, :6] = 0
    g[:, 6:] = np.maximum(g[:, 6:], 50)
    assert border_free_scale(g) == pytest.approx(1 - 2 * 6 / W)


def test_rotated_frame_with_black_corners():
    theta = 5.0
    f = np.full((H, W, 3), 200, np.uint8)
    M = cv2.getRotationMatrix2D((W / 2 - 0.5, H / 2 - 0.5), theta, 1.0)
    r = cv2.warpAffine(f, M, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    c, s = math.cos(math.radians(theta)), math.sin(math.radians(theta))
    expect = min(W / (W * c + H * s), H / (W * s + H * c))  # largest centred W:H rectangle in the rotated frame
    got = border_free_scale(r)
    assert got == pytest.approx(expect, abs=2.5 / H)
    assert got < 1.0
    # the corners are uncovered, the centre is not
    m = uncovered_mask(r)
    assert m[0, 0] and m[-1, -1] and not m[H // 2, W // 2]


def test_dark_content_inside_the_frame_does_not_count():
    f = bright()
    f[50:100, 60:140] = 0  # a black object in the middle
    f[5:20, 5:20] = 3  # a dark patch near, but not touching, the border
    assert not uncovered_mask(f).any()
    assert border_free_scale(f) == 1.0
    f[0:20, 5:20] = 3  # now it touches the border: uncovered
    assert uncovered_mask(f)[10, 10] and not uncovered_mask(f)[75, 100]
    assert border_free_scale(f) < 1.0


def test_dark_object_touching_a_band_is_one_region():
    f = bright()
    f[:, :8] = 0
    f[70:80, 8:60] = 0  # a dark bar across the centre row, joined to the band, reaches 60 px in
    assert border_free_scale(f) == pytest.approx(1 - 2 * 60 / W)


def test_centre_line_pixel_gives_zero_and_mask_formula():
    m = np.zeros((5, 7), bool)
    m[2, 3] = True  # the centre pixel of an odd-sized frame
    assert scale_from_mask(m) == 0.0
    m = np.zeros((4, 8), bool)
    m[0, 0] = True  # a corner pixel
    assert scale_from_mask(m) == pytest.approx(max(1 - 2 / 8, 1 - 2 / 4))


def test_sequence_scale_is_the_minimum_over_frames():
    frames = [bright(seed=i) for i in range(4)]
    frames[1][:, :4] = 0
    frames[3][:12] = 0
    acc = BorderFreeAccumulator()
    for f in frames:
        acc.add(f)
    expect = min(1 - 2 * 4 / W, 1 - 2 * 12 / H)
    assert acc.scale == pytest.approx(expect)
    assert acc.frames == 4 and acc.frames_with_border == 2 and acc.worst_frame == 3
    assert sequence_border_free_scale(frames) == pytest.approx(expect)
    assert border_free_cropping(0.95, acc.scale) == pytest.approx(0.95 * expect)


# --------------------------------------------------------------------------------------------
# dark scene content at the border: only what the stabiliser left uncovered counts

SHARED_DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
FR1_RPY_DARK = "rgb/1305031234.261752.jpg"  # tum_fr1_rpy frame 142: a black monitor joined to the top edge


def textured(w: int = W, h: int = H, seed: int = 1) -> np.ndarray:
    """Blurred-noise texture (SIFT finds it), every pixel well above the black level."""
    rng = np.random.default_rng(seed)
    acc = sum(s * cv2.GaussianBlur(rng.normal(0, 1, (h, w)).astype(np.float32), (0, 0), s) for s in (1.5, 3.0, 6.0))
    grey = np.clip(150 + 50 * (acc - acc.mean()) / acc.std(), 50, 250).astype(np.uint8)
    return cv2.merge([grey, np.roll(grey, 5, axis=1), np.roll(grey, 3, axis=0)])


def shifted_right(img: np.ndarray, k: int) -> np.ndarray:
    """The image moved k px to the right, a black band of k columns on the left (a stabiliser's warp)."""
    out = np.zeros_like(img)
    out[:, k:] = img[:, :-k]
    return out


def translation(dx: float) -> np.ndarray:
    """Output -> input homography (centred coordinates) of an output moved dx px to the right."""
    return np.array([[1.0, 0.0, -dx], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


def scored(inp: np.ndarray, out: np.ndarray) -> tuple[float, BorderFreeAccumulator, np.ndarray | None]:
    """Border-free scale of ``out`` with the homography the quality metrics fit to (``inp``, ``out``)."""
    m = MetricsAccumulator()
    m.add(inp, out)
    acc = BorderFreeAccumulator()
    return acc.add(out, inp, m.last_homography), acc, m.last_homography


def with_dark_top(img: np.ndarray) -> np.ndarray:
    f = img.copy()
    f[0:60, 60:140] = 3  # dark content (a black screen) reaching the top edge
    return f


def test_content_mask_follows_the_homography():
    inp = bright()
    inp[30:50, 50:70] = 0
    m = content_mask(inp, translation(12), inp.shape, margin=0)
    expect = np.zeros((H, W), bool)
    expect[30:50, 62:82] = True
    assert np.array_equal(m, expect)
    grown = content_mask(inp, translation(12), inp.shape, margin=3)
    assert grown[27, 72] and grown[40, 59] and not grown[40, 58] and not grown[26, 72]
    assert not content_mask(bright(), translation(12), inp.shape).any()
    # output pixels the homography maps outside the input are not content, even if the input is black there
    dark_edge = bright()
    dark_edge[:, :5] = 0
    assert not content_mask(dark_edge, translation(30), inp.shape, margin=0)[:, :30].any()


def test_input_scored_against_itself_is_border_free_with_dark_content_at_its_edge():
    f = with_dark_top(textured())
    assert border_free_scale(f) < 0.3  # the plain rule takes the dark screen for a border
    s, acc, h = scored(f, f)
    assert h is not None and np.allclose(h, np.eye(3), atol=0.05)
    assert s == 1.0 and acc.scale == 1.0 and acc.frames_unaligned == 0


def test_a_band_added_by_a_shift_is_detected_with_its_scale():
    f = with_dark_top(textured())
    out = shifted_right(f, 12)
    s, acc, h = scored(f, out)
    assert h is not None and abs(h[0, 2] + 12) < 0.5
    assert s == pytest.approx(1 - 2 * 12 / W)
    assert acc.add(out, f, translation(12)) == pytest.approx(1 - 2 * 12 / W)
    assert acc.frames_with_border == 2


def test_dark_content_next_to_a_band_does_not_hide_it():
    f = bright()
    f[20:50, 0:40] = 0  # dark content on the left edge, above the centre row
    out = shifted_right(f, 12)  # the band joins it
    assert border_free_scale(out) < 0.6  # the plain rule: the content counts as border, 52 px deep
    assert BorderFreeAccumulator().add(out, f, translation(12)) == pytest.approx(1 - 2 * 12 / W)
    g = bright()
    g[50:100, 0:40] = 0  # across the centre row: the band may lose the margin beside it, no more
    s = BorderFreeAccumulator().add(shifted_right(g, 12), g, translation(12))
    assert 1 - 2 * 12 / W <= s <= 1 - 2 * (12 - DEFAULT_MARGIN) / W + 1e-12


def test_no_homography_falls_back_to_the_plain_rule_and_is_counted():
    f = with_dark_top(bright())
    acc = BorderFreeAccumulator()
    assert acc.add(f, f, None) == border_free_scale(f) < 1.0
    assert acc.add(f) == border_free_scale(f)  # no input at all: the plain rule, not counted
    assert acc.frames_unaligned == 1
    d = acc.as_dict()
    assert d["border_frames_unaligned"] == 1 and d["border_margin_px"] == DEFAULT_MARGIN


def fr1_rpy_frame() -> np.ndarray:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"{SHARED_DATA} not present")
    img = cv2.imread(str(SHARED_DATA / "tum_fr1_rpy" / FR1_RPY_DARK))
    assert img is not None, FR1_RPY_DARK
    return img


def test_real_frame_with_a_black_monitor_at_its_edge():
    img = fr1_rpy_frame()
    assert border_free_scale(img) < 0.1  # the plain rule on the input itself
    s, acc, _ = scored(img, img)
    assert s == 1.0 and acc.frames_unaligned == 0
    out = shifted_right(img, 16)
    s, _, h = scored(img, out)
    assert h is not None
    assert s == pytest.approx(1 - 2 * 16 / img.shape[1])

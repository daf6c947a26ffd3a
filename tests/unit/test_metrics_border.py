"""Border-free cropping (quick_stream.quality.metrics_border) on synthetic frames with known borders."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from quick_stream.quality.metrics_border import (BorderFreeAccumulator, border_free_cropping, border_free_scale,
                                         scale_from_mask, sequence_border_free_scale, uncovered_mask)

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

"""The least jitter a border-free stabilizer can reach at a cropping (docs/method.md 6.3, (18))."""
from __future__ import annotations

import math

import numpy as np
import pytest

from quick_stream.quality.jitter_bound import border_free_jitter_bound, turn_room_deg
from quick_stream.quality.metrics_jitter import trajectory_jitter

W, H, SIGMA = 640, 480, 5.0


def _hand_held(n: int = 120, seed: int = 3) -> np.ndarray:
    """Per-pair motions (tx px, ty px, angle deg): a slow sweep plus a 3-6 Hz shake of a few px."""
    rng = np.random.default_rng(seed)
    t = np.arange(n)
    sweep = np.stack([40 * np.sin(2 * np.pi * 0.3 * t / 30), 25 * np.sin(2 * np.pi * 0.2 * t / 30 + 1),
                      2 * np.sin(2 * np.pi * 0.25 * t / 30)], axis=1)
    shake = rng.normal(0, [6.0, 5.0, 1.5], size=(n, 3))
    traj = sweep + np.cumsum(shake, axis=0) * 0.3 + shake
    return np.diff(traj, axis=0)


def test_at_cropping_1_the_bound_is_the_input_jitter() -> None:
    m = _hand_held()
    assert border_free_jitter_bound(m, 1.0, W, H, SIGMA) == pytest.approx(trajectory_jitter(m, SIGMA), rel=1e-9)


def test_no_shifted_and_turned_window_inside_the_frame_beats_the_bound() -> None:
    m = _hand_held()
    cropping = 0.9
    bound = border_free_jitter_bound(m, cropping, W, H, SIGMA)
    rooms = np.array([(W - 1) / 2 * (1 - cropping), (H - 1) / 2 * (1 - cropping), turn_room_deg(W, H, cropping)])
    rng = np.random.default_rng(0)
    traj = np.vstack([np.zeros((1, 3)), np.cumsum(m, axis=0)])
    for trial in range(40):
        # feasible windows: smoothed targets, clipped to the room (the good ones), and random ones
        if trial % 2:
            c = rng.uniform(-1, 1, size=traj.shape) * rooms
        else:
            k = np.ones(1 + 2 * (trial % 7)) / (1 + 2 * (trial % 7))
            hp = traj - np.stack([np.convolve(traj[:, j], k, mode="same") for j in range(3)], axis=1)
            c = np.clip(hp * rng.uniform(0.5, 1.5), -rooms, rooms)
        out = np.diff(traj - c, axis=0)
        px, deg = trajectory_jitter(out, SIGMA)
        assert px / cropping >= bound[0] - 1e-9 and deg >= bound[1] - 1e-9


def test_the_bound_falls_as_the_crop_grows_and_a_shake_inside_the_room_leaves_nothing() -> None:
    m = _hand_held()
    bounds = [border_free_jitter_bound(m, c, W, H, SIGMA) for c in (1.0, 0.95, 0.9, 0.85)]
    assert all(a[0] > b[0] for a, b in zip(bounds, bounds[1:]))
    assert bounds[0][1] > bounds[1][1] and all(a[1] >= b[1] for a, b in zip(bounds, bounds[1:]))
    # a pure 4 Hz shake of +-3 px / 0.3 deg fits a 5 % crop's room whole: the bound is (nearly) 0
    t = np.arange(91)
    traj = np.stack([3 * np.sin(2 * np.pi * 4 * t / 30), 3 * np.cos(2 * np.pi * 4 * t / 30),
                     0.3 * np.sin(2 * np.pi * 4 * t / 30)], axis=1)
    px, deg = border_free_jitter_bound(np.diff(traj, axis=0), 0.95, W, H, SIGMA)
    assert px < 1e-3 and deg < 1e-4


def test_turn_room_of_a_square_window_matches_its_closed_form() -> None:
    side = 501  # half-size 250 px
    for c in (0.75, 0.8, 0.95):
        # corners of the turned window: c 250 (cos t + sin t) <= 250
        expected = math.degrees(math.asin(1 / (c * math.sqrt(2)))) - 45
        assert turn_room_deg(side, side, c) == pytest.approx(expected, abs=1e-6)
    assert turn_room_deg(W, H, 1.0) == pytest.approx(0.0, abs=1e-6)
    # a square window of 0.75: turns up to ~25.5 deg fit, those around 45 do not, 90 fits again: the first
    assert turn_room_deg(side, side, 0.75) < 30 and turn_room_deg(side, side, 0.7) == 90.0
    with pytest.raises(ValueError, match="cropping"):
        turn_room_deg(W, H, 0.0)

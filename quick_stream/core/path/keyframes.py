"""Keyframe selection (docs/method.md 4.1).

A keyframe closes a segment every ``interval`` frames, or earlier where the
direction of the camera path's velocity turns by more than ``turn_deg``: the
mean camera velocity over the last ``window`` frames is compared with the mean
over the segment's first ``window`` frames, both expressed in the segment's
first camera frame. Directions of a camera that barely moves are noise, so a
turn only counts when both mean speeds exceed ``min_speed_m`` per frame. The
detector is causal: it decides when each motion arrives.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class KeyframeParams:
    interval: int = 30  # frames per segment at most
    min_interval: int = 10  # no turn keyframe before this many frames into a segment
    turn_deg: float = 60.0  # velocity-direction change that forces a keyframe
    window: int = 5  # frames averaged for a velocity direction
    min_speed_m: float = 0.002  # mean speed (m per frame) below which direction is undefined

    def validate(self) -> None:
        if self.interval < 2:
            raise ValueError(f"keyframe interval must be >= 2, got {self.interval}")
        if self.window < 1 or self.min_interval < 1:
            raise ValueError("keyframe window and min_interval must be >= 1")


class KeyframeDetector:
    """Decides, motion by motion, whether the frame just reached is a keyframe."""

    def __init__(self, params: KeyframeParams | None = None) -> None:
        self.params = params or KeyframeParams()
        self.params.validate()
        self.reset()

    def reset(self) -> None:
        """Start a new segment at the current frame."""
        self._R = np.eye(3)  # rotation of the current camera relative to the segment's first
        self._vel: list[np.ndarray] = []  # camera velocities in the segment's first frame

    def push(self, motion: np.ndarray) -> str:
        """Add the camera motion to the next frame; returns "interval", "turn" or "" (no keyframe)."""
        p = self.params
        self._vel.append(self._R @ motion[:3, 3])
        self._R = self._R @ motion[:3, :3]
        n = len(self._vel)
        if n >= p.interval:
            return "interval"
        if n >= max(p.min_interval, 2 * p.window):
            first = np.mean(self._vel[: p.window], axis=0)
            last = np.mean(self._vel[-p.window:], axis=0)
            a, b = np.linalg.norm(first), np.linalg.norm(last)
            if a > p.min_speed_m and b > p.min_speed_m:
                cos = float(first @ last) / (a * b)
                if cos < np.cos(np.radians(p.turn_deg)):
                    return "turn"
        return ""

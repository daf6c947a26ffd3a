"""The constant-velocity bridge: a few motions nothing could be fitted to, taken as the last one known
(docs/method.md 2.4).

A flow with nothing in it (a frame blurred or dark beyond any texture, a frame skipped upstream, a
flow the estimator could not even fit a rotation to) does not stop the path at once: for up to
``max_frames`` frames the camera is taken to keep its recent velocity, the mean twist of the last
``RECENT`` motions that were known (hand-held shake reverses within a few frames, so the last motion
alone is a worse guess than their mean), and the motion says so (``kind`` "bridge", its covariance
the mean's plus the recent motions' own spread per bridged frame: a bridge is a guess). Only a
longer hole, or one with no known motion before it, goes to the planner as an invalid motion, and
the path restarts.
"""
from __future__ import annotations

from collections import deque
from dataclasses import replace

import numpy as np
import scipy.linalg

from ..lie import get_group
from ..lie.expm import expm
from . import UNKNOWN_VARIANCE, MotionEstimate

RECENT = 5  # the bridge's velocity: the mean twist of this many last known motions


class MotionBridge:
    """Turns invalid motions into constant-velocity bridges while the hole is short (one stream):
    at most ``max_frames`` consecutive frame steps (0: no bridge, every invalid motion restarts)."""

    def __init__(self, max_frames: int = 3) -> None:
        if max_frames < 0:
            raise ValueError(f"bridge max_frames must be >= 0, got {max_frames}")
        self.max_frames = max_frames
        self._recent: deque[MotionEstimate] = deque(maxlen=RECENT)  # the last motions known (fit or rotation)
        self._bridged = 0  # frame steps bridged since then
        self.bridges = 0  # motions bridged (frame steps), counted over the stream

    def reset(self) -> None:
        """A break in the stream (a new numbering, a new stream): nothing is known before it."""
        self._recent.clear()
        self._bridged = 0

    def take(self, m: MotionEstimate, steps: int = 1) -> MotionEstimate:
        """``m`` as the path is to take it: a known motion as it is (remembered); an invalid one over
        ``steps`` frame steps as the last known motion repeated ``steps`` times while the bridge
        reaches (kind "bridge", the reason saying why), else as it is (the path restarts)."""
        if m.valid:
            if m.kind in ("fit", "rotation"):
                self._recent.append(m)
                self._bridged = 0
            return m
        if not self._recent or self._bridged + steps > self.max_frames or steps < 1:
            self.reset()
            return m
        self._bridged += steps
        self.bridges += steps
        g = get_group(m.group)
        recent = list(self._recent)
        twist = np.mean([r.twist for r in recent], axis=0) * steps
        cov = bridge_covariance(recent, steps, self._bridged)
        return replace(m, matrix=g.exp(twist), twist=twist, zeta_bar=g.log(g.inverse(g.exp(twist))), valid=True,
                       kind="bridge", covariance=cov, fallback="",
                       reason=f"{m.reason}; constant-velocity bridge ({self._bridged} of at most "
                              f"{self.max_frames} frames)")


def bridge_covariance(recent: list[MotionEstimate], steps: int, bridged: int) -> np.ndarray:
    """The covariance of a bridge over ``steps`` frames, ``bridged`` frames after the ``recent`` known motions
    (docs/method.md 2.4): their mean's covariance times steps^2 plus, per bridged frame, the recent motions'
    own spread about their mean per component (how far the next motion may be from it; at least the
    mean's size, as for one motion)."""
    n = len(recent[0].twist)
    covs = [r.covariance if r.covariance is not None else np.eye(n) * UNKNOWN_VARIANCE for r in recent]
    base = np.mean(covs, axis=0) / len(recent)
    tw = np.array([r.twist for r in recent])
    spread = np.maximum(np.var(tw, axis=0), np.mean(tw, axis=0) ** 2) if len(recent) > 1 else tw[0] ** 2
    return base * steps ** 2 + np.diag(np.maximum(spread, 1e-8)) * float(bridged) * steps


def split_over(m: MotionEstimate, over: tuple[int, ...]) -> list[MotionEstimate]:
    """``m`` (frame ``seq`` to ``seq_next``) cut at the frames ``over`` that the flow stage reached over
    (docs/method.md 2.4): at constant velocity, the part over a fraction a of its frame steps m^a =
    expm(a logm(m)) with covariance a Sigma, so the parts compose to ``m`` and their covariances sum to its
    own; an invalid ``m`` into invalid parts (each frame then restarts the path, as its own flow would
    have). Without ``over``, [m]."""
    if not over:
        return [m]
    cuts = [m.seq, *over, m.seq_next]
    steps = m.seq_next - m.seq
    g = get_group(m.group)
    generator = np.real(scipy.linalg.logm(m.matrix)) if m.valid else None  # m = expm(generator): the
    # one-parameter subgroup through m, along which the parts compose to m exactly
    parts = []
    for a, b in zip(cuts, cuts[1:]):
        why = (f"{m.reason}; " if m.reason else "") + (
            f"split at constant velocity across frame{'s' * (len(over) > 1)} {', '.join(map(str, over))} "
            f"(reached over: their own flow starved)")
        if not m.valid:
            parts.append(replace(m, seq=a, seq_next=b, reason=why))
            continue
        frac = (b - a) / steps
        mat = g.project(expm(generator * frac))
        parts.append(replace(m, seq=a, seq_next=b, matrix=mat, twist=g.log(mat), zeta_bar=g.log(g.inverse(mat)),
                             covariance=None if m.covariance is None else m.covariance * frac, reason=why))
    return parts

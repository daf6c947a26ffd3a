"""Lie groups of QuICK camera motion: SE(3), SIM(3), SA(3), GA(3) (docs/method.md sections 2-4).

All groups share the interface of :class:`~quick_stream.core.lie.base.LieGroup`: 4x4 affine matrices,
twists ``xi = [t(3), u(n-3)]`` (translation first), the paper's decoupled exponential chart.

    >>> from quick_stream.core.lie import get_group
    >>> G = get_group("se3")
    >>> g = G.exp([0.1, 0, 0, 0, 0, 0.2])
"""
from __future__ import annotations

from . import so3
from .affine import GA3, SA3
from .base import LieGroup
from .rigid import SE3, SIM3

__all__ = ["so3", "LieGroup", "SE3", "SIM3", "SA3", "GA3", "GROUPS", "get_group"]

GROUPS: dict[str, LieGroup] = {G.name: G for G in (SE3(), SIM3(), SA3(), GA3())}


def get_group(name: str) -> LieGroup:
    """The group instance for ``name`` ("se3", "sim3", "sa3", "ga3"; case-insensitive)."""
    try:
        return GROUPS[str(name).lower()]
    except KeyError:
        raise ValueError(
            f"unknown Lie group {name!r}; valid names: {', '.join(GROUPS)}"
        ) from None

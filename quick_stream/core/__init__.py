"""The stabilizer itself: frames, Lie groups, scene flow, motion, path, rendering and the stages
that chain them (in-process: :class:`~quick_stream.core.stabilizer.Stabilizer`).

Pure computation: nothing here opens a zenoh session, reads or writes a file, or parses a command
line (tests/unit/test_layers.py checks that core imports no other layer, nor zenoh, mcap or argparse).

``from quick_stream.core import Stabilizer, StabilizerParams`` gives the stabilizer with the product's
defaults (``quick-stream stabilize`` with no flags); both load on first use, so importing one part of
core does not load the whole stabilizer.
"""
from __future__ import annotations

from typing import Any

__all__ = ["Stabilizer", "StabilizerParams"]


def __getattr__(name: str) -> Any:
    if name == "Stabilizer":
        from .stabilizer import Stabilizer
        return Stabilizer
    if name == "StabilizerParams":
        from .params import StabilizerParams
        return StabilizerParams
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

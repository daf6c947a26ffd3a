"""A correction's place in its planner release (:class:`Tag`) and the numbering the motion stage gives
its releases (:class:`ReleaseNumbering`): what travels with each correction to the render stage
(docs/wire-format.md). Apart from :mod:`quick_stream.core.release` (the render side), so the motion
stage does not load the renderer.
"""
from __future__ import annotations

from typing import NamedTuple

from .path.planner import Correction


class Tag(NamedTuple):
    """A correction's place in its planner release: the release, its index in it, the release's size
    and the newest frame the motion stage had taken when it released (``closed_by``: the frame whose
    arrival closed the release, what the latency stamps measure from; None: the end of the stream
    closed it, or a sender that does not say)."""

    release: int
    index: int
    size: int
    closed_by: int | None = None


class ReleaseNumbering:
    """Releases tagged as the motion service publishes them: each list of corrections one release,
    numbered from 0 for the service's life (not reset at the end of a stream)."""

    def __init__(self) -> None:
        self.release = 0
        self.sent = 0  # corrections tagged

    def number(self, released: list[list[Correction]], closed_by: int | None = None) -> list[tuple[Correction, Tag]]:
        """Tag each list of corrections as one release; ``closed_by``: the newest frame taken when they were released."""
        out: list[tuple[Correction, Tag]] = []
        for b in released:
            out += [(c, Tag(self.release, i, len(b), closed_by)) for i, c in enumerate(b)]
            self.sent += len(b)
            self.release += 1
        return out

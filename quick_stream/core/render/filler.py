"""One frame rendered with its border filled from its neighbours (docs/method.md 5.4), over a stream.

:class:`BorderFiller` keeps the last frames rendered (the fill's past sources), estimates before
rendering the zoom a frame needs so that the fill covers what its mesh leaves (:meth:`BorderFiller.need`)
and renders a frame at its zoom, filling the band its mesh leaves from the release's frames and the
past ones and zooming in on what no neighbour saw (:meth:`BorderFiller.render`). It counts the
frames filled (``filled``), zoomed beyond their plan (``fill_raised``) and left with output pixels
no source reached (``bordered``, 0 expected). The pixel work is :mod:`.fill`'s.
"""
from __future__ import annotations

import numpy as np

from ..frame import RGBDFrame
from ..path.planner import Correction
from .fill import FillSource, covered_zoom, fill_border, ordered_sources, raise_for
from .framing import FramingParams
from .mapping import map_samples, render, render_covered, rezoom_samples
from .warp import MeshWarp


def source_of(c: Correction, f: RGBDFrame) -> FillSource:
    """What the border fill can read of frame ``f`` with correction ``c`` (which carries its camera pose)."""
    return FillSource(c.seq, c.chain, c.camera, f.color, f.intrinsics.K)


class BorderFiller:
    """The border fill over a stream (module docstring); with ``framing.fill_frames`` 0 it only renders."""

    def __init__(self, framing: FramingParams) -> None:
        self.framing = framing
        self.past: list[FillSource] = []  # the last fill_frames rendered frames the border fill can read
        self.filled = 0  # frames whose border was filled from neighbours
        self.fill_raised = 0  # frames zoomed in beyond their plan because fill left a border
        self.bordered = 0  # frames rendered with output pixels no source reached (a black border): 0 expected

    def sources(self, c: Correction, ahead: list[FillSource]) -> list[FillSource]:
        """The frames the fill reads for ``c``'s frame, nearest first: ``ahead`` (the release's) and the past."""
        if c.camera is None:
            return []
        return ordered_sources(c.seq, c.chain, self.past + ahead, self.framing.fill_frames)

    def need(self, c: Correction, f: RGBDFrame, mesh: MeshWarp, zoom: float, samples: np.ndarray,
             ahead: list[FillSource]) -> float:
        """The zoom frame ``f`` needs so that the fill covers what its mesh leaves at ``zoom``, estimated
        before rendering on the map ``samples`` at that zoom (docs/method.md 5.4)."""
        return covered_zoom(mesh, f.depth, f.intrinsics.K, zoom, None if c.camera is None else c.camera @ c.matrix,
                            self.sources(c, ahead), samples=samples)

    def render(self, c: Correction, f: RGBDFrame, mesh: MeshWarp, zoom: float, samples: np.ndarray | None,
               ahead: list[FillSource]) -> tuple[np.ndarray, float]:
        """Frame ``f`` at ``zoom`` (``samples``: its map samples at that zoom, if made), its border filled
        from its neighbours when the correction carries a camera pose; what the fill leaves uncovered
        is zoomed away (``auto`` framing, up to ``fill_zoom_max``). Returns (image, zoom)."""
        reach = self.framing.fill_frames
        if not reach:
            return render(f.color, mesh, zoom), zoom
        planned, sources = zoom, self.sources(c, ahead)
        virtual = c.camera @ c.matrix if c.camera is not None else None
        samples, filled = map_samples(mesh, zoom) if samples is None else samples, False
        for _ in range(3):
            image, uncovered, depth = render_covered(f.color, f.depth, mesh, zoom, samples=samples)
            if depth is None:
                break
            if sources:
                uncovered = fill_border(image, uncovered, depth, f.intrinsics.K, zoom, virtual, sources)
                filled = True
            if not uncovered.any() or self.framing.mode != "auto" or zoom >= self.framing.fill_zoom_max:
                break
            raised = min(raise_for(uncovered, zoom) * (1.0 + 1e-6), self.framing.fill_zoom_max)
            samples = rezoom_samples(samples, mesh.width, mesh.height, zoom, raised)
            zoom = raised
        self.filled += filled
        self.fill_raised += zoom > planned
        self.bordered += depth is not None and bool(uncovered.any())
        if c.camera is not None:
            self.past = (self.past + [source_of(c, f)])[-reach:]
        return image, zoom

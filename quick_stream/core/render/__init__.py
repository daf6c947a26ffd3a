"""Rendering stage: content-preserving warp, one-remap rendering and framing (docs/method.md section 5).

* :mod:`.warp`: :func:`solve_warp` fits a 2x2-cell mesh (Liu et al. 2009) moving each
  valid-depth pixel to where the stabilised (virtual) camera sees its 3D point;
* :mod:`.mapping`: :func:`render` warps an image with one ``cv2.remap`` built from the
  per-cell inverse bilinear maps (:mod:`.inverse_bilinear`), optionally zoomed about the image
  centre; :mod:`.uncovered`: the output pixels it leaves without a source;
* :mod:`.fill`: the border fill from neighbouring frames;
* :mod:`.framing`: ``black`` / ``crop`` / ``auto`` framing, :func:`border_free_zoom`
  and :class:`ZoomSmoother`.

Typical use per frame: ``mesh = solve_warp(frame, T)`` with ``T`` the 4x4 map from
real-camera to stabilised-camera coordinates, then ``render(frame.color, mesh, zoom)``.
"""
from .framing import Framing, FramingParams, ZoomSmoother, border_free_zoom, segment_zooms
from .inverse_bilinear import map_points
from .mapping import coverage, inverse_map, remap, render, valid_mask
from .warp import MeshWarp, WarpParams, control_pixels, solve_mesh, solve_warp

__all__ = [
    "Framing", "FramingParams", "MeshWarp", "WarpParams", "ZoomSmoother", "border_free_zoom",
    "control_pixels", "coverage", "inverse_map", "map_points", "remap",
    "render", "segment_zooms", "solve_mesh", "solve_warp", "valid_mask",
]

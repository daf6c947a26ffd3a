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
from __future__ import annotations

import importlib
from typing import Any

_WHERE = {"Framing": "framing", "FramingParams": "framing", "ZoomSmoother": "framing", "border_free_zoom": "framing",
          "segment_zooms": "framing", "map_points": "inverse_bilinear", "coverage": "mapping",
          "inverse_map": "mapping", "remap": "mapping", "render": "mapping", "valid_mask": "mapping",
          "MeshWarp": "warp", "WarpParams": "warp", "control_pixels": "warp", "solve_mesh": "warp",
          "solve_warp": "warp"}
__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    """The package's names load their module on first use: a stage that needs only the warp's
    parameters or the mesh model (the motion stage's crop budget) does not load the renderer."""
    if name in _WHERE:
        return getattr(importlib.import_module(f".{_WHERE[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

"""Framing of the stabilised frames: black borders, a fixed crop or an automatic crop (docs/method.md 5.3).

* ``black``: zoom 1, out-of-frame areas are black;
* ``crop``: a fixed zoom (``crop_zoom``) about the image centre for every frame;
* ``auto``: per frame the smallest zoom that leaves no black border
  (:func:`border_free_zoom`), smoothed over the segment by :class:`ZoomSmoother`.

:func:`border_free_zoom` is exact for the renderer of :mod:`.mapping`: the output
pixels with a source are exactly the polygon of the mesh's outer output vertices
(the grid's outer edges are the source border), so the smallest zoom is where the
zoomed output rectangle first touches that polygon, a closed form per polygon edge.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Callable, Iterator, Sequence

import numpy as np

from .warp import MeshWarp


class Framing(str, Enum):
    """How out-of-frame areas are handled."""

    BLACK = "black"
    CROP = "crop"
    AUTO = "auto"

    @classmethod
    def parse(cls, value: "str | Framing") -> "Framing":
        """The mode named ``value``; ValueError naming the choices otherwise."""
        try:
            return cls(value)
        except ValueError:
            raise ValueError(
                f"framing must be one of {[m.value for m in cls]}, got {value!r}"
            ) from None


ZOOM_LIMIT = 100.0  # no zoom setting goes beyond (a 100x zoom shows 1 % of the frame's width); the wire's range


@dataclass
class FramingParams:
    """Parameters of the framing modes (each one documented where it acts)."""

    mode: str = "black"  # black | crop | auto
    crop_zoom: float = 1.15  # crop: fixed zoom about the image centre
    max_zoom: float = 1.6  # auto: never zoom more (a frame needing more keeps some black border)
    fall_per_frame: float = 0.004  # auto: largest zoom decrease per frame (0.2 takes 50 frames)
    rise_per_frame: float = 0.01  # auto: largest anticipated zoom increase per frame within a segment
    fill_frames: int = 30  # border fill (docs/method.md 5.4): neighbours searched on each side; 0 = no fill
    fill_zoom_max: float = 1.6  # border fill: what fill leaves uncovered is zoomed away, up to this zoom
    fill_lift_rate: float = 0.002  # border fill: largest change per frame of that extra zoom (rises start early)
    fill_lookahead: int = 8  # border fill: frames ahead a rise of that extra zoom is started from (docs/method.md (14a))

    def validate(self) -> None:
        Framing.parse(self.mode)
        if not (np.isfinite(self.crop_zoom) and 1.0 <= self.crop_zoom <= ZOOM_LIMIT):
            raise ValueError(f"framing crop_zoom must be in [1, {ZOOM_LIMIT:g}], got {self.crop_zoom}")
        if not (np.isfinite(self.max_zoom) and 1.0 <= self.max_zoom <= ZOOM_LIMIT):
            raise ValueError(f"framing max_zoom must be in [1, {ZOOM_LIMIT:g}], got {self.max_zoom}")
        if not (self.fall_per_frame > 0 and self.rise_per_frame > 0):
            raise ValueError("framing fall_per_frame and rise_per_frame must be > 0")
        if not (isinstance(self.fill_frames, int) and self.fill_frames >= 0):
            raise ValueError(f"framing fill_frames must be an integer >= 0, got {self.fill_frames!r}")
        if not (np.isfinite(self.fill_zoom_max) and 1.0 <= self.fill_zoom_max <= ZOOM_LIMIT):
            raise ValueError(f"framing fill_zoom_max must be in [1, {ZOOM_LIMIT:g}], got {self.fill_zoom_max}")
        if not self.fill_lift_rate > 0:
            raise ValueError(f"framing fill_lift_rate must be > 0, got {self.fill_lift_rate}")
        if not (isinstance(self.fill_lookahead, int) and self.fill_lookahead >= 0):
            raise ValueError(f"framing fill_lookahead must be an integer >= 0, got {self.fill_lookahead!r}")


def outline(dst: np.ndarray) -> np.ndarray:
    """Outer output vertices of mesh vertex arrays ``dst`` (..., gy+1, gx+1, 2) in cyclic order
    (top, right, bottom, left): (..., M, 2)."""
    return np.concatenate((dst[..., 0, :-1, :], dst[..., :-1, -1, :], dst[..., -1, :0:-1, :],
                           dst[..., :0:-1, 0, :]), axis=-2)


def _inside_polygon(poly: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Point ``q`` strictly inside each closed polygon ``poly`` (..., M, 2) (even-odd rule): (...,) bool."""
    a = poly
    b = np.roll(poly, -1, axis=-2)
    cross = (a[..., 1] > q[1]) != (b[..., 1] > q[1])
    with np.errstate(divide="ignore", invalid="ignore"):
        xi = a[..., 0] + (q[1] - a[..., 1]) * (b[..., 0] - a[..., 0]) / (b[..., 1] - a[..., 1])
    return np.count_nonzero(cross & (q[0] < xi), axis=-1) % 2 == 1


def edge_extents(dst: np.ndarray, width: int, height: int) -> np.ndarray:
    """Per outer mesh edge, the half-size t of the largest centred output rectangle that edge allows.

    With c the centre and a = (W-1)/2, b = (H-1)/2, the output at zoom s shows the
    rectangle R(1/s) = {q : max(|q_x - c_x| / a, |q_y - c_y| / b) <= 1/s} of the
    unzoomed output (docs/method.md (12)). Edge e of the covered polygon (the mesh's
    outer output vertices) allows R(t) up to t_e, the minimum over the edge of that
    weighted max norm: a convex piecewise-linear function of the edge parameter,
    attained at an end point or where |x|/a = |y|/b. ``dst``: (..., gy+1, gx+1, 2) mesh
    vertices; returns (..., M) with M outer edges, 0 for every edge of a polygon that
    does not contain the centre. The border-free zoom is 1 / min_e t_e.
    """
    a, b = (width - 1) / 2.0, (height - 1) / 2.0
    poly = outline(np.asarray(dst, dtype=np.float64))
    p = (poly - (a, b)) / (a, b)  # centred, normalised: R(t) is the square max(|x|, |y|) <= t
    d = np.roll(p, -1, axis=-2) - p
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = np.stack([
            np.zeros(p.shape[:-1]), np.ones(p.shape[:-1]),
            (p[..., 1] - p[..., 0]) / (d[..., 0] - d[..., 1]),  # x = y
            -(p[..., 0] + p[..., 1]) / (d[..., 0] + d[..., 1]),  # x = -y
        ], axis=-1)
    lam = np.clip(np.nan_to_num(lam, nan=0.0, posinf=0.0, neginf=0.0), 0.0, 1.0)
    x = p[..., :1] + lam * d[..., :1]
    y = p[..., 1:] + lam * d[..., 1:]
    t = np.min(np.maximum(np.abs(x), np.abs(y)), axis=-1)
    inside = _inside_polygon(poly, np.array([a, b]))
    return np.where(inside[..., None], t, 0.0)


def border_free_zoom(mesh: MeshWarp, width: int | None = None, height: int | None = None) -> float:
    """Smallest zoom s >= 1 about the image centre whose output has a source pixel everywhere.

    1 / min over the outer edges of :func:`edge_extents` (docs/method.md (12)); inf when the
    centre itself is uncovered. ``width``/``height`` default to the mesh's (the output has
    the source's size).
    """
    w = mesh.width if width is None else int(width)
    h = mesh.height if height is None else int(height)
    if (w, h) != (mesh.width, mesh.height):
        raise ValueError(f"border_free_zoom: output {w}x{h} differs from the mesh's {mesh.width}x{mesh.height}")
    t = float(np.min(edge_extents(mesh.dst, w, h)))
    if t <= 0:
        return float("inf")
    s = 1.0 / t
    return 1.0 if s <= 1.0 + 1e-9 else s  # round-off of an identity mesh is not a zoom


class ZoomSmoother:
    """Per-frame zooms for ``auto`` framing, one segment at a time.

    Given a whole segment's required zooms (known before it is rendered), returns
    zooms that are never below the requirement (capped at ``max_zoom``), fall by
    at most ``fall_per_frame`` per frame, and rise by at most ``rise_per_frame``
    within the segment by starting early (a backward pass). The last zoom is kept,
    so the next segment continues from it; only a requirement at a segment's very
    first frame that exceeds the last zoom forces a jump (it cannot be anticipated
    without looking into the next segment).
    """

    def __init__(self, params: FramingParams | None = None, last: float | None = None) -> None:
        self.params = params or FramingParams()
        self.params.validate()
        self.last = last
        self.raised = 0  # planned zooms raised to what the rendered mesh (or the border fill) needed
        self.lift = 0.0  # cover: the last frame's raise above its planned zoom

    def follow(self, planned: Sequence[float], required: Sequence[float]) -> np.ndarray:
        """Zooms planned with the path, each raised to its frame's ``required`` zoom if the plan
        (made on the planner's model of the frame) fell short; capped at ``max_zoom``."""
        z = np.asarray(planned, dtype=np.float64).ravel()
        req = np.clip(np.nan_to_num(np.asarray(required, dtype=np.float64).ravel(), nan=np.inf), 1.0,
                      self.params.max_zoom)
        short = req > z + 1e-9
        self.raised += int(np.count_nonzero(short))
        z = np.minimum(np.where(short, req, z), max(self.params.max_zoom, float(z.max(initial=1.0))))
        if len(z):
            self.last = float(z[-1])
        return z

    def cover(self, planned: Sequence[float], required: Sequence[float]) -> np.ndarray:
        """Zooms planned with the path, raised where a frame ``required`` more (docs/method.md (14a)):
        :meth:`cover_frames` of a segment whose requirements are all known."""
        req = np.asarray(required, dtype=np.float64).ravel()
        return np.fromiter(self.cover_frames(planned, lambda j: float(req[j])), dtype=np.float64,
                           count=len(req))

    def cover_frames(self, planned: Sequence[float], required: Callable[[int], float]) -> Iterator[float]:
        """Zooms planned with the path, raised where a frame requires more (docs/method.md (14a)), one
        frame at a time: the raise (zoom above the plan) changes by at most ``fill_lift_rate`` per
        frame, rising early over the ``fill_lookahead`` frames ahead within the segment and falling
        slowly, continuing from the last segment's; zooms capped at ``fill_zoom_max``.

        ``required(j)``: frame j's required zoom, asked once per frame, in order, and only when a zoom
        needs it: frame i's zoom is yielded once frames up to i + ``fill_lookahead`` are known, so a
        renderer can show it before estimating the rest of the segment."""
        p = self.params
        z = np.asarray(planned, dtype=np.float64).ravel()
        top = max(p.fill_zoom_max, float(z.max(initial=1.0)))
        need: list[float] = []  # each known frame's required raise
        for i in range(len(z)):
            last = min(i + p.fill_lookahead, len(z) - 1)
            while len(need) <= last:
                j = len(need)
                r = float(required(j))
                r = top if np.isnan(r) else min(max(r, 1.0), top)  # NaN: no zoom covers it
                need.append(max(r - z[j], 0.0))
            lift = need[last]
            for j in range(last - 1, i - 1, -1):  # rises start early (a backward pass over the frames ahead)
                lift = max(need[j], lift - p.fill_lift_rate)
            lift = max(lift, self.lift - p.fill_lift_rate)  # falls are slow, from the last frame's
            self.lift = lift
            self.raised += int(lift > 1e-9)
            self.last = float(z[i] + lift)
            yield self.last

    def smooth(self, required: Sequence[float]) -> np.ndarray:
        """Zooms for one segment's ``required`` zooms (inf/NaN = no border-free zoom: max_zoom)."""
        p = self.params
        req = np.asarray(required, dtype=np.float64).ravel()
        req = np.clip(np.where(np.isnan(req), np.inf, req), 1.0, p.max_zoom)
        z = req.copy()
        for i in range(len(z) - 2, -1, -1):  # anticipate rises
            z[i] = max(z[i], z[i + 1] - p.rise_per_frame)
        prev = self.last
        for i in range(len(z)):  # limit falls, continuing from the last segment
            if prev is not None:
                z[i] = max(z[i], prev - p.fall_per_frame)
            prev = z[i]
        if len(z):
            self.last = float(z[-1])
        return z

    def reset(self) -> None:
        """Forget the last zoom (start of a new stream)."""
        self.last = None
        self.lift = 0.0


def segment_zooms(meshes: Sequence[MeshWarp], params: FramingParams | None = None,
                  smoother: ZoomSmoother | None = None, planned: Sequence[float | None] | None = None) -> np.ndarray:
    """Per-frame zooms of one segment for the framing mode in ``params``.

    ``auto`` needs the stream's ``smoother`` (one per stream, it carries the last
    zoom across segments); a failed mesh (``ok`` False) is the identity and needs zoom 1.
    ``planned``: zooms planned with the path (docs/method.md (11)); ``auto`` follows them
    when every frame has one (:meth:`ZoomSmoother.follow`).
    """
    p = params or FramingParams()
    p.validate()
    mode = Framing.parse(p.mode)
    n = len(meshes)
    if mode is Framing.BLACK:
        return np.ones(n)
    if mode is Framing.CROP:
        return np.full(n, p.crop_zoom)
    if smoother is None:
        raise ValueError("auto framing needs the stream's ZoomSmoother")
    required = [border_free_zoom(m) if m.ok else 1.0 for m in meshes]
    if planned is not None and len(planned) == n and all(z is not None for z in planned):
        return smoother.follow(planned, required)
    return smoother.smooth(required)


def scale_from_mask(mask: np.ndarray) -> float:
    """Largest centred, aspect-preserving rectangle free of ``mask`` pixels, as a fraction of the frame (1: empty).

    The border fill's zoom (:func:`.fill.raise_for`) and the border-free metric
    (``quality.metrics_border``) both measure an uncovered mask with it."""
    h, w = mask.shape
    ys, xs = np.nonzero(mask)
    if xs.size == 0:
        return 1.0
    # distance from the centre to the pixel's nearer edge, in units of the half-size
    dx = np.maximum(np.abs(xs + 0.5 - w / 2.0) - 0.5, 0.0) * (2.0 / w)
    dy = np.maximum(np.abs(ys + 0.5 - h / 2.0) - 0.5, 0.0) * (2.0 / h)
    return float(np.min(np.maximum(dx, dy)))

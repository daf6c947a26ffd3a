"""Content-preserving warp (Liu et al. 2009) driven by depth: docs/method.md 5.1.

A regular grid of ``gx`` x ``gy`` cells covers the input frame; its vertices sit on
pixel centres, from (0, 0) to (W-1, H-1), so every pixel lies in some cell and the
outer edges of the grid are the source image's border. The unknowns are the
output positions of the (gx+1)(gy+1) vertices (18 for the paper's 2x2 grid).

Control points: valid-depth pixels ``p`` on a regular sub-grid (at most
``max_control_points``, deterministic), their 3D points ``x = K^-1 [p, 1] Z(p)`` and
targets ``p_hat = project(K, T x)`` where ``T`` (4x4 affine) maps real-camera to
virtual-camera coordinates. Points landing behind the virtual camera are dropped.

Energy (docs/method.md (13)), with ``V`` the output vertices::

    E = E_d / N + alpha * E_s
    E_d = sum_p | sum_k w_k(p) V_k - p_hat |^2        (w_k: bilinear weights of p in its input cell)
    E_s = sum_triangles | V1 - V2 - u (V3 - V2) - v R90 (V3 - V2) |^2

``(u, v)`` are the coordinates of V1 in the frame of edge V2->V3 on the *reference*
grid, so E_s = 0 exactly when each triangle is a similar copy of its reference.
Each cell contributes its 4 corner triangles (a corner and its two neighbours).
The reference (``shape_reference``) is by default the input grid moved by the
correction's rotation, K R K^-1: a rotation moves every pixel by that homography
whatever its depth, so following it costs nothing and E_s only holds back what
depth parallax (the correction's translation) would do to the cells; with the
input grid itself as the reference (Liu et al. 2009) the shape term also fights
the rotation's perspective (measured: 2.3 px of residual for a 1.5/2/1 degree
rotation that the mesh can follow to 0.55 px).

Normalisation: the data term is a *mean* over the control points, so ``alpha``
weighs "one control point's squared error" against the shape term and keeps its
meaning whatever the resolution or the number of control points. The paper's
E_d + 0.1 E_s with the data term *summed* over N points is alpha = 0.1 / N here
(about 5e-5 for N = 2000): with full-frame control points the shape term is then
irrelevant, and the mesh shears to fit depth parallax (whole stabilizer on
7scenes: distortion 0.942 against 0.989 at alpha = 0.1; docs/method.md section 5
has the measurements behind the default). All coefficients are dimensionless,
so the 2n x 2n normal matrix is scale-free and its condition number is a
meaningful singularity test.

A failed solve (too few control points, singular system, folded mesh) gives the
identity mesh with ``ok = False`` and a ``reason``, so callers can flag the frame.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..frame import RGBDFrame
from .shape_term import rotation_reference, similarity_normal


@dataclass
class WarpParams:
    """Parameters of :func:`solve_warp` (each one documented where it acts)."""

    grid: tuple[int, int] = (2, 2)  # cells in x and y
    # Weight of the similarity term against the MEAN squared control-point error, docs/method.md (13):
    # alpha = 1 prices a 1 px similarity residual on every corner triangle like a 1 px error on
    # every control point. Independent of the number of control points and of the resolution.
    # The paper's E_d + 0.1 E_s with E_d summed over N points is alpha = 0.1 / N here (~5e-5): the
    # mesh then shears to fit depth parallax (measured: docs/method.md section 5).
    alpha: float = 0.1
    # What the similarity term compares each output triangle with: "rotation" = its input triangle
    # moved by the correction's rotation (the homography K R K^-1, parallax-free, so it costs nothing
    # to follow a camera rotation and only depth parallax is held back); "input" = the input
    # triangle itself (Liu et al. 2009, which also resists the rotation's perspective).
    shape_reference: str = "rotation"
    max_control_points: int = 2000  # valid-depth pixels are subsampled on a regular grid to at most this
    min_control_points: int = 8  # fewer usable control points: identity mesh, ok=False
    min_depth: float = 0.0  # metres; control points need depth > min_depth (0 = invalid)
    min_target_z: float = 1e-3  # metres; points with virtual-camera z below this are dropped
    max_condition: float = 1e10  # normal matrix condition number above this: singular
    # The mesh never shears to fit (docs/method.md (13c)): when a cell's sigma_min / sigma_max falls below
    # this (or below the reference's own, a large rotation's perspective), alpha is raised until it does not.
    min_cell_ratio: float = 0.975
    max_alpha_steps: int = 12  # at most this many raises of alpha, each x2 (alpha up to 4096 x its value)

    def validate(self) -> None:
        gx, gy = self.grid
        if int(gx) != gx or int(gy) != gy or gx < 1 or gy < 1:
            raise ValueError(f"warp grid must be two integers >= 1, got {self.grid}")
        if not (np.isfinite(self.alpha) and self.alpha >= 0):
            raise ValueError(f"warp alpha must be finite and >= 0, got {self.alpha}")
        if self.shape_reference not in ("rotation", "input"):
            raise ValueError(f"warp shape_reference must be 'rotation' or 'input', got {self.shape_reference!r}")
        if self.max_control_points < self.min_control_points or self.min_control_points < 1:
            raise ValueError("warp needs 1 <= min_control_points <= max_control_points")
        if not 0 <= self.min_cell_ratio <= 1 or self.max_alpha_steps < 0:
            raise ValueError(f"warp min_cell_ratio must be in [0, 1] and max_alpha_steps >= 0, got "
                             f"{self.min_cell_ratio}, {self.max_alpha_steps}")


@dataclass
class MeshWarp:
    """Input and output grid vertices of one frame's warp, (gy+1, gx+1, 2) arrays in pixels.

    ``dst`` is where each ``src`` vertex goes in the output image. ``ok`` False
    means the solve failed and ``dst`` is ``src`` (identity); ``reason`` says why.
    ``residual_px`` is the RMS distance between the warped control points and
    their targets; ``n_controls`` how many control points entered the solve.
    """

    width: int
    height: int
    src: np.ndarray
    dst: np.ndarray
    ok: bool = True
    reason: str = ""
    residual_px: float = 0.0
    n_controls: int = 0
    alpha: float = float("nan")  # the shape weight the solve used (raised above WarpParams.alpha: shear held back)

    @property
    def grid(self) -> tuple[int, int]:
        """Cells in x and y."""
        return self.src.shape[1] - 1, self.src.shape[0] - 1

    @classmethod
    def identity(cls, width: int, height: int, grid: tuple[int, int] = (2, 2), reason: str = "",
                 n_controls: int = 0) -> "MeshWarp":
        """The identity mesh; ``ok`` is False when a ``reason`` is given."""
        src = grid_geometry(width, height, int(grid[0]), int(grid[1])).src
        return cls(width, height, src, src.copy(), ok=not reason, reason=reason, n_controls=n_controls)

    def cell_distortion(self) -> np.ndarray:
        """Per output cell (gy, gx): sigma_min / sigma_max of the cell's affine part, 1 = no shear or stretch.

        The affine part is the least-squares affine map of the cell's 4 corners, which
        for a bilinear cell is its mean Jacobian: columns ((p1 - p0) + (p2 - p3)) / 2w and
        ((p3 - p0) + (p2 - p1)) / 2h for corners p0..p3 = 00, 10, 11, 01 and input size w x h.
        """
        s, d = self.src, self.dst
        w = s[0, 1, 0] - s[0, 0, 0]
        h = s[1, 0, 1] - s[0, 0, 1]
        p0, p1, p2, p3 = d[:-1, :-1], d[:-1, 1:], d[1:, 1:], d[1:, :-1]
        J = np.stack(((p1 - p0 + p2 - p3) / (2 * w), (p3 - p0 + p2 - p1) / (2 * h)), axis=-1)
        sv = np.linalg.svd(J, compute_uv=False)
        return sv[..., 1] / sv[..., 0]

    def quads_convex(self) -> bool:
        """True when every output cell is a convex quad with the input's orientation (no fold)."""
        d = self.dst
        # corners of each cell in cyclic order 00, 10, 11, 01 (clockwise on screen, y down)
        cyc = np.stack([d[:-1, :-1], d[:-1, 1:], d[1:, 1:], d[1:, :-1]], axis=2)  # (gy, gx, 4, 2)
        e = np.roll(cyc, -1, axis=2) - cyc
        en = np.roll(e, -1, axis=2)
        cross = e[..., 0] * en[..., 1] - e[..., 1] * en[..., 0]
        return bool(np.all(cross > 1e-9 * self.width * self.height))


@dataclass(frozen=True)
class GridGeometry:
    """Input grid of one (width, height, gx, gy): vertex positions and the similarity term."""

    xs: np.ndarray  # (gx+1,) vertex x positions
    ys: np.ndarray  # (gy+1,) vertex y positions
    src: np.ndarray  # (gy+1, gx+1, 2)
    sim_normal: np.ndarray  # (2n, 2n) S^T S of the similarity residuals S X (X = [x_0..x_n-1, y_0..y_n-1])


@lru_cache(maxsize=16)
def grid_geometry(width: int, height: int, gx: int, gy: int) -> GridGeometry:
    """Vertices on pixel centres spanning [0, W-1] x [0, H-1], and the similarity normal matrix (cached)."""
    xs = np.linspace(0.0, width - 1.0, gx + 1)
    ys = np.linspace(0.0, height - 1.0, gy + 1)
    src = np.stack(np.meshgrid(xs, ys), axis=-1)
    for a in (xs, ys, src):
        a.setflags(write=False)
    sn = similarity_normal(src)
    sn.setflags(write=False)
    return GridGeometry(xs, ys, src, sn)


@lru_cache(maxsize=8)
def _pixel_grid(height: int, width: int, step: int) -> np.ndarray:
    """Flat indices of a regular pixel sub-grid (offset step // 2), read-only and cached."""
    off = step // 2
    idx = (np.arange(off, height, step)[:, None] * width + np.arange(off, width, step)[None, :]).ravel()
    idx.setflags(write=False)
    return idx


def control_pixels(depth: np.ndarray, max_points: int, min_depth: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Valid-depth pixels on the finest regular sub-grid that keeps at most ``max_points``.

    Returns flat pixel indices and their depths. The step starts from an estimate
    of the valid fraction (measured on the coarsest grid that can hold at most
    ``max_points`` pixels) and grows until the count fits: deterministic, no randomness.
    """
    h, w = depth.shape
    flat = depth.ravel()
    s0 = max(1, int(np.ceil(np.sqrt(h * w / max_points))))
    idx0 = _pixel_grid(h, w, s0)
    frac = np.count_nonzero(flat[idx0] > min_depth) / max(idx0.size, 1)
    step = max(1, int(np.sqrt(frac * h * w / max_points)))
    while True:
        idx = _pixel_grid(h, w, step)
        z = flat[idx]
        ok = np.flatnonzero(z > min_depth)  # NaN compares False: invalid
        if ok.size <= max_points:
            return idx[ok], z[ok].astype(np.float64)
        step += 1


@dataclass
class WarpInput:
    """What :func:`solve_warp` needs of a frame before its correction is known: the control
    pixels, their 3D points and the data term's design matrix. A renderer computes it when a
    frame arrives, so the work left when the correction comes is small (same arithmetic)."""

    width: int
    height: int
    pixels: np.ndarray  # (N, 2) control pixels
    points: np.ndarray  # (N, 3) their 3D points, camera coordinates
    B: np.ndarray  # (N, n) bilinear weights of each pixel on the mesh vertices
    BtB: np.ndarray  # (n, n) B^T B / N


def prepare_warp(frame: RGBDFrame, params: WarpParams | None = None) -> WarpInput:
    """The correction-independent part of :func:`solve_warp` for ``frame``."""
    p = params or WarpParams()
    p.validate()
    h, w = frame.depth.shape
    K = frame.intrinsics
    idx, z = control_pixels(frame.depth, p.max_control_points, p.min_depth)
    u = (idx % w).astype(np.float64)
    v = (idx // w).astype(np.float64)
    x = np.empty((idx.size, 3))
    x[:, 0] = (u - K.cx) * (z / K.fx)
    x[:, 1] = (v - K.cy) * (z / K.fy)
    x[:, 2] = z
    pixels = np.column_stack((u, v))
    B, BtB = _design(pixels, w, h, p)
    return WarpInput(w, h, pixels, x, B, BtB)


def solve_warp(frame: RGBDFrame, point_transform: np.ndarray, params: WarpParams | None = None,
               prepared: WarpInput | None = None) -> MeshWarp:
    """Mesh warp moving each valid-depth pixel to where the virtual camera sees its 3D point.

    ``point_transform`` (4x4 affine) maps real-camera coordinates to
    virtual-camera coordinates; the virtual camera has the frame's intrinsics.
    ``prepared`` (from :func:`prepare_warp` with the same params) skips recomputing it.
    With ``shape_reference="rotation"`` the similarity term's reference is the grid
    moved by the correction's rotation (:func:`rotation_reference`), docs/method.md (13).
    """
    p = params or WarpParams()
    p.validate()
    T = np.asarray(point_transform, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"point_transform must be a finite 4x4 matrix, got shape {T.shape}")
    wi = prepared if prepared is not None else prepare_warp(frame, p)
    K = frame.intrinsics
    y = wi.points @ T[:3, :3].T + T[:3, 3]
    front = y[:, 2] > p.min_target_z
    every = bool(np.all(front))
    if not every:
        y = y[front]
    tgt = np.empty((y.shape[0], 2))
    tgt[:, 0] = K.fx * y[:, 0] / y[:, 2] + K.cx
    tgt[:, 1] = K.fy * y[:, 1] / y[:, 2] + K.cy
    ref = None
    if p.shape_reference == "rotation":
        gx, gy = (int(g) for g in p.grid)
        ref = rotation_reference(K, T, grid_geometry(wi.width, wi.height, gx, gy).src)
    if every:
        return _solve(wi.B, wi.BtB, tgt, wi.width, wi.height, p, ref)
    return solve_mesh(wi.pixels[front], tgt, wi.width, wi.height, p, ref)


def bilinear_weights(pixels: np.ndarray, geo: GridGeometry) -> tuple[np.ndarray, np.ndarray]:
    """Vertex indices (N, 4) and bilinear weights (N, 4) of each pixel in its input cell."""
    gx, gy = geo.xs.size - 1, geo.ys.size - 1
    cw = geo.xs[-1] / gx
    ch = geo.ys[-1] / gy
    fx = pixels[:, 0] / cw
    fy = pixels[:, 1] / ch
    i = np.clip(np.floor(fx).astype(np.intp), 0, gx - 1)
    j = np.clip(np.floor(fy).astype(np.intp), 0, gy - 1)
    a = fx - i
    b = fy - j
    k00 = j * (gx + 1) + i
    ks = np.stack([k00, k00 + 1, k00 + gx + 1, k00 + gx + 2], axis=1)
    ws = np.stack([(1 - a) * (1 - b), a * (1 - b), (1 - a) * b, a * b], axis=1)
    return ks, ws


def solve_mesh(pixels: np.ndarray, targets: np.ndarray, width: int, height: int,
               params: WarpParams | None = None, reference: np.ndarray | None = None) -> MeshWarp:
    """Minimise E = E_d / N + alpha E_s (docs/method.md (13)) for control ``pixels`` (N, 2) -> ``targets`` (N, 2).

    ``reference`` (gy+1, gx+1, 2): the vertex positions whose triangles E_s keeps
    the output similar to (None: the input grid). The normal equations are
    accumulated in one matrix product (the data term's x and y blocks share the
    n x n matrix B^T B) and the 2n x 2n system is solved directly. See the module
    docstring for the energy and its normalisation.
    """
    p = params or WarpParams()
    B, BtB = _design(pixels, width, height, p)
    return _solve(B, BtB, targets, width, height, p, reference)


def _design(pixels: np.ndarray, width: int, height: int, p: WarpParams) -> tuple[np.ndarray, np.ndarray]:
    """The data term's design matrix B (N, n) and B^T B / N."""
    gx, gy = (int(g) for g in p.grid)
    geo = grid_geometry(width, height, gx, gy)
    n = (gx + 1) * (gy + 1)
    N = len(pixels)
    B = np.zeros((N, n))
    if N == 0:
        return B, np.zeros((n, n))
    ks, ws = bilinear_weights(pixels, geo)
    np.put_along_axis(B, ks, ws, axis=1)  # the 4 indices of a row are distinct
    return B, (B.T @ B) / N


def _solve(B: np.ndarray, BtB: np.ndarray, targets: np.ndarray, width: int, height: int,
           p: WarpParams, reference: np.ndarray | None = None) -> MeshWarp:
    gx, gy = (int(g) for g in p.grid)
    geo = grid_geometry(width, height, gx, gy)
    n = (gx + 1) * (gy + 1)
    N = len(B)
    if N < p.min_control_points:
        return MeshWarp.identity(width, height, (gx, gy), f"too few control points ({N} < {p.min_control_points})", N)
    D = np.zeros((2 * n, 2 * n))
    D[:n, :n] = BtB
    D[n:, n:] = BtB
    S = geo.sim_normal if reference is None else similarity_normal(reference)
    rhs = np.concatenate((B.T @ targets[:, 0], B.T @ targets[:, 1])) / N
    if not np.all(np.isfinite(D)) or not np.all(np.isfinite(rhs)) or not np.all(np.isfinite(S)):
        return MeshWarp.identity(width, height, (gx, gy), "non-finite control point targets", N)
    floor = p.min_cell_ratio if p.alpha > 0 else 0.0  # alpha = 0 asks for no shape term at all
    if floor > 0 and reference is not None:  # a rotation's own perspective is no shear: the floor allows it
        floor = min(floor, float(MeshWarp(width, height, geo.src, reference).cell_distortion().min()) - 1e-9)
    alpha = p.alpha
    for step in range(p.max_alpha_steps + 1):
        G = D + alpha * S
        cond = np.linalg.cond(G)
        if not cond < p.max_condition:
            return MeshWarp.identity(width, height, (gx, gy), f"singular warp system (condition {cond:.3g})", N)
        X = np.linalg.solve(G, rhs)
        dst = np.stack((X[:n], X[n:]), axis=-1).reshape(gy + 1, gx + 1, 2)
        mesh = MeshWarp(width, height, geo.src, dst, ok=True, n_controls=N, alpha=alpha)
        if floor <= 0 or step == p.max_alpha_steps or float(mesh.cell_distortion().min()) >= floor:
            break
        alpha *= 2.0
    r = np.column_stack((B @ X[:n], B @ X[n:])) - targets
    mesh.residual_px = float(np.sqrt(np.mean(np.einsum("ij,ij->i", r, r))))
    if not mesh.quads_convex():
        return MeshWarp.identity(width, height, (gx, gy), "warped mesh folds (a cell is not a convex quad)", N)
    return mesh

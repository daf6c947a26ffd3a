"""The synthetic source's scene: a furnished room of textured planar quads, and its renderer.

World frame = the OpenCV camera frame of the nominal (unshaken, unpanned) camera:
x right, y down, z forward. The room spans x in [-2.3, 2.3], y in [-1.2, 1.2]
(floor at y = +1.2), z in [0.2, 4.0] (back wall at 4.0); five axis-aligned boxes
(crates on the floor, a floor-to-ceiling pillar, a hanging panel, a floating cube)
stand 1-3.6 m in front of a camera that moves near the origin.

Rendering uses that a textured plane seen by a pinhole camera is a homography of
its texture: each visible quad is one ``cv2.warpPerspective`` (bilinear,
``BORDER_TRANSPARENT``) into the canvas in painter's order (room first, then the
boxes far to near), so edges come out anti-aliased. A second warp, nearest-neighbour
of a 1x1 label image, records which quad owns each pixel: exactly the pixels whose
centre ray ``K^-1 [u, v, 1]`` hits the quad (the back wall owns all pixels at the
start: a ray meeting no other room face meets it). Depth then comes per pixel from
the owner's plane: inverse depth is affine in (u, v), looked up by label and
evaluated with a few multiply-adds, so it agrees with the colour geometry (and with
ray casting) to float precision. Quads reaching behind the camera are clipped.

Textures are multi-octave value noise (plus blobs or stripes) in world units,
generated once per (seed, resolution): each face gets a texel pitch of about one
pixel where it is seen smallest (farthest / most oblique), and its finest detail is
4 texels, so nothing aliases or shimmers and dense optical flow finds structure
at every scale.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

ROOM_LO = np.array([-2.3, -1.2, 0.2])
ROOM_HI = np.array([2.3, 1.2, 4.0])
FEATURE_TEXELS = 4.0  # finest texture wavelength, in texels (1 texel ~ <= 1 px on screen)
MAX_TEX = 2048
Z_NEAR = 0.02  # m; quads reaching closer to the camera plane take the clipped path
ROOM_EXT = 2  # texels of texture continued past a room edge shared with a later-drawn face

# Boxes: name, lo corner, hi corner, (x, y, z) jitter amplitudes (m). y down: hi y=1.2 = on floor.
_BOXES = (
    ("crate_left", (-1.6, 0.45, 2.4), (-0.9, 1.2, 3.0), (0.10, 0.0, 0.10)),
    ("crate_back", (0.2, 0.5, 3.1), (1.0, 1.2, 3.6), (0.10, 0.0, 0.10)),
    ("pillar", (1.3, -1.2, 2.2), (1.6, 1.2, 2.5), (0.10, 0.0, 0.10)),
    ("panel", (-0.8, -0.75, 1.7), (-0.15, -0.25, 1.76), (0.08, 0.08, 0.08)),
    ("cube_near", (0.3, 0.1, 1.05), (0.7, 0.5, 1.45), (0.05, 0.05, 0.03)),
)


@dataclass
class Quad:
    """A textured rectangle p0 + a*es + b*et (a, b in [0, 1]) visible from the +normal side."""

    name: str
    label: int
    p0: np.ndarray
    es: np.ndarray
    et: np.ndarray
    normal: np.ndarray
    shade: float
    ext: tuple[int, int, int, int] = (0, 0, 0, 0)  # texels added before/after s, before/after t
    label_eps: float = 0.0  # m the ownership quad is grown by (hides cracks between room faces)
    texture: np.ndarray | None = None  # (th + ext, tw + ext, 4) uint8 BGRA
    tw: int = 0
    th: int = 0


def _box_quads(name: str, lo: np.ndarray, hi: np.ndarray, first_label: int) -> list[Quad]:
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    ex, ey, ez = np.eye(3)
    dx, dy, dz = hi - lo
    faces = (  # (suffix, p0, es, et, normal, shade)
        ("front", (x0, y0, z0), ex * dx, ey * dy, -ez, 1.0),
        ("back", (x1, y0, z1), -ex * dx, ey * dy, ez, 0.85),
        ("left", (x0, y0, z1), -ez * dz, ey * dy, -ex, 0.78),
        ("right", (x1, y0, z0), ez * dz, ey * dy, ex, 0.72),
        ("top", (x0, y0, z1), ex * dx, -ez * dz, -ey, 0.92),
        ("bottom", (x0, y1, z0), ex * dx, ez * dz, ey, 0.6),
    )
    return [Quad(f"{name}.{s}", first_label + i, np.array(p, float), es, et, n, sh)
            for i, (s, p, es, et, n, sh) in enumerate(faces)]


def _room_quads() -> list[Quad]:
    (x0, y0, z0), (x1, y1, z1) = ROOM_LO, ROOM_HI
    ex, ey, ez = np.eye(3)
    W, H, D = x1 - x0, y1 - y0, z1 - z0
    e = ROOM_EXT
    # Painter's order back, floor, ceiling, left, right: a face's texture continues past the
    # edges it shares with faces drawn after it, so those draw over it with clean seams.
    return [
        Quad("back_wall", 1, np.array([x0, y0, z1]), ex * W, ey * H, -ez, 1.0, (e, e, e, e)),
        Quad("floor", 2, np.array([x0, y1, z1]), ex * W, -ez * D, -ey, 0.82, (e, e, 0, 0)),
        Quad("ceiling", 3, np.array([x0, y0, z0]), ex * W, ez * D, ey, 0.68, (e, e, 0, 0)),
        Quad("left_wall", 4, np.array([x0, y0, z0]), ez * D, ey * H, ex, 0.9),
        Quad("right_wall", 5, np.array([x1, y0, z1]), -ez * D, ey * H, -ex, 0.86),
    ]


def layout(seed: int) -> tuple[list[Quad], list[tuple[np.ndarray, np.ndarray, list[int]]]]:
    """All quads (room first) and the boxes as (lo, hi, quad indices), jittered per seed."""
    rng = np.random.default_rng([seed, 0x5CE4E])
    quads = _room_quads()
    for q in quads:
        q.label_eps = 5e-5
    boxes = []
    for name, lo, hi, jit in _BOXES:
        lo0, hi0 = np.array(lo), np.array(hi)
        size = (hi0 - lo0) * rng.uniform(0.9, 1.1, 3)
        lo = lo0 + rng.uniform(-1, 1, 3) * np.array(jit)
        hi = lo + size
        if hi0[1] >= ROOM_HI[1]:  # floor-standing boxes stay on the floor ...
            lo[1], hi[1] = ROOM_HI[1] - size[1], ROOM_HI[1]
        if lo0[1] <= ROOM_LO[1]:  # ... and the pillar reaches the ceiling
            lo[1] = ROOM_LO[1]
        lo, hi = np.maximum(lo, ROOM_LO), np.minimum(hi, ROOM_HI)
        idx = list(range(len(quads), len(quads) + 6))
        quads += _box_quads(name, lo, hi, len(quads) + 1)
        boxes.append((lo, hi, idx))
    for i, (alo, ahi, _) in enumerate(boxes):  # layout sanity: boxes never interpenetrate
        for blo, bhi, _ in boxes[i + 1:]:
            assert np.any((ahi < blo - 0.05) | (bhi < alo - 0.05)), "boxes overlap"
    return quads, boxes


# -- textures -------------------------------------------------------------------------------

def _noise(rng, shape, length, lam):
    """Cubic value noise with wavelength ``lam`` (m, per axis) over ``length`` (m, per axis)."""
    nx, ny = (max(2, int(np.ceil(L / l)) + 2) for L, l in zip(length, lam))
    lattice = rng.standard_normal((ny, nx)).astype(np.float32)
    return cv2.resize(lattice, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)


def _standardize(a):
    return (a - a.mean()) / (a.std() + 1e-6)


def make_texture(rng, shape, length, pitch, shade) -> np.ndarray:
    """A BGRA texture of ``shape`` (rows, cols) texels covering ``length`` (m) at ``pitch``.

    Luminance: octaves of value noise from 1 m down to FEATURE_TEXELS texels (clamped per
    axis, so oblique faces get coarser detail along their foreshortened axis), plus
    soft-edged blobs or stripes; colour: two random hues mixed by coarse noise.
    """
    lam_min = FEATURE_TEXELS * np.asarray(pitch, float)
    lam0 = min(1.0, max(length))
    lum = np.zeros(shape, np.float32)
    k = 0
    while True:
        lam = np.maximum(lam0 * 0.5 ** k, lam_min)
        lum += (lam.mean() / lam0) ** 0.15 * _standardize(_noise(rng, shape, length, lam))
        k += 1
        if np.all(lam0 * 0.5 ** k < lam_min) or k > 12:
            break
    lum = _standardize(lum)
    kind = rng.integers(3)
    ty, tx = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float32)
    ty *= pitch[1]
    tx *= pitch[0]
    if kind == 1:  # soft blobs, 3 .. 30 finest wavelengths across
        layer = np.zeros(shape, np.uint8)
        n = int(np.clip(length[0] * length[1] / 0.04, 4, 200))
        for _ in range(n):
            c = (rng.uniform(0, shape[1]), rng.uniform(0, shape[0]))
            ax = [rng.uniform(1.5, 15) * lm / p for lm, p in zip(lam_min, pitch)]
            cv2.ellipse(layer, (c, tuple(ax), rng.uniform(0, 180)), int(rng.integers(20, 255)), -1,
                        cv2.LINE_AA)
        layer = cv2.GaussianBlur(layer.astype(np.float32), (0, 0), 1.2)
        lum += 0.9 * _standardize(layer)
    elif kind == 2:  # stripes, modulated by coarse noise
        th = rng.uniform(0, np.pi)
        wl = 3.0 * max(abs(np.cos(th)) * lam_min[0], abs(np.sin(th)) * lam_min[1]) * rng.uniform(1, 4)
        st = np.sin((tx * np.cos(th) + ty * np.sin(th)) * (2 * np.pi / wl) + rng.uniform(0, 6.3))
        mod = _noise(rng, shape, length, np.maximum(lam_min, 0.4))
        lum += 0.9 * st * (0.5 + 0.5 * np.tanh(mod))
    lum = 0.52 + 0.44 * np.tanh(0.6 * _standardize(lum))  # soft: contrast everywhere
    hues = rng.uniform(0, 180, 2)
    cols = []
    for h in hues:
        hsv = np.uint8([[[h, rng.uniform(70, 170), 255]]])
        cols.append(cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0, 0].astype(np.float32) / 255.0)
    mix = 0.5 + 0.5 * np.tanh(1.5 * _noise(rng, shape, length, np.maximum(lam_min, 0.35)))
    col = cols[0] * mix[..., None] + cols[1] * (1 - mix[..., None])
    bgr = np.clip(lum[..., None] * col * (255.0 * shade), 0, 255)
    out = np.empty(shape + (4,), np.uint8)
    out[..., :3] = bgr
    out[..., 3] = 255
    return out


def _pixels_per_metre(q: Quad, f: float, tan_half: tuple[float, float], cams: np.ndarray):
    """Least screen density (px/m) along es and along et over the parts of q the cameras may see.

    With J the 2x2 Jacobian (metres along es, et) -> pixels at a point, a one-pixel step in
    the worst image direction moves |row k of J^-1| metres along axis k; its inverse is the
    density. Oblique faces thus get coarse texels along their foreshortened axis.
    """
    a, b = np.meshgrid(np.linspace(0.01, 0.99, 24), np.linspace(0.01, 0.99, 24))
    X = q.p0 + a.reshape(-1, 1) * q.es + b.reshape(-1, 1) * q.et
    us, ut = q.es / np.linalg.norm(q.es), q.et / np.linalg.norm(q.et)
    best = np.array([np.inf, np.inf])
    for c in cams:
        d = X - c
        Z = d[:, 2]
        ok = (Z > 0.1) & ((c - X) @ q.normal > 0)
        x, y = d[:, 0] / np.where(ok, Z, 1), d[:, 1] / np.where(ok, Z, 1)
        ok &= (np.abs(x) < tan_half[0]) & (np.abs(y) < tan_half[1])
        if not ok.any():
            continue
        js = np.stack([us[0] - x * us[2], us[1] - y * us[2]]) * (f / Z)  # px per m along es
        jt = np.stack([ut[0] - x * ut[2], ut[1] - y * ut[2]]) * (f / Z)
        det = np.abs(js[0] * jt[1] - js[1] * jt[0])
        floor = 0.03 * f / Z  # caps the coarsening of faces seen nearly edge-on
        dens_s = np.maximum(det / np.maximum(np.hypot(*jt), 1e-12), floor)
        dens_t = np.maximum(det / np.maximum(np.hypot(*js), 1e-12), floor)
        best = np.minimum(best, [dens_s[ok].min(), dens_t[ok].min()])
    return [float(v) if np.isfinite(v) else f / 6.0 for v in best]


@lru_cache(maxsize=4)
def build_scene(seed: int, f: float, width: int, height: int, cam_lo: tuple, cam_hi: tuple):
    """Quads with textures for a camera of focal length f px, centre within [cam_lo, cam_hi]."""
    quads, boxes = layout(seed)
    tan_half = (1.15 * (width / 2) / f + 0.15, 1.15 * (height / 2) / f + 0.15)
    cams = np.array([[x, y, z] for x in (cam_lo[0], cam_hi[0]) for y in (cam_lo[1], cam_hi[1])
                     for z in (cam_lo[2], cam_hi[2])])
    for q in quads:
        rng = np.random.default_rng([seed, 0x7E47, q.label])
        length = (np.linalg.norm(q.es), np.linalg.norm(q.et))
        dens = _pixels_per_metre(q, f, tan_half, cams)
        q.tw, q.th = (int(np.clip(np.ceil(L * d), 2, MAX_TEX)) for L, d in zip(length, dens))
        pitch = (length[0] / q.tw, length[1] / q.th)
        e0, e1, e2, e3 = q.ext
        shape = (q.th + e2 + e3, q.tw + e0 + e1)
        q.texture = make_texture(rng, shape, (shape[1] * pitch[0], shape[0] * pitch[1]), pitch, q.shade)
        q.texture.setflags(write=False)
    return quads, boxes


# -- rendering ------------------------------------------------------------------------------

def _clip_near(pts: np.ndarray, z: float) -> np.ndarray:
    """Sutherland-Hodgman clip of a convex polygon (camera coords, (n, 3)) to the half-space Z >= z."""
    out = []
    for i in range(len(pts)):
        p, q = pts[i], pts[(i + 1) % len(pts)]
        if p[2] >= z:
            out.append(p)
        if (p[2] >= z) != (q[2] >= z):
            out.append(p + (q - p) * ((z - p[2]) / (q[2] - p[2])))
    return np.array(out).reshape(-1, 3)


class Renderer:
    """Renders the scene for a camera-to-world pose and intrinsics K into (BGR uint8, depth float32)."""

    def __init__(self, quads: list[Quad], boxes, width: int, height: int, cx: float, cy: float):
        self.quads, self.boxes = quads, boxes
        self.size = (width, height)
        self.cx0, self.cy0 = cx, cy
        n = len(quads)
        self.m_tex = np.zeros((n, 3, 3))  # full-texture texel (s, t, 1) -> world point
        self.m_lab = np.zeros((n, 3, 3))  # 1x1 label image coords (s, t, 1) -> world point
        self.corners = np.zeros((n, 4, 3))  # world corners of the colour warp's footprint
        self.normals = np.array([q.normal for q in quads], float)
        self.d = np.array([q.normal @ q.p0 for q in quads], float)
        for i, q in enumerate(quads):
            ds, dt = q.es / q.tw, q.et / q.th
            e0, e1, e2, e3 = q.ext
            o = q.p0 + (0.5 - e0) * ds + (0.5 - e2) * dt
            self.m_tex[i] = np.column_stack([ds, dt, o])
            ws, wt = q.tw + e0 + e1, q.th + e2 + e3
            self.corners[i] = [o + s * ds + t * dt for s, t in ((-1, -1), (ws, -1), (ws, wt), (-1, wt))]
            us, ut = q.es / np.linalg.norm(q.es), q.et / np.linalg.norm(q.et)
            es, et = q.es + 2 * q.label_eps * us, q.et + 2 * q.label_eps * ut
            p0 = q.p0 - q.label_eps * (us + ut)
            self.m_lab[i] = np.column_stack([es, et, p0 + 0.5 * (es + et)])
        self.label_images = [np.full((1, 1), q.label, np.uint8) for q in quads]
        self.room = [i for i, q in enumerate(quads) if "." not in q.name]
        assert quads[self.room[0]].name == "back_wall"  # drawn first, owns all pixels at start
        self.gu = (np.arange(width, dtype=np.float32) - np.float32(cx))[None, :]  # u - cx0, (1, W)
        self.gv = (np.arange(height, dtype=np.float32) - np.float32(cy))[:, None]  # v - cy0, (H, 1)
        self._scratch = threading.local()

    def _box_order(self, C: np.ndarray) -> list[int]:
        """Boxes in painter's order (a box is drawn before every box that may hide it)."""
        def before(a, b):  # must box a be drawn before box b?
            (alo, ahi, _), (blo, bhi, _) = self.boxes[a], self.boxes[b]
            for k in range(3):
                if ahi[k] <= blo[k]:
                    return C[k] >= ahi[k]
                if bhi[k] <= alo[k]:
                    return C[k] <= alo[k]
            return False
        order = sorted(range(len(self.boxes)),
                       key=lambda i: -np.linalg.norm((self.boxes[i][0] + self.boxes[i][1]) / 2 - C))
        for _ in range(len(order)):
            for j in range(len(order) - 1):
                if before(order[j + 1], order[j]) and not before(order[j], order[j + 1]):
                    order[j], order[j + 1] = order[j + 1], order[j]
        return order

    def render(self, pose: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(BGR uint8 HxWx3, depth float32 HxW in metres) seen from camera-to-world ``pose``."""
        W, H = self.size
        R, C = pose[:3, :3], pose[:3, 3]
        rcw = R.T
        tcw = -rcw @ C
        P = K @ np.column_stack([rcw, tcw])
        visible = self.normals @ C - self.d > 1e-9
        zc = self.corners @ rcw[2] + tcw[2]  # (n, 4) camera depth of the footprint corners
        pc = self.corners @ P[:, :3].T + P[:, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = pc[..., :2] / pc[..., 2:]
        g_tex = P[:, :3] @ self.m_tex
        g_tex[:, :, 2] += P[:, 3]
        g_lab = P[:, :3] @ self.m_lab
        g_lab[:, :, 2] += P[:, 3]
        inv_tex, inv_lab = np.linalg.inv(g_tex), np.linalg.inv(g_lab)
        # inverse depth of each quad's plane: a (u - cx0) + b (v - cy0) + c
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        nc = self.normals @ rcw.T
        dc = self.d - self.normals @ C
        a, b = nc[:, 0] / (fx * dc), nc[:, 1] / (fy * dc)
        c = nc[:, 2] / dc + a * (self.cx0 - cx) + b * (self.cy0 - cy)

        canvas = np.zeros((H, W, 4), np.uint8)
        # Every ray from inside the room that meets no other room face meets the back wall,
        # so it owns all pixels to begin with (saves its label warp, the largest one).
        labels = np.full((H, W), self.quads[self.room[0]].label, np.uint8)
        order = list(self.room)
        for bi in self._box_order(C):
            order += self.boxes[bi][2]
        for i in order:
            if not visible[i]:
                continue
            clipped = zc[i].min() <= Z_NEAR
            if clipped:
                if zc[i].max() <= Z_NEAR:
                    continue
                cam = self.corners[i] @ rcw.T + tcw
                poly = _clip_near(cam, Z_NEAR) @ K.T
                pts = poly[:, :2] / poly[:, 2:]
            else:
                pts = uv[i]
            x0, y0 = max(int(np.floor(pts[:, 0].min())) - 1, 0), max(int(np.floor(pts[:, 1].min())) - 1, 0)
            x1, y1 = min(int(np.ceil(pts[:, 0].max())) + 2, W), min(int(np.ceil(pts[:, 1].max())) + 2, H)
            if x1 <= x0 or y1 <= y0:
                continue
            m_t, m_l = inv_tex[i].copy(), inv_lab[i].copy()  # dst ROI pixel -> source coords
            m_t[:, 2] += m_t[:, 0] * x0 + m_t[:, 1] * y0
            m_l[:, 2] += m_l[:, 0] * x0 + m_l[:, 1] * y0
            roi, lroi = canvas[y0:y1, x0:x1], labels[y0:y1, x0:x1]
            dst, ldst = (roi.copy(), lroi.copy()) if clipped else (roi, lroi)
            cv2.warpPerspective(self.quads[i].texture, m_t, (x1 - x0, y1 - y0), dst=dst,
                                flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                borderMode=cv2.BORDER_TRANSPARENT)
            if i != self.room[0]:
                cv2.warpPerspective(self.label_images[i], m_l, (x1 - x0, y1 - y0), dst=ldst,
                                    flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                                    borderMode=cv2.BORDER_TRANSPARENT)
            if clipped:  # keep only pixels whose ray meets the plane in front of the camera
                front = (a[i] * self.gu[:, x0:x1] + (b[i] * self.gv[y0:y1] + c[i])) > 0
                np.copyto(roi, dst, where=front[..., None])
                np.copyto(lroi, ldst, where=front)

        luts = np.zeros((3, 1, 256), np.float32)
        labs = [self.quads[i].label for i in range(len(self.quads))]
        luts[0, 0, labs], luts[1, 0, labs], luts[2, 0, labs] = a, b, c
        luts[2, 0, 0] = np.inf  # label 0 (no surface) would give depth 0 (invalid)
        scratch = getattr(self._scratch, "buf", None)
        if scratch is None:  # per-thread work buffers: render() may run in several threads
            scratch = self._scratch.buf = np.empty((2, H, W), np.float32)
        inv = cv2.LUT(labels, luts[0])
        np.multiply(inv, self.gu, out=inv)
        tmp = cv2.LUT(labels, luts[1], dst=scratch[0])
        np.multiply(tmp, self.gv, out=tmp)
        inv += tmp
        inv += cv2.LUT(labels, luts[2], dst=scratch[1])
        depth = np.divide(np.float32(1.0), inv, out=inv)
        np.maximum(depth, 0, out=depth)  # a ray leaving through the open front: invalid
        return cv2.cvtColor(canvas, cv2.COLOR_BGRA2BGR), depth

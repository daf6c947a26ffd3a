"""Tests of the embedded synthetic RGB-D source (rendered room, shaky camera, ground truth)."""
from __future__ import annotations

import math
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:  # allow running pytest without installing the package
    sys.path.insert(0, str(REPO))

from quick_stream.core.frame import RGBDFrame  # noqa: E402
from quick_stream.io.sources import SourceError, open_source  # noqa: E402
from quick_stream.io.sources.base import Source  # noqa: E402
from quick_stream.io.sources.scene import Renderer, build_scene  # noqa: E402
from quick_stream.core.lie import so3  # noqa: E402
from quick_stream.io.sources.synthetic import SyntheticSource  # noqa: E402


def rotvecs(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (N, 3) of rotation matrices (N, 3, 3)."""
    return np.array([cv2.Rodrigues(np.ascontiguousarray(r))[0].ravel() for r in R])


def reproject(f0: RGBDFrame, f1: RGBDFrame, K0=None, K1=None):
    """Frame f0's pixels lifted with its depth and moved by the ground-truth relative pose into f1.

    Returns (x, y, z): where each pixel of f0 lands in f1 (px) and its depth there (m).
    """
    H, W = f0.depth.shape
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    K0 = f0.intrinsics.K if K0 is None else K0
    K1 = f1.intrinsics.K if K1 is None else K1
    X = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K0).T * f0.depth[..., None]
    T = np.linalg.inv(f1.pose) @ f0.pose
    Y = X @ T[:3, :3].T + T[:3, 3]
    p = Y @ K1.T
    return p[..., 0] / p[..., 2], p[..., 1] / p[..., 2], Y[..., 2]


def visible_match(f0: RGBDFrame, f1: RGBDFrame):
    """Ground-truth flow f0 -> f1, the mask of pixels seen in both, and f1 sampled there."""
    x, y, z = reproject(f0, f1)
    H, W = z.shape
    mx, my = x.astype(np.float32), y.astype(np.float32)
    inside = (x > 0) & (x < W - 1) & (y > 0) & (y < H - 1)
    d1 = cv2.remap(f1.depth, mx, my, cv2.INTER_LINEAR)
    visible = inside & (np.abs(d1 - z) < 0.01 * z)
    c1 = cv2.remap(f1.color, mx, my, cv2.INTER_LINEAR)
    v, u = np.mgrid[0:H, 0:W]
    flow = np.stack([x - u, y - v], -1)
    return flow, inside, visible, c1, d1, z


def test_protocol_and_frames():
    s = SyntheticSource(width=160, height=120, frames=6, fps=25.0, seed=4)
    assert isinstance(s, Source)
    assert s.name == "synthetic" and s.has_ground_truth and len(s) == 6 and s.fps == 25.0
    frames = list(s)
    again = list(s)
    poses = s.poses()
    assert poses.shape == (6, 4, 4) and poses.dtype == np.float64
    for i, f in enumerate(frames):
        assert isinstance(f, RGBDFrame)
        f.validate()
        assert f.seq == i and f.origin == "synthetic" and not f.notes
        assert f.timestamp_ns == round(i * 1e9 / 25.0)
        assert f.color.shape == (120, 160, 3) and f.color.dtype == np.uint8
        assert f.depth.shape == (120, 160) and f.depth.dtype == np.float32
        assert f.pose.dtype == np.float64 and np.array_equal(f.pose, poses[i])
        R = f.pose[:3, :3]
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)
        assert np.array_equal(f.color, again[i].color) and np.array_equal(f.depth, again[i].depth)
    last = s.frame(-1)
    assert last.seq == 5 and np.array_equal(last.color, frames[5].color)
    with pytest.raises(IndexError, match="out of range"):
        s.frame(6)


def test_deterministic_per_seed():
    a = SyntheticSource(width=320, height=240, frames=40, seed=3)
    build_scene.cache_clear()  # regenerate the textures from scratch for b
    b = SyntheticSource(width=320, height=240, frames=40, seed=3)
    c = SyntheticSource(width=320, height=240, frames=40, seed=4)
    for i in (0, 17, 39):
        fa, fb, fc = a.frame(i), b.frame(i), c.frame(i)
        assert np.array_equal(fa.color, fb.color) and np.array_equal(fa.depth, fb.depth)
        assert np.array_equal(fa.pose, fb.pose)
        assert not np.array_equal(fa.color, fc.color)
        assert not np.allclose(fa.pose, fc.pose)
    # a frame does not depend on what was rendered before it, nor on the clip length
    assert np.array_equal(SyntheticSource(width=320, height=240, frames=18, seed=3).frame(17).color,
                          a.frame(17).color)


@pytest.mark.parametrize("shake, zoom", [(0.0, 0.0), (1.0, 0.0), (3.0, 0.2)])
def test_depth_everywhere_in_range(shake, zoom):
    s = SyntheticSource(width=160, height=120, frames=300, seed=1, shake=shake, zoom=zoom)
    for i in range(0, 300, 15):
        d = s.frame(i).depth
        assert np.all(np.isfinite(d)) and d.min() >= 0.8 and d.max() <= 5.0, (i, d.min(), d.max())


@pytest.mark.parametrize("kw", [dict(seed=0), dict(seed=2, zoom=0.2, shake=2.0)])
def test_ground_truth_pose_maps_pixels_between_frames(kw):
    s = SyntheticSource(frames=120, **kw)
    for i in (10, 100):
        f0, f1 = s.frame(i), s.frame(i + 1)
        flow, inside, visible, c1, d1, z = visible_match(f0, f1)
        assert np.median(np.linalg.norm(flow, axis=-1)[visible]) > 0.3  # the camera did move
        assert visible.sum() > 0.95 * inside.sum()  # only disocclusions disagree
        diff = np.abs(c1.astype(np.float64) - f0.color).mean(-1)[visible]
        assert diff.mean() < 2.0 and np.percentile(diff, 99) < 12, (diff.mean(), np.percentile(diff, 99))
        assert np.median(np.abs(d1 - z)[visible] / z[visible]) < 1e-4
        # a wrong pose (e.g. the inverse relative motion) does not match
        wrong = f1.with_(pose=f0.pose @ np.linalg.inv(f1.pose) @ f0.pose)
        _, inside_w, _, c1w, _, _ = visible_match(f0, wrong)
        assert np.abs(c1w.astype(np.float64) - f0.color).mean(-1)[inside_w].mean() > 3 * diff.mean()


def test_flow_from_dis_matches_ground_truth():
    s = SyntheticSource(frames=200, seed=5)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_FAST)
    for i in (30, 150):
        f0, f1 = s.frame(i), s.frame(i + 1)
        gt, _, visible, *_ = visible_match(f0, f1)
        g0, g1 = (cv2.cvtColor(f.color, cv2.COLOR_BGR2GRAY) for f in (f0, f1))
        flow = dis.calc(g0, g1, None)
        epe = np.linalg.norm(flow - gt, axis=-1)[visible]
        assert np.median(epe) < 0.5, np.median(epe)
        assert np.median(np.linalg.norm(gt, axis=-1)[visible]) > 0.3


def test_texture_has_contrast_everywhere():
    s = SyntheticSource(seed=6)
    for i in (0, 200):
        g = cv2.cvtColor(s.frame(i).color, cv2.COLOR_BGR2GRAY).astype(np.float32)
        b = 16
        blocks = g.reshape(g.shape[0] // b, b, g.shape[1] // b, b).transpose(0, 2, 1, 3)
        sd = blocks.reshape(-1, b * b).std(axis=1)
        assert np.mean(sd < 4.0) < 0.02 and np.median(sd) > 10, (np.mean(sd < 4.0), np.median(sd))
        fine = g - cv2.GaussianBlur(g, (0, 0), 2.0)  # detail at the finest scales too
        assert fine.std() > 3.0


def test_shake_rotates_about_all_axes_and_translates():
    def stats(shake):
        P = SyntheticSource(frames=300, seed=8, shake=shake).poses()
        rel = np.linalg.inv(P[1:]) @ P[:-1]
        return np.degrees(rotvecs(rel[:, :3, :3])).std(axis=0), rel[:, :3, 3].std(axis=0)

    rot, trans = stats(1.0)
    assert np.all(rot > 0.05), rot  # deg/frame about x, y and z (roll)
    assert np.all(rot < 1.0), rot
    assert np.all(trans > 5e-4) and np.all(trans < 0.01), trans  # m/frame
    rot0, _ = stats(0.0)
    assert rot0[2] < 0.01 and np.all(rot0 < 0.1)  # the intended path is a smooth pan, no roll
    rot2, _ = stats(2.0)
    assert np.all(rot2 > 1.6 * rot) and np.all(rot2 < 2.4 * rot)  # shake scales the shake
    # hand-held band: the shake is 1..12 Hz, amplitude ~0.3-1 deg per axis
    base = SyntheticSource(frames=900, seed=8, shake=0.0).poses()
    dev = np.degrees(rotvecs((np.linalg.inv(base) @ SyntheticSource(frames=900, seed=8).poses())[:, :3, :3]))
    assert np.all(np.sqrt((dev ** 2).mean(axis=0)) > 0.2) and np.all(np.abs(dev).max(axis=0) < 2.0)


def test_zoom_reported_or_hidden():
    kw = dict(width=320, height=240, frames=200, seed=2, zoom=0.15)
    rep = SyntheticSource(**kw)
    hid = SyntheticSource(report_zoom=False, **kw)
    still = SyntheticSource(**{**kw, "zoom": 0.0})
    idx = range(0, 200, 20)
    fx = np.array([rep.frame(i).intrinsics.fx for i in idx])
    assert fx.max() - fx.min() > 0.05 * rep.intrinsics.fx
    assert all(rep.frame(i).intrinsics.fy == rep.frame(i).intrinsics.fx for i in idx)
    assert {hid.frame(i).intrinsics for i in idx} == {hid.intrinsics}
    for i in (0, 90):
        a, b, c = rep.frame(i), hid.frame(i), still.frame(i)
        assert np.array_equal(a.color, b.color)  # same images, only the reported intrinsics differ
        assert np.array_equal(a.pose, c.pose)
        if abs(a.intrinsics.fx - c.intrinsics.fx) > 0.01 * c.intrinsics.fx:
            assert not np.array_equal(a.color, c.color)
    # the hidden zoom really changes the image scale: the true intrinsics explain a frame
    # pair 10 frames apart, the reported (nominal) ones do not
    fxs = np.array([rep.intrinsics_at(j).fx for j in range(200)])
    i = int(np.argmax(np.abs(fxs[10:] - fxs[:-10])))
    assert abs(fxs[i + 10] - fxs[i]) > 0.02 * fxs[i]
    f0, f1 = hid.frame(i), hid.frame(i + 10)
    errs = []
    for K0, K1 in ((rep.intrinsics_at(i).K, rep.intrinsics_at(i + 10).K), (None, None)):
        x, y, _ = reproject(f0, f1, K0, K1)
        c1 = cv2.remap(f1.color, x.astype(np.float32), y.astype(np.float32), cv2.INTER_LINEAR)
        inside = (x > 0) & (x < 319) & (y > 0) & (y < 239)
        errs.append(np.abs(c1.astype(np.float64) - f0.color).mean(-1)[inside].mean())
    assert errs[0] < 4.0 and errs[1] > 2 * errs[0], errs


@pytest.mark.parametrize("size", [(320, 240), (1280, 720)])
def test_any_resolution(size):
    W, H = size
    s = SyntheticSource(width=W, height=H, frames=10, seed=0)
    ref = SyntheticSource(frames=10, seed=0).intrinsics  # 640x480, hfov 60 deg
    k = s.intrinsics
    assert (k.width, k.height) == (W, H)
    assert math.isclose(k.fx, ref.fx * W / 640) and k.fy == k.fx
    assert (k.cx, k.cy) == ((W - 1) / 2, (H - 1) / 2)
    if H * 4 == W * 3:
        scaled = ref.scaled(W / 640)
        assert all(math.isclose(a, b, abs_tol=1e-9) for a, b in
                   zip(vars(k).values(), vars(scaled).values()))
    f = s.frame(3)
    f.validate()
    assert f.color.shape == (H, W, 3) and f.depth.shape == (H, W)
    assert f.depth.min() >= 0.8 and f.depth.max() <= 5.0
    assert np.array_equal(f.pose, SyntheticSource(frames=10, seed=0).poses()[3])  # same path


def test_from_spec_and_open_source():
    s = SyntheticSource.from_spec({"seed": "3", "frames": "100", "width": "320", "height": "240",
                                   "zoom": "0.05", "report_zoom": "false", "hfov": "50", "fps": "15"})
    assert (s.seed, len(s), s.width, s.height, s.zoom, s.report_zoom, s.hfov_deg, s.fps) == \
        (3, 100, 320, 240, 0.05, False, 50.0, 15.0)
    s = open_source("synthetic:seed=3,frames=100,width=320,height=240,zoom=0.05")
    assert isinstance(s, SyntheticSource) and (s.seed, len(s), s.width, s.zoom) == (3, 100, 320, 0.05)
    assert isinstance(open_source("synthetic"), SyntheticSource)
    bad = [({"colour": "red"}, "colour"), ({"width": "wide"}, "width"), ({"frames": "2.5"}, "frames"),
           ({"shake": "lots"}, "shake"), ({"zoom": "-0.1"}, "zoom"),
           ({"report_zoom": "maybe"}, "report_zoom"),
           ({"fps": "0"}, "fps"), ({"height": "4"}, "height"), ({"hfov": "170"}, "hfov"),
           ({"seed": "-1"}, "seed"), ({"shake": "nan"}, "shake")]
    for opts, name in bad:
        with pytest.raises(ValueError, match=name):
            SyntheticSource.from_spec(opts)
    with pytest.raises(SourceError, match="frames"):
        open_source("synthetic:frames=many")


def test_renderer_clips_faces_crossing_the_camera_plane(monkeypatch):
    """Camera placed at the room's open front edge, turned: walls cross the camera plane."""
    from quick_stream.io.sources import scene

    clipped = []
    clip = scene._clip_near
    monkeypatch.setattr(scene, "_clip_near", lambda *a: clipped.append(1) or clip(*a))
    s = SyntheticSource(width=160, height=120, seed=0)
    quads, boxes = build_scene(0, s.intrinsics.fx, 160, 120, (-0.3, -0.1, -0.4), (0.3, 0.1, 0.1))
    r = Renderer(quads, boxes, 160, 120, s.intrinsics.cx, s.intrinsics.cy)
    K = s.intrinsics.K
    for C, rv in (((0.0, 0.0, 0.3), (0.0, 0.6, 0.0)), ((0.1, 0.3, 0.25), (0.3, -0.5, 0.2))):
        pose = np.eye(4)
        pose[:3, :3] = so3.exp(np.array(rv))
        pose[:3, 3] = C
        _, depth = r.render(pose, K)
        # brute-force ray casting against every quad
        v, u = np.mgrid[0:120, 0:160].astype(np.float64)
        rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T @ pose[:3, :3].T
        best = np.full(u.shape, np.inf)
        for q in quads:
            den = rays @ q.normal
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (q.normal @ (q.p0 - pose[:3, 3])) / den
                X = pose[:3, 3] + t[..., None] * rays - q.p0
                a, b = X @ q.es / (q.es @ q.es), X @ q.et / (q.et @ q.et)
            hit = (den < 0) & (t > 0) & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)
            best = np.where(hit & (t < best), t, best)
        assert np.isfinite(best).all()
        wrong = np.abs(depth - best) > 1e-4 * best
        assert wrong.sum() < 0.001 * wrong.size, wrong.sum()  # exact up to ties on edges
    assert clipped  # the near-plane clipping path was taken

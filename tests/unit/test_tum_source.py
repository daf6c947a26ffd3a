"""Tests of the TUM-layout source and the TUM trajectory helpers."""
from __future__ import annotations

import itertools
import json
import logging
import math
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:  # allow running pytest without installing the package
    sys.path.insert(0, str(REPO))

from quick_stream.core.frame import BadFrame, Intrinsics, RGBDFrame  # noqa: E402
from quick_stream.io.sources.base import Source, SourceError  # noqa: E402
from quick_stream.io.sources.trajectory import (  # noqa: E402
    interpolate_pose,
    matrix_to_quat,
    poses_at,
    quat_to_matrix,
    read_tum_trajectory,
    slerp,
    write_tum_trajectory,
)
from quick_stream.io.sources.tum import TumSource, associate  # noqa: E402

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
KITCHEN = DATA / "7scenes_redkitchen"
PAIR = DATA / "jointvosf_pairs" / "person_standing"
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason=f"no test data folder {DATA}")

W, H = 8, 6
LOGGER = "quick_stream.io.sources.tum"


# ---------------------------------------------------------------- synthetic folders
def make_tum(
    root: Path,
    rgb_ts=(0.0, 1 / 30, 2 / 30, 3 / 30),
    depth_ts=None,
    calib: dict | None = None,
    gt: list[tuple] | None = None,
) -> Path:
    """A tiny TUM folder: colour PNGs, uint16 depth PNGs (1000 = 1 m), intrinsics.json."""
    root.mkdir(parents=True, exist_ok=True)
    (root / "rgb").mkdir(exist_ok=True)
    (root / "depth").mkdir(exist_ok=True)
    depth_ts = rgb_ts if depth_ts is None else depth_ts
    rgb_lines = ["# color images", "# timestamp filename", ""]
    for i, t in enumerate(rgb_ts):
        name = f"rgb/{i:03d}.png"
        img = np.full((H, W, 3), (10 * i) % 256, np.uint8)
        cv2.imwrite(str(root / name), img)
        rgb_lines.append(f"{t:.6f} {name}")
    depth_lines = ["# depth maps"]
    for j, t in enumerate(depth_ts):
        name = f"depth/{j:03d}.png"
        cv2.imwrite(str(root / name), np.full((H, W), 1000 + j, np.uint16))
        depth_lines.append(f"{t:.6f} {name}")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    if calib is None:
        calib = {"fx": 10.0, "fy": 11.0, "cx": 3.5, "cy": 2.5, "width": W, "height": H,
                 "depth_scale": 1000.0}
    if calib:
        (root / "intrinsics.json").write_text(json.dumps(calib))
    if gt is not None:
        lines = ["# timestamp tx ty tz qx qy qz qw"]
        lines += [" ".join(f"{v:.9f}" for v in row) for row in gt]
        (root / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    return root


def kinds(frames) -> list[str]:
    return ["ok" if isinstance(f, RGBDFrame) else "bad" for f in frames]


# ---------------------------------------------------------------- real data
@needs_data
def test_redkitchen_opens_with_poses():
    src = TumSource(KITCHEN)
    assert isinstance(src, Source)
    assert src.name == f"tum:{KITCHEN}"
    assert len(src) == 250
    K = src.intrinsics
    assert (K.width, K.height, K.fx, K.fy) == (640, 480, 585.0, 585.0)
    assert src.depth_scale == 1000.0 and not src.intrinsics_approximate
    assert src.fps == pytest.approx(30.0, rel=1e-3)
    assert src.has_ground_truth and not src.unmatched_rgb
    for i in (0, 1, 125, 249):
        f = src.frame(i)
        assert isinstance(f, RGBDFrame), f
        assert f.seq == i and f.color.shape == (480, 640, 3) and f.color.dtype == np.uint8
        assert f.depth.dtype == np.float32 and f.depth.shape == (480, 640)
        valid = f.depth[f.depth > 0]
        assert valid.size > 0.3 * f.depth.size
        assert 0.5 < float(np.median(valid)) < 4.0
        assert f.timestamp_ns == int(round(round(i / 30, 6) * 1e9))
        assert f.origin.startswith("rgb/") and " + depth/" in f.origin
        R = f.pose[:3, :3]
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.linalg.det(R) == pytest.approx(1)
    # frame 0's pose is the first ground-truth line (sample times coincide)
    ts, poses = read_tum_trajectory(KITCHEN / "groundtruth.txt")
    assert np.allclose(src.frame(0).pose, poses[0])
    assert np.allclose(src.frame(0).pose[:3, 3], [-0.3404563, 0.0164698, 0.2965692])


@needs_data
def test_redkitchen_iteration_is_lazy(monkeypatch):
    calls = []
    real = cv2.imread

    def counting(path, *a):
        calls.append(Path(path).name)
        return real(path, *a)

    monkeypatch.setattr(cv2, "imread", counting)
    src = TumSource(KITCHEN)
    assert calls == []  # opening reads no image
    frames = list(itertools.islice(iter(src), 3))
    assert kinds(frames) == ["ok"] * 3
    assert len(calls) == 6  # one colour + one depth per delivered frame, nothing ahead
    assert [f.seq for f in frames] == [0, 1, 2]


@needs_data
def test_jointvosf_pair_uses_depth_scale_5000():
    src = TumSource(PAIR)
    assert len(src) == 2 and src.depth_scale == 5000.0
    assert src.intrinsics_approximate and not src.has_ground_truth
    assert src.intrinsics.fx == pytest.approx(527.3)
    frames = list(src)
    assert kinds(frames) == ["ok", "ok"]
    raw = cv2.imread(str(PAIR / "depth" / "0.000000.png"), cv2.IMREAD_UNCHANGED)
    assert np.allclose(frames[0].depth, raw.astype(np.float32) / 5000.0)
    med = float(np.median(frames[0].depth[frames[0].depth > 0]))
    assert 0.5 < med < 6.0
    assert all(f.pose is None for f in frames)
    # the scale can be overridden
    assert TumSource(PAIR, depth_scale=1000).frame(0).depth.max() == pytest.approx(
        raw.max() / 1000.0)


# ---------------------------------------------------------------- association
def test_association_with_jittered_depth(tmp_path):
    rgb_ts = [i / 30 for i in range(6)]
    jitter = [0.004, -0.006, 0.009, -0.002, 0.0, 0.007]
    depth_ts = [t + j for t, j in zip(rgb_ts, jitter)]
    order = [3, 0, 5, 1, 4, 2]  # depth.txt listed out of order: association is by time
    root = make_tum(tmp_path / "d", rgb_ts, [depth_ts[k] for k in order])
    src = TumSource(root)
    assert len(src) == 6 and not src.unmatched_rgb
    frames = list(src)
    assert kinds(frames) == ["ok"] * 6
    for i, f in enumerate(frames):
        j = order.index(i)  # the depth entry written with rgb i's jittered time
        assert f.origin == f"rgb/{i:03d}.png + depth/{j:03d}.png"
        assert f.depth[0, 0] == pytest.approx((1000 + j) / 1000.0)
        assert f.timestamp_ns == int(round(round(rgb_ts[i], 6) * 1e9))


def test_association_is_greedy_and_one_to_one():
    # depth 0.10 is nearest to rgb 0.105 (dt 0.005) and takes it; rgb 0.09 gets nothing
    m = associate([0.09, 0.105, 0.2], [0.10, 0.19], max_dt=0.02)
    assert m == {1: 0, 2: 1}


def test_rgb_without_depth_is_skipped_and_counted(tmp_path, caplog):
    rgb_ts = [0.0, 0.1, 0.2, 0.3, 0.4]
    depth_ts = [0.001, 0.1, 0.25, 0.299, 0.4]  # 0.2 has no partner within 0.02
    root = make_tum(tmp_path / "d", rgb_ts, depth_ts)
    with caplog.at_level(logging.WARNING, logger=LOGGER):
        src = TumSource(root)
    assert len(src) == 4
    assert src.unmatched_rgb == [(0.2, "rgb/002.png")]
    assert any("1 of 5 rgb images" in r.getMessage() for r in caplog.records)
    assert [f.origin.split(" + ")[0] for f in src] == [
        "rgb/000.png", "rgb/001.png", "rgb/003.png", "rgb/004.png"]
    assert len(TumSource(root, max_dt=0.06)) == 5  # a looser max_dt pairs it


# ---------------------------------------------------------------- bad frames
def _break(root: Path, case: str) -> str:
    """Damage frame 1 of a 4-frame folder; returns the file name the error must name."""
    if case == "missing colour":
        (root / "rgb/001.png").unlink()
        return "001.png"
    if case == "unreadable colour":
        (root / "rgb/001.png").write_bytes(b"not a png at all")
        return "001.png"
    if case == "missing depth":
        (root / "depth/001.png").unlink()
        return "001.png"
    if case == "unreadable depth":
        (root / "depth/001.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
        return "001.png"
    if case == "depth wrong size":
        cv2.imwrite(str(root / "depth/001.png"), np.full((H - 1, W), 1000, np.uint16))
        return "001.png"
    if case == "depth declares 20000x20000":  # a small file whose header asks for 1.6 GB: never decoded
        png = bytearray((root / "depth/001.png").read_bytes())
        png[16:24] = (20000).to_bytes(4, "big") * 2
        (root / "depth/001.png").write_bytes(bytes(png))
        return "001.png"
    if case == "depth wrong dtype":
        cv2.imwrite(str(root / "depth/001.png"), np.full((H, W), 100, np.uint8))
        return "001.png"
    if case == "depth 3 channels":
        cv2.imwrite(str(root / "depth/001.png"), np.full((H, W, 3), 1000, np.uint16))
        return "001.png"
    if case == "depth all zero":
        cv2.imwrite(str(root / "depth/001.png"), np.zeros((H, W), np.uint16))
        return "001.png"
    if case == "float depth all non-finite":
        d = np.full((H, W), np.nan, np.float32)
        d[0, :3] = np.inf
        cv2.imwrite(str(root / "depth/001.tiff"), d)
        txt = (root / "depth.txt").read_text().replace("depth/001.png", "depth/001.tiff")
        (root / "depth.txt").write_text(txt)
        return "001.tiff"
    if case == "colour wrong size":
        cv2.imwrite(str(root / "rgb/001.png"), np.zeros((H, W + 2, 3), np.uint8))
        return "001.png"
    if case == "timestamp out of order":
        lines = (root / "rgb.txt").read_text().splitlines()
        lines = [ln.replace("0.033333 rgb/001", "0.000000 rgb/001") for ln in lines]
        (root / "rgb.txt").write_text("\n".join(lines) + "\n")
        dtxt = (root / "depth.txt").read_text().replace("0.033333 depth/001", "0.000000 depth/001")
        (root / "depth.txt").write_text(dtxt)  # keep it associated: only the order is wrong
        return "rgb.txt"
    raise AssertionError(case)


BAD_CASES = [
    "missing colour", "unreadable colour", "missing depth", "unreadable depth",
    "depth wrong size", "depth declares 20000x20000", "depth wrong dtype", "depth 3 channels", "depth all zero",
    "float depth all non-finite", "colour wrong size", "timestamp out of order",
]


@pytest.mark.parametrize("case", BAD_CASES)
def test_bad_frame_is_yielded_and_iteration_continues(tmp_path, caplog, case):
    root = make_tum(tmp_path / "d")
    fname = _break(root, case)
    src = TumSource(root, max_dt=0.02)
    with caplog.at_level(logging.WARNING, logger=LOGGER):
        frames = list(src)
    assert kinds(frames) == ["ok", "bad", "ok", "ok"], [getattr(f, "error", "") for f in frames]
    bad = frames[1]
    assert isinstance(bad, BadFrame) and bad.seq == 1
    assert fname in bad.error and str(root) in bad.error
    assert bad.origin == "rgb/001.png + " + ("depth/001.tiff" if "tiff" in fname else "depth/001.png")
    if case != "timestamp out of order":
        assert bad.timestamp_ns == int(round(0.033333 * 1e9))
    else:
        assert "rgb.txt:5" in bad.error and "out of order" in bad.error
    assert [f.seq for f in frames] == [0, 1, 2, 3]
    if case == "depth declares 20000x20000":
        assert "20000x20000 (from its header; not decoded)" in bad.error
    warned = [r for r in caplog.records if r.levelno == logging.WARNING and fname in r.getMessage()]
    assert warned
    assert isinstance(src.frame(1), BadFrame)  # random access agrees


def test_float_depth_with_some_nan_is_repaired_and_noted(tmp_path):
    root = make_tum(tmp_path / "d")
    d = np.full((H, W), 1.5, np.float32)
    d[0, 0], d[1, 1], d[2, 2] = np.nan, np.inf, -1.0
    cv2.imwrite(str(root / "depth/002.tiff"), d)
    txt = (root / "depth.txt").read_text().replace("depth/002.png", "depth/002.tiff")
    (root / "depth.txt").write_text(txt)
    f = TumSource(root).frame(2)
    assert isinstance(f, RGBDFrame)
    assert f.depth[0, 0] == 0 and f.depth[1, 1] == 0 and f.depth[2, 2] == 0
    assert f.depth[3, 3] == pytest.approx(1.5)  # float depth is taken as metres, not scaled
    assert f.notes and "3 non-finite" in f.notes[0]


def test_gray_and_bgra_colour_become_bgr(tmp_path):
    root = make_tum(tmp_path / "d")
    cv2.imwrite(str(root / "rgb/000.png"), np.full((H, W), 77, np.uint8))
    bgra = np.zeros((H, W, 4), np.uint8)
    bgra[..., 0], bgra[..., 2], bgra[..., 3] = 200, 30, 128
    cv2.imwrite(str(root / "rgb/001.png"), bgra)
    f0, f1 = TumSource(root).frame(0), TumSource(root).frame(1)
    assert f0.color.shape == (H, W, 3) and np.all(f0.color == 77)
    assert f1.color.shape == (H, W, 3) and tuple(f1.color[0, 0]) == (200, 0, 30)


# ---------------------------------------------------------------- open errors
def test_missing_folder_or_index_raises(tmp_path):
    with pytest.raises(SourceError, match="nowhere"):
        TumSource(tmp_path / "nowhere")
    root = make_tum(tmp_path / "d")
    (root / "rgb.txt").unlink()
    with pytest.raises(SourceError, match="rgb.txt"):
        TumSource(root)
    root2 = make_tum(tmp_path / "e")
    (root2 / "depth.txt").unlink()
    with pytest.raises(SourceError, match="depth.txt"):
        TumSource(root2)


@pytest.mark.parametrize("line", ["garbage", "0.5", "abc rgb/000.png", "nan rgb/000.png"])
def test_garbage_line_names_file_and_line(tmp_path, line):
    root = make_tum(tmp_path / "d")
    lines = (root / "depth.txt").read_text().splitlines()
    lines.insert(2, line)  # becomes line 3
    (root / "depth.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(SourceError) as e:
        TumSource(root)
    assert f"{root / 'depth.txt'}:3" in str(e.value)


def test_bad_groundtruth_line_names_file_and_line(tmp_path):
    root = make_tum(tmp_path / "d", gt=[(0, 0, 0, 0, 0, 0, 0, 1)])
    (root / "groundtruth.txt").write_text("# gt\n0 0 0 0 0 0 0 1\n0.1 1 2 3\n")
    with pytest.raises(SourceError, match=r"groundtruth.txt:3"):
        TumSource(root)


def test_missing_intrinsics_names_folder_and_keys(tmp_path):
    root = make_tum(tmp_path / "d", calib={})
    with pytest.raises(SourceError) as e:
        TumSource(root)
    msg = str(e.value)
    assert str(root) in msg and all(k in msg for k in ("fx", "cy", "depth_scale"))
    root2 = make_tum(tmp_path / "e", calib={"fx": 10, "fy": 10, "cx": 3.5, "cy": 2.5})
    with pytest.raises(SourceError, match="depth_scale") as e:
        TumSource(root2)
    assert "fx" not in str(e.value)
    # arguments supply what the folder lacks; image size comes from the first image
    src = TumSource(root2, depth_scale=5000)
    assert (src.intrinsics.width, src.intrinsics.height) == (W, H)
    K = Intrinsics(20, 20, 3.5, 2.5, W, H)
    src = TumSource(root, depth_scale=5000, intrinsics=K)
    assert src.intrinsics == K
    f = src.frame(0)
    assert isinstance(f, RGBDFrame) and f.depth[0, 0] == pytest.approx(1000 / 5000)


# ---------------------------------------------------------------- spec, windowing
def test_from_spec_options_and_window(tmp_path):
    root = make_tum(tmp_path / "d", rgb_ts=[i * 0.05 for i in range(8)])
    src = TumSource.from_spec(f"tum:{root}", {"depth_scale": "5000", "fx": "12.5",
                                              "start": "2", "count": "3", "max_dt": "0.01"})
    assert len(src) == 3 and src.depth_scale == 5000 and src.intrinsics.fx == 12.5
    assert src.intrinsics.fy == 11.0  # untouched keys still come from intrinsics.json
    assert src.fps == pytest.approx(20.0)
    frames = list(src)
    assert [f.seq for f in frames] == [2, 3, 4]  # seq = position in the full association
    assert src.frame(-1).seq == 4 and src.frame(0).seq == 2
    with pytest.raises(IndexError):
        src.frame(3)
    assert TumSource.from_spec(str(root), {"fps": "15"}).fps == 15.0
    assert len(TumSource.from_spec(str(root), {"start": "6", "count": "10"})) == 2
    with pytest.raises(ValueError, match="bogus"):
        TumSource.from_spec(str(root), {"bogus": "1"})
    with pytest.raises(ValueError, match="depth_scale"):
        TumSource.from_spec(str(root), {"depth_scale": "lots"})
    with pytest.raises(ValueError, match="count"):
        TumSource.from_spec(str(root), {"count": "1.5"})
    with pytest.raises(ValueError, match="start"):
        TumSource.from_spec(str(root), {"start": "-1"})
    with pytest.raises(ValueError, match="depth_scale"):
        TumSource.from_spec(str(root), {"depth_scale": "0"})


# ---------------------------------------------------------------- trajectories
def _rot(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    R, _ = cv2.Rodrigues(axis * angle)
    return R


def test_quaternion_round_trip():
    rng = np.random.default_rng(0)
    qs = list(rng.normal(size=(200, 4)))
    qs += [np.array(q, float) for q in
           ([0, 0, 0, 1], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0.7071068, 0, 0, 0.7071068])]
    for q in qs:
        q = q / np.linalg.norm(q)
        R = quat_to_matrix(q)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.linalg.det(R) == pytest.approx(1)
        q2 = matrix_to_quat(R)
        assert np.allclose(q2, q if q[3] >= 0 else -q, atol=1e-9) or np.allclose(q2, -q, atol=1e-9)
        assert np.allclose(quat_to_matrix(q2), R, atol=1e-12)
    # known convention: 90 deg about z is (0, 0, sin45, cos45), maps x to y
    R = quat_to_matrix([0, 0, math.sin(math.pi / 4), math.cos(math.pi / 4)])
    assert np.allclose(R @ [1, 0, 0], [0, 1, 0])
    for axis in ([1, 0, 0], [0, 1, 1], [1, -2, 3]):  # near-180 deg rotations
        R = _rot(axis, math.pi - 1e-9)
        assert np.allclose(quat_to_matrix(matrix_to_quat(R)), R, atol=1e-8)


def test_trajectory_of_a_similarity_path_keeps_the_rotation(tmp_path):
    """A SIM(3) or affine path's linear part is not a rotation: the file gets the nearest rotation."""
    R = _rot([1, -2, 3], 0.7)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = 2.5 * R, (1, 2, 3)
    write_tum_trajectory(tmp_path / "t.txt", [0.0], [T])
    _, poses = read_tum_trajectory(tmp_path / "t.txt")
    assert np.allclose(poses[0][:3, :3], R, atol=1e-9) and np.allclose(poses[0][:3, 3], (1, 2, 3))


def test_trajectory_write_read_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    ts = np.arange(10) / 30.0
    poses = []
    for _ in ts:
        T = np.eye(4)
        T[:3, :3] = _rot(rng.normal(size=3), rng.uniform(0, 3))
        T[:3, 3] = rng.normal(size=3)
        poses.append(T)
    poses_with_gap = poses[:4] + [None] + poses[5:]
    p = tmp_path / "traj.txt"
    assert write_tum_trajectory(p, ts, poses_with_gap) == 9
    ts2, poses2 = read_tum_trajectory(p)
    keep = [i for i in range(10) if i != 4]
    assert np.allclose(ts2, ts[keep], atol=1e-9)
    assert poses2.shape == (9, 4, 4)
    assert np.allclose(poses2, np.array(poses)[keep], atol=1e-8)
    with pytest.raises(ValueError):
        write_tum_trajectory(p, ts[:3], poses)


def test_groundtruth_interpolation(tmp_path):
    T0 = np.eye(4)
    T1 = np.eye(4)
    T1[:3, :3] = _rot([0, 0, 1], math.pi / 2)
    T1[:3, 3] = [1.0, 2.0, -4.0]
    ts = np.array([1.0, 1.02])
    mid = poses_at(ts, np.array([T0, T1]), [1.005, 1.01, 0.99, 1.03], max_dt=0.02)
    assert np.allclose(mid[1][:3, 3], [0.5, 1.0, -2.0])
    assert np.allclose(mid[1][:3, :3], _rot([0, 0, 1], math.pi / 4))
    assert np.allclose(mid[0][:3, :3], _rot([0, 0, 1], math.pi / 8))
    assert np.allclose(mid[0][:3, 3], [0.25, 0.5, -1.0])
    assert mid[2] is None and mid[3] is None  # outside the ground-truth time range
    assert np.allclose(interpolate_pose(T0, T1, 1.0), T1)
    assert np.allclose(slerp([0, 0, 0, 1], [0, 0, 0, -1], 0.5), [0, 0, 0, 1])
    # a gap in the ground truth longer than 2 * max_dt leaves the middle unknown
    far = poses_at([0.0, 1.0], np.array([T0, T1]), [0.01, 0.5, 0.99], max_dt=0.02)
    assert far[0] is not None and far[1] is None and far[2] is not None

    # through the source: frames get poses interpolated at their rgb timestamps
    q1 = matrix_to_quat(T1)
    gt = [(0.0, 0, 0, 0, 0, 0, 0, 1), (0.04, 1.0, 2.0, -4.0, *q1)]
    root = make_tum(tmp_path / "d", rgb_ts=[0.0, 0.02, 0.04, 0.5], gt=gt)
    src = TumSource(root)
    assert src.has_ground_truth
    frames = list(src)
    assert kinds(frames) == ["ok"] * 4
    assert np.allclose(frames[0].pose, T0)
    assert np.allclose(frames[1].pose[:3, 3], [0.5, 1.0, -2.0])
    assert np.allclose(frames[1].pose[:3, :3], _rot([0, 0, 1], math.pi / 4), atol=1e-6)
    assert np.allclose(frames[2].pose, T1, atol=1e-6)
    assert frames[3].pose is None  # after the last ground-truth sample
    # a window wholly outside the ground truth has none
    assert not TumSource(root, start=3).has_ground_truth


def test_a_folder_whose_name_has_a_comma_opens_with_and_without_options(tmp_path):
    """The known-shake and degraded clips the benchmarks make are named like ``..._sh4,2_lag1_...``: the
    spec's options are the ``key=value`` items at its end, and a spec naming an existing folder is a path."""
    from quick_stream.io.sources import open_source

    root = make_tum(tmp_path / "clip_sh4,2_lag1")
    assert len(list(open_source(f"tum:{root}"))) == 4
    assert len(list(open_source(f"tum:{root},count=2"))) == 2
    with pytest.raises(SourceError, match="nowhere,2"):
        open_source(f"tum:{tmp_path / 'nowhere,2'}")
    with pytest.raises(SourceError, match="bogus"):
        open_source(f"tum:{root},bogus=1")

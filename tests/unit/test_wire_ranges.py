"""The wire's numbers that feed math are range-checked at decode (docs/wire-format.md, "Ranges"; issue 30
row 5): finite is not enough. Each refusal names the message type, seq and field; what the stabilizer
itself sends is in range."""
from __future__ import annotations

import msgpack
import numpy as np
import pytest

from quick_stream.core.frame import Intrinsics, RGBDFrame
from quick_stream.core.lie import get_group
from quick_stream.core.motion import MotionEstimate
from quick_stream.core.path.planner import Correction
from quick_stream.stream.wire import StabilizedImage, WireError, decode, encode_correction, encode_frame, encode_motion
from quick_stream.stream.wire import encode_stabilized
from quick_stream.stream.wire.ranges import MAX_ENTRY

RNG = np.random.default_rng(3)


def _frame(k: Intrinsics | None = None) -> RGBDFrame:
    k = k or Intrinsics(50.0, 51.0, 15.5, 11.5, 32, 24)
    color = RNG.integers(0, 255, (k.height, k.width, 3), dtype=np.uint8)
    depth = RNG.uniform(0.5, 3.0, (k.height, k.width)).astype(np.float32)
    return RGBDFrame(color, depth, k, 1_000, 9, np.eye(4), "test")


def _motion(group: str = "se3", matrix: np.ndarray | None = None) -> MotionEstimate:
    G = get_group(group)
    m = G.exp(RNG.uniform(-0.3, 0.3, G.dim)) if matrix is None else matrix
    return MotionEstimate(9, 10, group, "exact", m, np.zeros(G.dim), True, "", 10, 0.9, 0.2, None)


def _with(data: bytes, **fields) -> bytes:
    d = msgpack.unpackb(data, raw=False)
    for k, v in fields.items():
        if "." in k:
            outer, inner = k.split(".")
            d[outer][inner] = v
        else:
            d[k] = v
    return msgpack.packb(d, use_bin_type=True)


def _refused(data: bytes, field: str, words: str) -> None:
    with pytest.raises(WireError) as e:
        decode(data)
    assert e.value.field == field and e.value.seq == 9 and words in e.value.problem, str(e.value)


@pytest.mark.parametrize("group", ["se3", "sim3", "sa3", "ga3"])
def test_motions_of_every_group_pass_and_a_huge_finite_matrix_is_refused(group):
    data = encode_motion(_motion(group), "cam0")
    assert decode(data).obj.group == group
    _refused(_with(data, matrix=[1e308] * 16), "matrix", "outside")
    m = np.eye(4)
    m[0, 3] = 2 * MAX_ENTRY
    _refused(_with(data, matrix=m.ravel().tolist()), "matrix", "outside")


def test_a_motion_must_be_in_its_group():
    shear = np.eye(4)
    shear[0, 1] = 0.3
    _refused(encode_motion(_motion("se3", shear), "cam0"), "matrix", "not a rotation")
    _refused(encode_motion(_motion("sim3", shear), "cam0"), "matrix", "not a scaled rotation")
    assert decode(encode_motion(_motion("ga3", shear), "cam0")).obj.group == "ga3"
    stretch = np.diag([2.0, 1.0, 1.0, 1.0])
    _refused(encode_motion(_motion("sa3", stretch), "cam0"), "matrix", "determinant")
    assert decode(encode_motion(_motion("sim3", np.diag([2.0, 2.0, 2.0, 1.0])), "cam0")).obj.group == "sim3"
    mirror = np.diag([1.0, 1.0, -1.0, 1.0])
    _refused(encode_motion(_motion("ga3", mirror), "cam0"), "matrix", "mirrored")
    flat = np.diag([1.0, 1.0, 1e-9, 1.0])
    _refused(encode_motion(_motion("ga3", flat), "cam0"), "matrix", "ill-conditioned")
    row = np.eye(4)
    row[3, 0] = 0.5
    _refused(encode_motion(_motion("ga3", row), "cam0"), "matrix", "last row")
    data = encode_motion(_motion(), "cam0")
    _refused(_with(data, inlier_ratio=3.0), "inlier_ratio", "[0, 1]")


def test_corrections_poses_zooms_and_timestamps():
    c = Correction(9, get_group("se3").exp(np.full(6, 0.1)), 0, False, True, "", 1.2, np.eye(4), 0, "fit")
    data = encode_correction(c, "cam0")
    assert decode(data).obj.zoom == 1.2
    _refused(_with(data, matrix=[1e300] * 16), "matrix", "outside")
    _refused(_with(data, camera=np.diag([1.0, 1.0, 0.0, 1.0]).ravel().tolist()), "camera", "singular")
    _refused(_with(data, zoom=1e6), "zoom", "outside [0.01, 100]")
    _refused(_with(data, zoom=1e-300), "zoom", "outside")
    s = encode_stabilized(StabilizedImage(9, 5, np.zeros((8, 8, 3), np.uint8), 1.1), "cam0", src_pub_ns=3)
    assert decode(s).obj.zoom == 1.1
    _refused(_with(s, zoom=500.0), "zoom", "outside")
    _refused(_with(s, t_ns=-1), "t_ns", "timestamp")
    _refused(_with(s, src_pub_ns=2**64 - 1), "src_pub_ns", "timestamp")
    f = encode_frame(_frame(), "cam0", pub_ns=7)
    assert decode(f).pub_ns == 7
    _refused(_with(f, t_ns=-5), "t_ns", "timestamp")
    _refused(_with(f, pub_ns=2**63), "pub_ns", "timestamp")
    _refused(_with(f, pose=[1e307] * 16), "pose", "outside")
    pose = np.eye(4)
    pose[:3, 3] = (1e5, -2e5, 30.0)  # a ground-truth pose is checked for its magnitude only
    assert np.allclose(decode(_with(f, pose=pose.ravel().tolist())).obj.pose, pose)


def test_intrinsics_must_be_a_plausible_camera_for_the_image():
    data = encode_frame(_frame(), "cam0")
    _refused(_with(data, **{"intrinsics.fx": 1e-6}), "intrinsics.fx", "field of view")
    _refused(_with(data, **{"intrinsics.fy": 1e9}), "intrinsics.fy", "field of view")
    _refused(_with(data, **{"intrinsics.cx": 1e6}), "intrinsics.cx", "principal point")
    _refused(_with(data, **{"intrinsics.cy": -100.0}), "intrinsics.cy", "principal point")
    for k in (Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480), Intrinsics(4.0, 4.0, -20.0, 40.0, 32, 24)):
        assert decode(encode_frame(_frame(k), "cam0")).obj.intrinsics == k

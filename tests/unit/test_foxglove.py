"""Foxglove JSON channels: schemas in the MCAP file, valid messages, images and quaternions."""
import base64
import json
import math

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader

from quick_stream.core.frame import Intrinsics
from quick_stream.io import foxglove as fx
from quick_stream.io.recording import Recorder
from quick_stream.io.sources import open_source
from quick_stream.io.sources.trajectory import quat_to_matrix
from quick_stream.stream.keys import key
from quick_stream.stream.wire import (
    StabilizedImage,
    WireError,
    encode_frame,
    encode_motion,
    encode_stabilized,
)

_TYPES = {"object": dict, "array": list, "string": str}


def check(value, schema, where="$"):
    """Assert ``value`` fits the JSON-schema subset our schemas use; raises AssertionError naming the path."""
    t = schema.get("type")
    if t == "number":
        assert isinstance(value, (int, float)) and not isinstance(value, bool), f"{where}: not a number: {value!r}"
        assert math.isfinite(value), f"{where}: non-finite"
    elif t == "integer":
        assert isinstance(value, int) and not isinstance(value, bool), f"{where}: not an integer: {value!r}"
    elif t is not None:
        assert isinstance(value, _TYPES[t]), f"{where}: not a {t}: {type(value).__name__}"
    if "minimum" in schema:
        assert value >= schema["minimum"], f"{where}: {value} < {schema['minimum']}"
    if "maximum" in schema:
        assert value <= schema["maximum"], f"{where}: {value} > {schema['maximum']}"
    if t == "object":
        for name in schema.get("required", []):
            assert name in value, f"{where}: missing required {name!r}"
        for name, sub in schema.get("properties", {}).items():
            if name in value:
                check(value[name], sub, f"{where}.{name}")
    if t == "array":
        assert len(value) >= schema.get("minItems", 0), f"{where}: fewer than {schema['minItems']} items"
        assert len(value) <= schema.get("maxItems", len(value)), f"{where}: more than {schema['maxItems']} items"
        for i, item in enumerate(value):
            check(item, schema.get("items", {}), f"{where}[{i}]")


def test_checker_rejects_what_it_should():
    s = fx.SCHEMAS["foxglove.CameraCalibration"]
    good = json.loads(fx.camera_calibration(Intrinsics(100, 100, 50, 40, 101, 81), 5, "cam"))
    check(good, s)
    for bad in ({**good, "K": good["K"][:8]}, {**good, "width": 1.5}, {**good, "D": ["x"]},
                {k: v for k, v in good.items() if k != "frame_id"},
                {**good, "timestamp": {"sec": 0, "nsec": 10**9}}, {**good, "width": True}):
        with pytest.raises(AssertionError):
            check(bad, s)


@pytest.fixture(scope="module")
def frames():
    return list(open_source("synthetic:frames=3,width=160,height=120"))


@pytest.fixture(scope="module")
def recording(tmp_path_factory, frames):
    """A recording with msgpack channels and every Foxglove channel; returns (path, expected counts)."""
    path = tmp_path_factory.mktemp("fox") / "rec.mcap"
    with Recorder(path) as rec:
        topics = fx.register_channels(rec, "cam0", tf=True)
        for f in frames:
            t = f.timestamp_ns
            frame_msg = encode_frame(f, "cam0", color="jpeg")
            stab_msg = encode_stabilized(StabilizedImage(f.seq, t, f.color[::-1].copy()), "cam0", color="raw")
            rec.write(key("cam0", "frame"), frame_msg, log_time_ns=t)
            rec.write(key("cam0", "stabilized"), stab_msg, log_time_ns=t)
            rec.write(topics["color"], fx.compressed_image_from_message(frame_msg, "cam0_camera"), t)
            rec.write(topics["stabilized"], fx.compressed_image_from_message(stab_msg, "cam0_camera"), t)
            rec.write(topics["calibration"], fx.camera_calibration(f.intrinsics, t, "cam0_camera"), t)
            rec.write(topics["camera_pose"], fx.pose_in_frame(f.pose, t), t)
            sim3 = f.pose.copy()
            sim3[:3, :3] *= 1.3  # a scaled pose must still give a unit quaternion
            rec.write(topics["stabilized_pose"], fx.pose_in_frame(sim3, t), t)
            rec.write(topics["tf"], fx.frame_transform(f.pose, t, "world", "cam0_camera"), t)
    return path, topics


def test_foxglove_channels_have_schemas_and_valid_messages(recording, frames):
    path, topics = recording
    seen: dict[str, list] = {}
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        for schema, channel, message in reader.iter_messages(log_time_order=True):
            seen.setdefault(channel.topic, []).append((schema, channel, message))
    assert set(seen) == {key("cam0", "frame"), key("cam0", "stabilized"), *[t for n, t in topics.items()
                                                                             if not n.startswith("msgpack:")]}
    for name, topic in topics.items():
        if name.startswith("msgpack:"):
            ch = next(c for c in summary.channels.values() if c.topic == topic)
            assert ch.message_encoding == "msgpack" and ch.schema_id == 0
            continue
        want = "foxglove.FrameTransform" if name == "tf" else fx.STREAM_CHANNELS[name]
        assert len(seen[topic]) == len(frames), topic
        for schema, channel, message in seen[topic]:
            assert channel.message_encoding == "json"
            assert schema.name == want and schema.encoding == "jsonschema"
            schema_dict = json.loads(schema.data)
            assert schema_dict == fx.SCHEMAS[want]
            msg = json.loads(message.data)
            check(msg, schema_dict, topic)
            assert msg["timestamp"]["sec"] * 10**9 + msg["timestamp"]["nsec"] == message.log_time


def test_compressed_images_decode_to_the_frame_size(recording, frames):
    path, topics = recording
    with open(path, "rb") as fh:
        msgs = [(c.topic, json.loads(m.data)) for _, c, m in make_reader(fh).iter_messages(
            topics=[topics["color"], topics["stabilized"]])]
    assert len(msgs) == 2 * len(frames)
    for topic, msg in msgs:
        assert msg["format"] == "jpeg" and msg["frame_id"] == "cam0_camera"
        img = cv2.imdecode(np.frombuffer(base64.b64decode(msg["data"]), np.uint8), cv2.IMREAD_COLOR)
        assert img is not None and img.shape == (120, 160, 3), topic
    # the colour channel carries the frame message's JPEG bytes unchanged
    frame_msg = encode_frame(frames[0], "cam0", color="jpeg", quality=77)
    img = fx.image_from_message(frame_msg)
    assert img.data[:2] == b"\xff\xd8" and (img.stream, img.seq, img.timestamp_ns) == ("cam0", 0, 0)
    jpeg = base64.b64decode(json.loads(fx.compressed_image_from_message(frame_msg, "c"))["data"])
    assert jpeg == img.data


def test_image_from_message_rejects_other_types(frames):
    from quick_stream.core.motion import MotionEstimate

    m = MotionEstimate(0, 1, "se3", "exact", np.eye(4), np.zeros(6), True, "", 10, 1.0, 0.1, None)
    with pytest.raises(WireError, match="no image"):
        fx.image_from_message(encode_motion(m, "cam0"))
    with pytest.raises(WireError):
        fx.image_from_message(b"\x00junk")


def test_calibration_and_timestamps():
    k = Intrinsics(500.0, 510.0, 319.5, 239.5, 640, 480)
    msg = json.loads(fx.camera_calibration(k, 3_000_000_007, "cam"))
    assert msg["timestamp"] == {"sec": 3, "nsec": 7}
    assert np.allclose(np.reshape(msg["K"], (3, 3)), k.K)
    assert msg["P"][:3] == [500.0, 0.0, 319.5] and msg["P"][3] == 0.0
    assert (msg["width"], msg["height"], msg["distortion_model"]) == (640, 480, "plumb_bob")
    with pytest.raises(ValueError):
        fx.timestamp(-1)
    with pytest.raises(ValueError, match="format"):
        fx.compressed_image(0, b"x", "bmp", "cam")


def _rot(axis, deg):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    return cv2.Rodrigues(a * math.radians(deg))[0]


@pytest.mark.parametrize("axis,deg,expect", [
    ((1, 0, 0), 90, (math.sqrt(0.5), 0, 0, math.sqrt(0.5))),
    ((0, 1, 0), 90, (0, math.sqrt(0.5), 0, math.sqrt(0.5))),
    ((0, 0, 1), 180, (0, 0, 1, 0)),
    ((1, 0, 0), 180, (1, 0, 0, 0)),
    ((0, 1, 0), 179.999, (0, 1, 0, math.sin(math.radians(0.0005)))),
    ((1, 1, 1), 120, (0.5, 0.5, 0.5, 0.5)),
    ((0, 0, 1), 0, (0, 0, 0, 1)),
])
def test_known_rotations(axis, deg, expect):
    q = fx.rotation_to_quaternion(_rot(axis, deg))
    assert np.allclose(q, expect, atol=1e-6) or np.allclose(-q, expect, atol=1e-6)
    assert abs(np.linalg.norm(q) - 1) < 1e-12 and q[3] >= 0


def test_quaternion_round_trip():
    rng = np.random.default_rng(7)
    for _ in range(500):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        r = quat_to_matrix(q)
        q2 = fx.rotation_to_quaternion(r)
        assert np.allclose(fx.quaternion_to_rotation(q2), r, atol=1e-12)
        assert np.allclose(q2, q if q[3] >= 0 else -q, atol=1e-9)


def test_scaled_and_sheared_matrices_give_unit_quaternions_of_their_rotation():
    rng = np.random.default_rng(3)
    for _ in range(200):
        r = quat_to_matrix(rng.normal(size=4))
        s = float(rng.uniform(0.2, 5))
        q_sim3 = fx.rotation_to_quaternion(s * r)  # similarity: the rotation comes back exactly
        assert np.allclose(fx.quaternion_to_rotation(q_sim3), r, atol=1e-10)
        shear = np.eye(3) + np.triu(rng.normal(scale=0.1, size=(3, 3)), 1)
        a = r @ np.diag(rng.uniform(0.5, 2, 3)) @ shear  # affine (SA3/GA3 linear part)
        q = fx.rotation_to_quaternion(a)
        assert abs(np.linalg.norm(q) - 1) < 1e-12
        rq = fx.quaternion_to_rotation(q)
        assert np.allclose(rq.T @ rq, np.eye(3), atol=1e-10) and np.linalg.det(rq) > 0
        assert np.allclose(rq, fx.nearest_rotation(a), atol=1e-10)
        # the projection is the closest rotation: no nearby rotation is closer
        for _ in range(5):
            other = rq @ _rot(rng.normal(size=3), 2.0)
            assert np.linalg.norm(a - rq) <= np.linalg.norm(a - other) + 1e-12


def test_pose_message_drops_scale_and_rejects_bad_matrices():
    m = np.eye(4)
    m[:3, :3] = 2.5 * _rot((0, 0, 1), 90)
    m[:3, 3] = (1, 2, 3)
    msg = json.loads(fx.pose_in_frame(m, 10))
    check(msg, fx.SCHEMAS["foxglove.PoseInFrame"])
    assert msg["frame_id"] == "world" and msg["pose"]["position"] == {"x": 1.0, "y": 2.0, "z": 3.0}
    o = msg["pose"]["orientation"]
    assert np.allclose([o["x"], o["y"], o["z"], o["w"]], (0, 0, math.sqrt(0.5), math.sqrt(0.5)))
    bad = np.eye(4)
    bad[0, 0] = np.nan
    for b in (bad, np.zeros((4, 4)), np.eye(3)):
        with pytest.raises(ValueError):
            fx.pose_in_frame(b, 0)
    # a reflection is mapped to a proper rotation, never to det -1
    assert np.linalg.det(fx.nearest_rotation(np.diag([1.0, 1.0, -1.0]))) > 0


def test_topics_validate_stream_ids():
    assert fx.topic("cam0", "camera_pose") == "/cam0/camera_pose"
    with pytest.raises(ValueError):
        fx.topic("cam/0", "color")
    with pytest.raises(ValueError):
        fx.topic("cam0", "depth")

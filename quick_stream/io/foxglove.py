"""Foxglove-viewable JSON channels for MCAP recordings (beside the exact msgpack channels).

Foxglove cannot decode msgpack, so a recording also carries JSON channels with the
published Foxglove schemas (message encoding ``json``, schema encoding ``jsonschema``):

- ``/<stream>/color``: ``foxglove.CompressedImage`` of the input colour (the frame's JPEG);
- ``/<stream>/stabilized``: ``foxglove.CompressedImage`` of the stabilized output;
- ``/<stream>/calibration``: ``foxglove.CameraCalibration`` (pinhole, no distortion);
- ``/<stream>/camera_pose``, ``/<stream>/stabilized_pose``: ``foxglove.PoseInFrame`` in ``world``;
- ``/tf``: ``foxglove.FrameTransform`` (optional).

The exact-replay channels stay msgpack (topic = the zenoh key expression, no schema).

Timestamps are the frame's capture timestamp as ``{"sec", "nsec"}``. Bytes fields
(``CompressedImage.data``) are base64 strings, as JSON-encoded Foxglove messages
require. The schemas below use the published field names; they add ``required``
lists for the fields this module always writes (viewers ignore them).

Poses are 4x4 matrices. Motions of the larger groups (SIM3, SA3, GA3) have a
linear part that is not a rotation; :func:`nearest_rotation` projects it onto the
closest rotation (SVD, polar decomposition) and the scale/shear is dropped, since a
Foxglove pose has only a position and a unit quaternion.
"""
from __future__ import annotations

import base64
import json
from typing import Any, NamedTuple

import cv2
import numpy as np

from ..core.frame import Intrinsics
from ..stream.keys import key
from ..stream.wire.codec import unpack
from .recording import Recorder
from .sources.trajectory import matrix_to_quat

# --- schemas ------------------------------------------------------------------------------------

_TIME = {
    "type": "object",
    "title": "time",
    "properties": {
        "sec": {"type": "integer", "minimum": 0},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999},
    },
    "required": ["sec", "nsec"],
}
_NUMBER = {"type": "number"}
_VECTOR3 = {
    "type": "object",
    "title": "foxglove.Vector3",
    "properties": {"x": _NUMBER, "y": _NUMBER, "z": _NUMBER},
    "required": ["x", "y", "z"],
}
_QUATERNION = {
    "type": "object",
    "title": "foxglove.Quaternion",
    "properties": {"x": _NUMBER, "y": _NUMBER, "z": _NUMBER, "w": _NUMBER},
    "required": ["x", "y", "z", "w"],
}


def _numbers(n: int | None = None) -> dict[str, Any]:
    s: dict[str, Any] = {"type": "array", "items": _NUMBER}
    if n is not None:
        s.update(minItems=n, maxItems=n)
    return s


def _object(title: str, description: str, properties: dict[str, Any]) -> dict[str, Any]:
    return {"title": title, "description": description, "type": "object",
            "properties": properties, "required": list(properties)}


SCHEMAS: dict[str, dict] = {
    "foxglove.CompressedImage": _object("foxglove.CompressedImage", "A compressed image", {
        "timestamp": _TIME,
        "frame_id": {"type": "string"},
        "data": {"type": "string", "contentEncoding": "base64"},
        "format": {"type": "string"},
    }),
    "foxglove.CameraCalibration": _object("foxglove.CameraCalibration", "Camera calibration parameters", {
        "timestamp": _TIME,
        "frame_id": {"type": "string"},
        "width": {"type": "integer", "minimum": 0},
        "height": {"type": "integer", "minimum": 0},
        "distortion_model": {"type": "string"},
        "D": _numbers(),
        "K": _numbers(9),
        "R": _numbers(9),
        "P": _numbers(12),
    }),
    "foxglove.PoseInFrame": _object("foxglove.PoseInFrame", "A timestamped pose in a reference frame", {
        "timestamp": _TIME,
        "frame_id": {"type": "string"},
        "pose": {"type": "object", "title": "foxglove.Pose",
                 "properties": {"position": _VECTOR3, "orientation": _QUATERNION},
                 "required": ["position", "orientation"]},
    }),
    "foxglove.FrameTransform": _object("foxglove.FrameTransform", "A transform between two reference frames", {
        "timestamp": _TIME,
        "parent_frame_id": {"type": "string"},
        "child_frame_id": {"type": "string"},
        "translation": _VECTOR3,
        "rotation": _QUATERNION,
    }),
}

# topic suffix -> schema name of the per-stream channels
STREAM_CHANNELS: dict[str, str] = {
    "color": "foxglove.CompressedImage",
    "stabilized": "foxglove.CompressedImage",
    "calibration": "foxglove.CameraCalibration",
    "camera_pose": "foxglove.PoseInFrame",
    "stabilized_pose": "foxglove.PoseInFrame",
}
TF_TOPIC = "/tf"
MSGPACK_STAGES = ("frame", "flow", "motion", "correction", "stabilized", "stats")


def topic(stream: str, channel: str) -> str:
    """The Foxglove topic of a stream's channel, e.g. ``topic("cam0", "color") == "/cam0/color"``."""
    if channel not in STREAM_CHANNELS:
        raise ValueError(f"Foxglove channel must be one of {tuple(STREAM_CHANNELS)}, got {channel!r}")
    key(stream, "frame")  # validates the stream id
    return f"/{stream}/{channel}"


def schema_bytes(name: str) -> bytes:
    """The JSON text of schema ``name`` as stored in the MCAP schema record."""
    return json.dumps(SCHEMAS[name], separators=(",", ":")).encode()


def register_channels(recorder: Recorder, stream: str, tf: bool = False,
                      msgpack_stages: tuple[str, ...] = MSGPACK_STAGES) -> dict[str, str]:
    """Register a stream's Foxglove JSON channels (and ``/tf`` if ``tf``) and msgpack channels.

    Returns {name: topic} with names ``color``, ``stabilized``, ... , ``tf`` and, for the
    msgpack channels, ``msgpack:<stage>`` (topic = the zenoh key expression).
    """
    topics: dict[str, str] = {}
    for stage in msgpack_stages:
        recorder.channel(key(stream, stage), encoding="msgpack")
        topics[f"msgpack:{stage}"] = key(stream, stage)
    channels = [(name, topic(stream, name), schema) for name, schema in STREAM_CHANNELS.items()]
    if tf:
        channels.append(("tf", TF_TOPIC, "foxglove.FrameTransform"))
    for name, t, schema in channels:
        recorder.channel(t, encoding="json", schema_name=schema, schema=schema_bytes(schema),
                         schema_encoding="jsonschema")
        topics[name] = t
    return topics


# --- rotations ----------------------------------------------------------------------------------

def nearest_rotation(m: np.ndarray) -> np.ndarray:
    """The rotation matrix closest (Frobenius) to the 3x3 linear part ``m``.

    ``m = U S V^T`` -> ``U diag(1, 1, det(U V^T)) V^T``: the orthogonal polar factor,
    with the sign fixed so a reflection never comes out. For ``s R`` (SIM3) this is
    exactly ``R``; for an affine part (SA3/GA3) scale and shear are dropped.
    """
    m = np.asarray(m, dtype=np.float64)[:3, :3]
    if not np.all(np.isfinite(m)):
        raise ValueError(f"matrix has non-finite values: {m.tolist()}")
    u, s, vt = np.linalg.svd(m)
    if s[0] <= 0 or s[-1] <= 1e-12 * s[0]:
        raise ValueError(f"matrix is singular (singular values {s.tolist()}); no rotation to take")
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return u @ np.diag([1.0, 1.0, d]) @ vt


def rotation_to_quaternion(m: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(x, y, z, w)``, ``w >= 0``, of the rotation nearest ``m`` (Shepperd's method)."""
    return matrix_to_quat(nearest_rotation(m))


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """3x3 rotation matrix of the quaternion ``(x, y, z, w)`` (normalised first)."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


# --- messages -----------------------------------------------------------------------------------

def timestamp(timestamp_ns: int) -> dict[str, int]:
    """Foxglove time ``{"sec", "nsec"}`` of a non-negative timestamp in ns."""
    t = int(timestamp_ns)
    if t < 0:
        raise ValueError(f"Foxglove timestamps must be >= 0 ns, got {t}")
    return {"sec": t // 1_000_000_000, "nsec": t % 1_000_000_000}


def _json(msg: dict[str, Any]) -> bytes:
    return json.dumps(msg, separators=(",", ":"), allow_nan=False).encode()


def _pose_parts(matrix: np.ndarray) -> tuple[dict[str, float], dict[str, float]]:
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"pose must be a 4x4 matrix, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise ValueError("pose has non-finite values")
    q = rotation_to_quaternion(m[:3, :3])
    t = m[:3, 3]
    return ({"x": float(t[0]), "y": float(t[1]), "z": float(t[2])},
            {"x": float(q[0]), "y": float(q[1]), "z": float(q[2]), "w": float(q[3])})


def compressed_image(timestamp_ns: int, data: bytes, fmt: str, frame_id: str) -> bytes:
    """A ``foxglove.CompressedImage`` JSON message of already-compressed ``jpeg``/``png`` bytes."""
    if fmt not in ("jpeg", "png"):
        raise ValueError(f"image format must be 'jpeg' or 'png', got {fmt!r}")
    return _json({"timestamp": timestamp(timestamp_ns), "frame_id": str(frame_id),
                  "data": base64.b64encode(bytes(data)).decode("ascii"), "format": fmt})


def camera_calibration(intrinsics: Intrinsics, timestamp_ns: int, frame_id: str) -> bytes:
    """A ``foxglove.CameraCalibration`` JSON message: pinhole K, no distortion, R = I, P = [K | 0]."""
    k = intrinsics
    fx, fy, cx, cy = float(k.fx), float(k.fy), float(k.cx), float(k.cy)
    return _json({
        "timestamp": timestamp(timestamp_ns), "frame_id": str(frame_id),
        "width": int(k.width), "height": int(k.height),
        "distortion_model": "plumb_bob", "D": [0.0] * 5,
        "K": [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0],
        "R": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        "P": [fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0],
    })


def pose_in_frame(matrix: np.ndarray, timestamp_ns: int, frame_id: str = "world") -> bytes:
    """A ``foxglove.PoseInFrame`` JSON message of a 4x4 pose (linear part projected to a rotation)."""
    position, orientation = _pose_parts(matrix)
    return _json({"timestamp": timestamp(timestamp_ns), "frame_id": str(frame_id),
                  "pose": {"position": position, "orientation": orientation}})


def frame_transform(matrix: np.ndarray, timestamp_ns: int, parent_frame_id: str = "world",
                    child_frame_id: str = "camera") -> bytes:
    """A ``foxglove.FrameTransform`` JSON message: ``matrix`` maps child coordinates to parent ones."""
    translation, rotation = _pose_parts(matrix)
    return _json({"timestamp": timestamp(timestamp_ns), "parent_frame_id": str(parent_frame_id),
                  "child_frame_id": str(child_frame_id), "translation": translation, "rotation": rotation})


# --- images straight from wire messages -----------------------------------------------------------

class WireImage(NamedTuple):
    """The compressed image of a ``frame``/``stabilized`` message and its envelope."""

    data: bytes
    format: str  # "jpeg"
    timestamp_ns: int
    stream: str
    seq: int


_IMAGE_FIELD = {"frame": "color", "stabilized": "image"}


def image_from_message(data: bytes, quality: int = 90) -> WireImage:
    """The JPEG of a ``frame`` or ``stabilized`` wire message, without decoding it.

    A ``jpeg`` image's bytes are returned as they are; a ``raw`` image is encoded to
    JPEG (``quality``) with OpenCV. Raises :class:`~quick_stream.stream.wire.WireError` for
    other message types or malformed fields.
    """
    r = unpack(data)
    name = _IMAGE_FIELD.get(r.type)
    if name is None:
        raise r.error("type", f"no image in a {r.type!r} message (expected 'frame' or 'stabilized')")
    t_ns = r.int("t_ns")
    img = r.map(name)
    enc = img.str("enc")
    if enc == "jpeg":
        jpeg = img.bytes("data")
    elif enc == "raw":
        pixels = r.array(name, "|u1", 3, (3,))
        ok, buf = cv2.imencode(".jpg", pixels, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
        if not ok:
            raise r.error(name, "JPEG encoding failed")
        jpeg = buf.tobytes()
    else:
        raise img.error("enc", f"unknown image encoding {enc!r} (expected 'jpeg' or 'raw')")
    return WireImage(jpeg, "jpeg", t_ns, r.stream, r.seq)


def compressed_image_from_message(data: bytes, frame_id: str, quality: int = 90) -> bytes:
    """A ``foxglove.CompressedImage`` JSON message of a ``frame``/``stabilized`` wire message."""
    img = image_from_message(data, quality)
    return compressed_image(img.timestamp_ns, img.data, img.format, frame_id)


__all__ = [
    "MSGPACK_STAGES", "SCHEMAS", "STREAM_CHANNELS", "TF_TOPIC", "WireImage", "camera_calibration",
    "compressed_image", "compressed_image_from_message", "frame_transform", "image_from_message",
    "nearest_rotation", "pose_in_frame", "quaternion_to_rotation", "register_channels",
    "rotation_to_quaternion", "schema_bytes", "timestamp", "topic",
]

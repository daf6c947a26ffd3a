"""Foxglove-viewable protobuf channels for MCAP recordings (beside the msgpack channels).

Foxglove cannot decode msgpack, so a recording also carries channels with the standard
Foxglove schemas, message encoding ``protobuf`` and schema encoding ``protobuf`` (the
schema record holds a serialized ``google.protobuf.FileDescriptorSet`` of the message and
every file it imports, as Foxglove and the ``mcap`` protobuf readers expect). Per stream
(docs/recording.md lists them with their sizes):

- ``/<stream>/color``: ``foxglove.CompressedImage`` of the input colour (the frame's JPEG);
- ``/<stream>/stabilized``: ``foxglove.CompressedImage`` of the stabilized output;
- ``/<stream>/calibration``: ``foxglove.CameraCalibration`` (pinhole, no distortion);
- ``/<stream>/camera_pose``, ``/<stream>/stabilized_pose``: ``foxglove.PoseInFrame`` in ``world``;
- ``/<stream>/tf``: ``foxglove.FrameTransform`` from ``world`` to the camera frame ``<stream>``
  (the camera pose) and to ``<stream>_stabilized`` (the stabilized virtual camera), so the 3D
  panel places the images and calibration.

Images are the JPEG bytes themselves (a protobuf ``bytes`` field; the JSON encoding needed
base64, a third more). The schemas come from the ``foxglove-schemas-protobuf`` package
(docs/dependencies.md, "Runtime"). The exact-replay channels stay msgpack (topic = the zenoh key).

Poses are 4x4 matrices. Motions of the larger groups (SIM3, SA3, GA3) have a
linear part that is not a rotation; :func:`nearest_rotation` projects it onto the
closest rotation (SVD, polar decomposition) and the scale/shear is dropped, since a
Foxglove pose has only a position and a unit quaternion.
"""
from __future__ import annotations

from functools import lru_cache
from typing import Any, NamedTuple, Protocol

import cv2
import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from google.protobuf.descriptor import FileDescriptor
from google.protobuf.descriptor_pb2 import FileDescriptorSet
from google.protobuf.message import DecodeError, Message

from ..core.frame import Intrinsics
from ..core.lie import so3
from ..stream.keys import key
from ..stream.wire.codec import unpack
from .sources.trajectory import matrix_to_quat, quat_to_matrix

MESSAGE_ENCODING = "protobuf"
SCHEMA_ENCODING = "protobuf"

# schema name -> generated message class
MESSAGES: dict[str, type[Message]] = {
    cls.DESCRIPTOR.full_name: cls for cls in (CompressedImage, CameraCalibration, PoseInFrame, FrameTransform)
}

# topic suffix -> schema name of the per-stream channels
STREAM_CHANNELS: dict[str, str] = {
    "color": "foxglove.CompressedImage",
    "stabilized": "foxglove.CompressedImage",
    "calibration": "foxglove.CameraCalibration",
    "camera_pose": "foxglove.PoseInFrame",
    "stabilized_pose": "foxglove.PoseInFrame",
    "tf": "foxglove.FrameTransform",
}
MSGPACK_STAGES = ("frame", "flow", "motion", "correction", "stabilized", "stats")


def topic(stream: str, channel: str) -> str:
    """The Foxglove topic of a stream's channel, e.g. ``topic("cam0", "color") == "/cam0/color"``."""
    if channel not in STREAM_CHANNELS:
        raise ValueError(f"Foxglove channel must be one of {tuple(STREAM_CHANNELS)}, got {channel!r}")
    key(stream, "frame")  # validates the stream id
    return f"/{stream}/{channel}"


def camera_frame(stream: str, stabilized: bool = False) -> str:
    """The frame id of a stream's camera (``cam0``) or of its stabilized virtual camera (``cam0_stabilized``)."""
    return f"{stream}_stabilized" if stabilized else stream


@lru_cache(maxsize=None)
def schema_bytes(name: str) -> bytes:
    """The serialized ``FileDescriptorSet`` of schema ``name`` (its file after every file it imports)."""
    if name not in MESSAGES:
        raise ValueError(f"no Foxglove schema {name!r} here (known: {', '.join(MESSAGES)})")
    fds = FileDescriptorSet()
    done: set[str] = set()

    def add(f: FileDescriptor) -> None:
        for dep in f.dependencies:
            if dep.name not in done:
                add(dep)
        if f.name not in done:
            done.add(f.name)
            f.CopyToProto(fds.file.add())

    add(MESSAGES[name].DESCRIPTOR.file)
    return fds.SerializeToString(deterministic=True)


class ChannelRegistry(Protocol):
    """What :func:`register_channels` needs of a recorder (:class:`~quick_stream.io.recording.Recorder`)."""

    def channel(self, topic: str, encoding: str = "msgpack", schema_name: str = "", schema: bytes = b"",
                schema_encoding: str = "", metadata: dict[str, str] | None = None) -> int: ...


def register_channels(recorder: ChannelRegistry, stream: str,
                      msgpack_stages: tuple[str, ...] = MSGPACK_STAGES) -> dict[str, str]:
    """Register a stream's Foxglove protobuf channels and its msgpack channels.

    Returns {name: topic} with names ``color``, ``stabilized``, ... , ``tf`` and, for the
    msgpack channels, ``msgpack:<stage>`` (topic = the zenoh key expression).
    """
    topics: dict[str, str] = {}
    for stage in msgpack_stages:
        # the stages whose JPEGs the recorder stores once, in the Foxglove image record (recording_images)
        image = {"frame": "color", "stabilized": "stabilized"}.get(stage)
        recorder.channel(key(stream, stage), encoding="msgpack",
                         metadata={"image_topic": topic(stream, image)} if image else None)
        topics[f"msgpack:{stage}"] = key(stream, stage)
    for name, schema in STREAM_CHANNELS.items():
        t = topic(stream, name)
        recorder.channel(t, encoding=MESSAGE_ENCODING, schema_name=schema, schema=schema_bytes(schema),
                         schema_encoding=SCHEMA_ENCODING)
        topics[name] = t
    return topics


# --- rotations ----------------------------------------------------------------------------------

def nearest_rotation(m: np.ndarray) -> np.ndarray:
    """The rotation matrix closest (Frobenius) to the 3x3 linear part ``m``
    (:func:`quick_stream.core.lie.so3.nearest_rotation`): for ``s R`` (SIM3) exactly ``R``, for an
    affine part (SA3/GA3) scale and shear dropped, never a reflection. ValueError for a matrix with
    non-finite values or a singular one, which has no rotation to take.
    """
    m = np.asarray(m, dtype=np.float64)[:3, :3]
    if not np.all(np.isfinite(m)):
        raise ValueError(f"matrix has non-finite values: {m.tolist()}")
    U, s, Vt = np.linalg.svd(m)  # one decomposition: the check's and the projection's (so3's, below)
    if s[0] <= 0 or s[-1] <= 1e-12 * s[0]:
        raise ValueError(f"matrix is singular (singular values {s.tolist()}); no rotation to take")
    return so3.polar_rotation(U, Vt)


def rotation_to_quaternion(m: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(x, y, z, w)``, ``w >= 0``, of the rotation nearest ``m``."""
    return matrix_to_quat(nearest_rotation(m))


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """3x3 rotation matrix of the quaternion ``(x, y, z, w)`` (normalised first)."""
    return quat_to_matrix(q)


# --- messages -----------------------------------------------------------------------------------

def _stamp(msg: Any, timestamp_ns: int) -> None:
    t = int(timestamp_ns)
    if t < 0:
        raise ValueError(f"Foxglove timestamps must be >= 0 ns, got {t}")
    msg.timestamp.seconds, msg.timestamp.nanos = divmod(t, 1_000_000_000)


def _pose_parts(matrix: np.ndarray) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"pose must be a 4x4 matrix, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise ValueError("pose has non-finite values")
    return _parts(np.ascontiguousarray(m).tobytes())


@lru_cache(maxsize=8)
def _parts(matrix: bytes) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
    """:func:`_pose_parts` of a checked 4x4 float64 matrix's bytes, kept for the last few: a pose goes
    out as a ``PoseInFrame`` and as a ``FrameTransform`` (two SVDs and a quaternion, ~0.1 ms, once)."""
    m = np.frombuffer(matrix).reshape(4, 4)
    q = rotation_to_quaternion(m[:3, :3])
    t = m[:3, 3]
    return (float(t[0]), float(t[1]), float(t[2])), (float(q[0]), float(q[1]), float(q[2]), float(q[3]))


def compressed_image(timestamp_ns: int, data: bytes, fmt: str, frame_id: str) -> bytes:
    """A ``foxglove.CompressedImage`` message of already-compressed ``jpeg``/``png`` bytes (kept as they are)."""
    if fmt not in ("jpeg", "png"):
        raise ValueError(f"image format must be 'jpeg' or 'png', got {fmt!r}")
    msg = CompressedImage(frame_id=str(frame_id), data=bytes(data), format=fmt)
    _stamp(msg, timestamp_ns)
    return msg.SerializeToString()


def camera_calibration(intrinsics: Intrinsics, timestamp_ns: int, frame_id: str) -> bytes:
    """A ``foxglove.CameraCalibration`` message: pinhole K, no distortion, R = I, P = [K | 0]."""
    k = intrinsics
    fx, fy, cx, cy = float(k.fx), float(k.fy), float(k.cx), float(k.cy)
    msg = CameraCalibration(
        frame_id=str(frame_id), width=int(k.width), height=int(k.height), distortion_model="plumb_bob",
        D=[0.0] * 5, K=[fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0], R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        P=[fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0])
    _stamp(msg, timestamp_ns)
    return msg.SerializeToString()


def pose_in_frame(matrix: np.ndarray, timestamp_ns: int, frame_id: str = "world") -> bytes:
    """A ``foxglove.PoseInFrame`` message of a 4x4 pose (linear part projected to a rotation)."""
    (tx, ty, tz), (qx, qy, qz, qw) = _pose_parts(matrix)
    msg = PoseInFrame(frame_id=str(frame_id))
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = tx, ty, tz
    o = msg.pose.orientation
    o.x, o.y, o.z, o.w = qx, qy, qz, qw
    _stamp(msg, timestamp_ns)
    return msg.SerializeToString()


def frame_transform(matrix: np.ndarray, timestamp_ns: int, parent_frame_id: str = "world",
                    child_frame_id: str = "camera") -> bytes:
    """A ``foxglove.FrameTransform`` message: ``matrix`` maps child coordinates to parent ones
    (the child frame's pose in the parent frame)."""
    (tx, ty, tz), (qx, qy, qz, qw) = _pose_parts(matrix)
    msg = FrameTransform(parent_frame_id=str(parent_frame_id), child_frame_id=str(child_frame_id))
    msg.translation.x, msg.translation.y, msg.translation.z = tx, ty, tz
    msg.rotation.x, msg.rotation.y, msg.rotation.z, msg.rotation.w = qx, qy, qz, qw
    _stamp(msg, timestamp_ns)
    return msg.SerializeToString()


def parse(schema_name: str, data: bytes) -> Message:
    """A recorded Foxglove message decoded with its generated class; ``ValueError`` if it does not parse."""
    cls = MESSAGES.get(schema_name)
    if cls is None:
        raise ValueError(f"no Foxglove schema {schema_name!r} here (known: {', '.join(MESSAGES)})")
    try:
        return cls.FromString(bytes(data))
    except DecodeError as e:
        raise ValueError(f"not a {schema_name} protobuf message: {e}") from None


# --- images straight from wire messages -----------------------------------------------------------

class WireImage(NamedTuple):
    """The compressed image of a ``frame``/``stabilized`` message and its envelope."""

    data: bytes
    format: str  # "jpeg"
    timestamp_ns: int
    stream: str
    seq: int


IMAGE_FIELD = {"frame": "color", "stabilized": "image"}


def image_from_message(data: bytes, quality: int = 90) -> WireImage:
    """The JPEG of a ``frame`` or ``stabilized`` wire message, without decoding it.

    A ``jpeg`` image's bytes are returned as they are; a ``raw`` image is encoded to
    JPEG (``quality``) with OpenCV. ``timestamp_ns`` is the message's ``t_ns`` (capture
    time). Raises :class:`~quick_stream.stream.wire.WireError` for other message types or
    malformed fields.
    """
    r = unpack(data)
    name = IMAGE_FIELD.get(r.type)
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


def compressed_image_from_message(data: bytes, frame_id: str, quality: int = 90,
                                  timestamp_ns: int | None = None) -> bytes:
    """A ``foxglove.CompressedImage`` message of a ``frame``/``stabilized`` wire message, stamped
    ``timestamp_ns`` (default: the message's capture time ``t_ns``)."""
    img = image_from_message(data, quality)
    return compressed_image(img.timestamp_ns if timestamp_ns is None else timestamp_ns, img.data, img.format,
                            frame_id)


__all__ = [
    "IMAGE_FIELD", "MESSAGES", "MESSAGE_ENCODING", "MSGPACK_STAGES", "SCHEMA_ENCODING", "STREAM_CHANNELS", "WireImage",
    "camera_calibration", "camera_frame", "compressed_image", "compressed_image_from_message", "frame_transform",
    "image_from_message", "nearest_rotation", "parse", "pose_in_frame", "quaternion_to_rotation",
    "register_channels", "rotation_to_quaternion", "schema_bytes", "topic",
]

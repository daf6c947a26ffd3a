"""The Foxglove-viewable side of a recording, derived from the wire messages as they are logged.

For each stream: input and stabilized images (``foxglove.CompressedImage``, the
JPEG bytes reused without re-encoding), the calibration whenever it changes and
once a second (``foxglove.CameraCalibration``), the camera pose integrated from
the motions and the stabilized (virtual camera) pose, camera pose times the
frame's correction g_s (``foxglove.PoseInFrame`` in ``world``; docs/conventions.md).
Used by the ``recorder`` service and by anyone converting a recording.
"""
from __future__ import annotations

from collections import OrderedDict

import numpy as np

from ..stream.wire import decode
from ..stream.wire.codec import unpack
from ..stream.wire.messages import read_intrinsics
from . import foxglove

_KEEP = 512  # frames of timestamps/poses kept for matching motions and corrections


class FoxgloveView:
    """Turns one stream's wire messages into (topic, bytes) Foxglove messages.

    Messages of different stages reach a recorder by different routes, so a pose is
    emitted as soon as everything it needs (the frame's timestamp, the integrated
    camera pose, for the stabilized pose the correction) has arrived, in any order.
    """

    def __init__(self, stream: str) -> None:
        self.stream = stream
        self.topics = {name: foxglove.topic(stream, name) for name in foxglove.STREAM_CHANNELS}
        self._t_ns: OrderedDict[int, int] = OrderedDict()
        self._pose: OrderedDict[int, np.ndarray] = OrderedDict()
        self._corr: OrderedDict[int, np.ndarray] = OrderedDict()
        self._sent: OrderedDict[int, set] = OrderedDict()
        self._calib: tuple | None = None
        self._calib_t = -(1 << 62)

    @staticmethod
    def _remember(d: OrderedDict, k: int, v) -> None:
        d[k] = v
        while len(d) > _KEEP:
            d.popitem(last=False)

    def _poses(self, seq: int) -> list[tuple[str, bytes]]:
        """The pose messages of frame ``seq`` that have become complete and were not sent yet."""
        t, pose = self._t_ns.get(seq), self._pose.get(seq)
        if t is None or pose is None:
            return []
        sent = self._sent.get(seq)
        if sent is None:
            sent = set()
            self._remember(self._sent, seq, sent)
        out = []
        if "camera" not in sent:
            sent.add("camera")
            out.append((self.topics["camera_pose"], foxglove.pose_in_frame(pose, t)))
        corr = self._corr.get(seq)
        if corr is not None and "stabilized" not in sent:
            sent.add("stabilized")
            out.append((self.topics["stabilized_pose"], foxglove.pose_in_frame(pose @ corr, t)))
        return out

    def convert(self, stage: str, payload: bytes) -> list[tuple[str, bytes]]:
        """Foxglove messages for one wire message of ``stage`` (none for stages without a view).

        Raises :class:`~quick_stream.stream.wire.WireError` for a message that does not decode."""
        if stage == "frame":
            r = unpack(payload)
            if r.type != "frame":
                return []
            out = [(self.topics["color"], foxglove.compressed_image_from_message(payload, self.stream))]
            t_ns = r.int("t_ns")
            self._remember(self._t_ns, r.seq, t_ns)
            k = read_intrinsics(r, "intrinsics")
            key = (k.fx, k.fy, k.cx, k.cy, k.width, k.height)
            if key != self._calib or t_ns - self._calib_t >= 1_000_000_000:
                self._calib, self._calib_t = key, t_ns
                out.append((self.topics["calibration"], foxglove.camera_calibration(k, t_ns, self.stream)))
            return out + self._poses(r.seq)
        if stage == "stabilized":
            r = unpack(payload)
            if r.type != "stabilized":
                return []
            return [(self.topics["stabilized"],
                     foxglove.compressed_image_from_message(payload, f"{self.stream}_stabilized"))]
        if stage == "motion":
            m = decode(payload)
            if m.type != "motion":
                return []
            mo = m.obj
            if not self._pose:
                self._remember(self._pose, mo.seq, np.eye(4))
            prev = self._pose.get(mo.seq)
            if prev is None:  # the path has a hole: restart it here
                prev = np.eye(4)
                self._remember(self._pose, mo.seq, prev)
            self._remember(self._pose, mo.seq_next, prev @ mo.matrix)
            return self._poses(mo.seq) + self._poses(mo.seq_next)
        if stage == "correction":
            c = decode(payload)
            if c.type != "correction":
                return []
            self._remember(self._corr, c.seq, c.obj.matrix)
            return self._poses(c.seq)
        return []


__all__ = ["FoxgloveView"]

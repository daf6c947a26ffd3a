"""The Foxglove-viewable side of a recording, derived from the wire messages as they are logged.

For each stream: the calibration whenever it changes and once a second
(``foxglove.CameraCalibration``), the camera pose integrated from the motions and the
stabilized (virtual camera) pose, camera pose times the frame's correction g_s
(``foxglove.PoseInFrame`` in ``world``; docs/conventions.md), the same two poses as
``foxglove.FrameTransform`` from ``world`` to the frames ``<stream>`` and
``<stream>_stabilized`` (so the 3D panel places the camera), and the images of messages
whose image is not a JPEG (raw colour, encoded here). JPEG images are written by the
recorder itself as each message arrives, stored once (:mod:`quick_stream.io.recording_images`).

**Clock**: every Foxglove ``timestamp`` is wall clock, the clock of the recording's log
times: a frame's ``pub_ns`` (when the capture published it; for a stabilized image its
``src_pub_ns``), else the log time of its message. The capture time ``t_ns`` (a device's
or source's own clock, from 0 for the synthetic source) stays in the wire messages
(docs/recording.md, "Timestamps").
Used by the ``recorder`` service and by anyone converting a recording.
"""
from __future__ import annotations

from collections import OrderedDict

import numpy as np

from ..stream.wire.codec import unpack
from ..stream.wire.estimates import matrix_field, motion_transform
from ..stream.wire.fields import read_intrinsics
from ..stream.wire.ranges import MAX_ENTRY
from . import foxglove

_KEEP = 512  # frames of timestamps/poses kept for matching motions and corrections
MAX_POSE_ENTRY = MAX_ENTRY  # an integrated pose with an entry beyond this is not kept (the chain restarts)


def wall_stamp(value: object, log_time_ns: int | None, fallback: int) -> int:
    """``value`` (a message's ``pub_ns``) when it is a time, else the log time, else ``fallback``."""
    if isinstance(value, int) and not isinstance(value, bool) and value >= 0:
        return value
    return int(log_time_ns) if log_time_ns is not None else max(int(fallback), 0)


class FoxgloveView:
    """Turns one stream's wire messages into (topic, bytes) Foxglove messages.

    Messages of different stages reach a recorder by different routes, so a pose is
    emitted as soon as everything it needs (the frame's timestamp, the integrated
    camera pose, for the stabilized pose the correction) has arrived, in any order.

    What one message leaves behind never spoils the next: the wire's ranges are checked at decode
    (a motion of 1e308 is refused there), a pair's motion is integrated once (a replay or a copy
    arriving later rewrites nothing) and a pose that leaves the range is not kept, so the chain
    restarts at the next motion as at a hole. A message whose view fails raises; the caller skips
    its view and goes on (the recorder counts it, ``view_errors``).
    """

    def __init__(self, stream: str) -> None:
        self.stream = stream
        self.topics = {name: foxglove.topic(stream, name) for name in foxglove.STREAM_CHANNELS}
        self.frames = {"camera": foxglove.camera_frame(stream), "stabilized": foxglove.camera_frame(stream, True)}
        self._t_ns: OrderedDict[int, int] = OrderedDict()  # seq -> the frame's Foxglove timestamp (wall clock)
        self._pose: OrderedDict[int, np.ndarray] = OrderedDict()
        self._corr: OrderedDict[int, np.ndarray] = OrderedDict()
        self._sent: OrderedDict[int, set] = OrderedDict()
        self._integrated: OrderedDict[tuple[int, int], bool] = OrderedDict()  # motions (seq, seq_next) taken
        self.chain_restarts = 0  # poses not kept because the chain left MAX_POSE_ENTRY
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
            out.append((self.topics["tf"], foxglove.frame_transform(pose, t, "world", self.frames["camera"])))
        corr = self._corr.get(seq)
        if corr is not None and "stabilized" not in sent:
            sent.add("stabilized")
            virtual = pose @ corr
            out.append((self.topics["stabilized_pose"], foxglove.pose_in_frame(virtual, t)))
            out.append((self.topics["tf"], foxglove.frame_transform(virtual, t, "world", self.frames["stabilized"])))
        return out

    def convert(self, stage: str, payload: bytes, log_time_ns: int | None = None,
                jpeg: bool = True) -> list[tuple[str, bytes]]:
        """Foxglove messages for one wire message of ``stage`` (none for stages without a view).

        ``log_time_ns``: the message's log time (the timestamp of a frame without ``pub_ns``).
        ``jpeg``: also the image of a ``frame``/``stabilized`` message whose image is a JPEG already
        (the recorder passes False: it writes those itself as they arrive, stored once); raw images
        are always encoded to JPEG here. Raises
        :class:`~quick_stream.stream.wire.WireError` for a message that does not decode."""
        if stage == "frame":
            r = unpack(payload)
            if r.type != "frame":
                return []
            stamp = wall_stamp(r.d.get("pub_ns"), log_time_ns, r.int("t_ns"))
            out = []
            if jpeg or r.map("color").str("enc") != "jpeg":
                out.append((self.topics["color"], foxglove.compressed_image_from_message(
                    payload, self.frames["camera"], timestamp_ns=stamp)))
            self._remember(self._t_ns, r.seq, stamp)
            k = read_intrinsics(r, "intrinsics")
            key = (k.fx, k.fy, k.cx, k.cy, k.width, k.height)
            if key != self._calib or stamp - self._calib_t >= 1_000_000_000:
                self._calib, self._calib_t = key, stamp
                out.append((self.topics["calibration"], foxglove.camera_calibration(k, stamp, self.frames["camera"])))
            return out + self._poses(r.seq)
        if stage == "stabilized":
            r = unpack(payload)
            if r.type != "stabilized" or (not jpeg and r.map("image").str("enc") == "jpeg"):
                return []
            fallback = self._t_ns.get(r.seq, log_time_ns)
            stamp = wall_stamp(r.d.get("src_pub_ns"), fallback, r.int("t_ns"))
            return [(self.topics["stabilized"], foxglove.compressed_image_from_message(
                payload, self.frames["stabilized"], timestamp_ns=stamp))]
        # motions and corrections: only the fields a pose needs, each checked as decode checks it (the
        # rest was checked on arrival; decoding the whole message again cost a recorder ~0.4 ms a message)
        if stage == "motion":
            r = unpack(payload)
            if r.type != "motion":
                return []
            seq, (seq_next, matrix) = r.seq, motion_transform(r)
            if not self._pose:
                self._remember(self._pose, seq, np.eye(4))
            prev = self._pose.get(seq)
            if prev is None:  # the path has a hole: restart it here
                prev = np.eye(4)
                self._remember(self._pose, seq, prev)
            if (seq, seq_next) not in self._integrated:  # a pair's first motion: a replay or a late
                self._remember(self._integrated, (seq, seq_next), True)  # copy rewrites no pose
                pose = prev @ matrix
                if np.all(np.isfinite(pose)) and np.max(np.abs(pose)) <= MAX_POSE_ENTRY:
                    self._remember(self._pose, seq_next, pose)
                else:  # out of range (a chain that grew too far): not kept, the next motion restarts the chain
                    self.chain_restarts += 1
            return self._poses(seq) + self._poses(seq_next)
        if stage == "correction":
            r = unpack(payload)
            if r.type != "correction":
                return []
            self._remember(self._corr, r.seq, matrix_field(r))
            return self._poses(r.seq)
        return []


__all__ = ["FoxgloveView", "wall_stamp"]

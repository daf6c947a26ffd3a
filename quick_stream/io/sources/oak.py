"""Luxonis OAK (depthai) cameras as a frame source: the device-independent part.

Spec: ``depthai`` or ``depthai:DEVICE_ID`` with options ``width``, ``height``, ``fps``
(default 640x400 at 30, native on OAK-D / OAK-D Pro; 640x480 on OAK-D Lite),
``tolerance_ms`` (colour/depth pairing by timestamp), ``retries`` (reconnection
attempts), the stereo settings of :class:`StereoSettings` (``preset``, ``subpixel``,
``lr_check``, ``confidence``, ``median``, ``spatial``, ``temporal``, ``speckle``, ``extended``;
defaults chosen from the measured depth noise the stabilizer tolerates), and ``fake=1`` for the
scripted stand-in device of :mod:`~quick_stream.io.sources.stand_in.oak_fake` (tests and demos without
hardware, in a source checkout only; it has no stereo matcher, so it ignores the stereo settings).

Everything that talks to depthai sits behind :class:`CameraBackend`: ``open()``,
``read(timeout)`` returning the colour and depth messages that arrived (objects
with depthai's ``ImgFrame`` API: ``getCvFrame``, ``getTransformation().
getIntrinsicMatrix()``, ``getTimestamp``, ``getTimestampDevice``,
``getSequenceNum``), ``close()``; it raises :class:`DeviceGone` when the device
drops. The real backend is :mod:`~quick_stream.io.sources.oak_device` (depthai v3).

This module turns messages into frames:

* **pairing** (:class:`FramePairer`): colour and depth (already aligned to the
  colour output on the device) by equal device sequence number, else by device
  timestamp within ``tolerance_ms``; a message whose partner never comes is
  dropped and counted, so one lost message costs one frame, never the stream. The
  real device pairs them itself (a ``Sync`` node, :mod:`~quick_stream.io.sources.oak_device`)
  and hands over one pair per read; the pairer then only confirms it;
* **conversion** (:func:`to_rgbd`): BGR colour, depth uint16 millimetres to float32
  metres (0 = invalid), intrinsics from *each* frame's own transformation (the
  calibration's are wrong after the device resized or cropped the image),
  device/host timestamps and device sequence numbers in ``RGBDFrame.capture``;
* **reconnection** (:class:`OakSource`): when the device drops, bounded retries
  with back-off, logged; the stream goes on with a :class:`~quick_stream.core.frame.BadFrame`
  marking the gap, and sequence numbers stay increasing across connections.
"""
from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Iterator

import numpy as np

from ...core.frame import BadFrame, FrameError, Intrinsics, RGBDFrame
from .base import SourceError
from .oak_options import CameraBackend, DeviceGone, NoDevice, oak_settings

log = logging.getLogger("quick_stream.io.sources.oak")

DEPTH_SCALE = 1000.0  # device depth is uint16 millimetres


def _ns(td: Any) -> int:
    """A depthai timestamp (datetime.timedelta) in integer nanoseconds."""
    return int(round(td.total_seconds() * 1e9))


def intrinsics_of(msg: Any) -> Intrinsics:
    """Intrinsics of an ImgFrame from its own transformation (after any on-device resize/crop)."""
    K = np.asarray(msg.getTransformation().getIntrinsicMatrix(), dtype=np.float64)
    if K.shape != (3, 3):
        raise FrameError(f"intrinsic matrix must be 3x3, got shape {K.shape}")
    img = msg.getCvFrame()
    h, w = img.shape[:2]
    return Intrinsics(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), int(w), int(h))


def to_rgbd(color_msg: Any, depth_msg: Any, seq: int, device_id: str, connection: int = 0) -> RGBDFrame:
    """One RGBDFrame from a colour and an aligned depth ImgFrame; FrameError names what is wrong."""
    color = color_msg.getCvFrame()
    depth_raw = depth_msg.getCvFrame()
    origin = f"depthai {device_id} colour #{color_msg.getSequenceNum()}"
    if not isinstance(color, np.ndarray) or color.dtype != np.uint8:
        raise FrameError(f"{origin}: colour must be uint8, got {getattr(color, 'dtype', type(color))}")
    if color.ndim == 2:
        import cv2

        color = cv2.cvtColor(color, cv2.COLOR_GRAY2BGR)
    if not isinstance(depth_raw, np.ndarray) or depth_raw.dtype != np.uint16 or depth_raw.ndim != 2:
        raise FrameError(f"{origin}: depth must be HxW uint16 millimetres, got "
                         f"{getattr(depth_raw, 'shape', '?')} {getattr(depth_raw, 'dtype', type(depth_raw))}")
    if depth_raw.shape != color.shape[:2]:
        raise FrameError(f"{origin}: depth {depth_raw.shape[1]}x{depth_raw.shape[0]} is not aligned to colour "
                         f"{color.shape[1]}x{color.shape[0]} (link the colour output to stereo.inputAlignTo)")
    k = intrinsics_of(color_msg)
    depth = depth_raw.astype(np.float32) / np.float32(DEPTH_SCALE)
    t_dev, t_host = _ns(color_msg.getTimestampDevice()), _ns(color_msg.getTimestamp())
    capture = {"device_id": device_id, "t_device_ns": t_dev, "t_host_ns": t_host,
               "seq_color": int(color_msg.getSequenceNum()), "seq_depth": int(depth_msg.getSequenceNum()),
               "depth_skew_ns": _ns(depth_msg.getTimestampDevice()) - t_dev, "connection": connection}
    return RGBDFrame(np.ascontiguousarray(color), depth, k, t_host, seq, None, origin, capture=capture).validate()


@dataclass
class PairStats:
    paired_by_seq: int = 0
    paired_by_time: int = 0
    unpaired_color: int = 0
    unpaired_depth: int = 0


class FramePairer:
    """Pairs colour and depth messages: equal sequence number first, else device time within tolerance.

    Messages wait at most ``max_wait`` of their kind; older ones are given up (counted).
    Pairs come out in colour order.
    """

    def __init__(self, tolerance_ms: float = 10.0, max_wait: int = 8) -> None:
        self.tolerance_ns = int(tolerance_ms * 1e6)
        self.max_wait = max_wait
        self._color: deque[Any] = deque()
        self._depth: deque[Any] = deque()
        self.stats = PairStats()

    def reset(self) -> None:
        """Forget everything waiting (after a reconnect: device sequence numbers restart)."""
        self.stats.unpaired_color += len(self._color)
        self.stats.unpaired_depth += len(self._depth)
        self._color.clear()
        self._depth.clear()

    def add(self, colors: list[Any], depths: list[Any]) -> list[tuple[Any, Any]]:
        self._color.extend(colors)
        self._depth.extend(depths)
        out = []
        while self._color:
            c = self._color[0]
            d = self._match(c)
            if d is None:
                if len(self._color) > self.max_wait or self._depth_is_past(c):
                    self._color.popleft()
                    self.stats.unpaired_color += 1
                    continue
                break
            self._color.popleft()
            out.append((c, d))
        while len(self._depth) > self.max_wait:
            self._depth.popleft()
            self.stats.unpaired_depth += 1
        return out

    def _match(self, c: Any) -> Any | None:
        seq, t = c.getSequenceNum(), _ns(c.getTimestampDevice())
        best, best_dt = None, None
        for d in self._depth:
            if d.getSequenceNum() == seq:
                best, best_dt = d, -1
                break
            dt = abs(_ns(d.getTimestampDevice()) - t)
            if dt <= self.tolerance_ns and (best_dt is None or dt < best_dt):
                best, best_dt = d, dt
        if best is None:
            return None
        # take the match, and drop depth messages clearly older than it (their colour is gone)
        t_best = _ns(best.getTimestampDevice())
        keep = deque(d for d in self._depth
                     if d is not best and _ns(d.getTimestampDevice()) >= t_best - self.tolerance_ns)
        self.stats.unpaired_depth += len(self._depth) - 1 - len(keep)
        self._depth = keep
        if best_dt == -1:
            self.stats.paired_by_seq += 1
        else:
            self.stats.paired_by_time += 1
        return best

    def _depth_is_past(self, c: Any) -> bool:
        """A depth message newer than this colour's time + tolerance exists: its partner is lost."""
        t = _ns(c.getTimestampDevice())
        return any(_ns(d.getTimestampDevice()) > t + self.tolerance_ns for d in self._depth)


class OakSource:
    """Frames from an OAK camera through a :class:`CameraBackend` (see the module doc)."""

    name = "depthai"
    has_ground_truth = False
    depth_scale = DEPTH_SCALE

    def __init__(self, backend: CameraBackend, width: int = 640, height: int = 400, fps: float = 30.0,
                 tolerance_ms: float = 10.0, retries: int = 5, retry_delay_s: float = 0.5,
                 read_timeout_s: float = 2.0, frames: int | None = None) -> None:
        self.backend = backend
        self.fps = float(fps)
        self.frames = frames
        self.intrinsics = Intrinsics(width * 0.9, width * 0.9, (width - 1) / 2, (height - 1) / 2, width, height)
        self.pairer = FramePairer(tolerance_ms)
        self.retries, self.retry_delay_s, self.read_timeout_s = retries, retry_delay_s, read_timeout_s
        self.connections = 0
        self.reconnects: list[dict[str, Any]] = []
        self.stop: threading.Event | None = None  # set (e.g. on SIGTERM): retrying gives up at once
        self.backend_open = False  # opened by open(), not yet iterated

    def open(self) -> None:
        """Open the device now (retrying as configured), so a camera that is not there fails before
        the stream starts (raises :class:`NoDevice`); iterating then uses this connection."""
        if not self.backend_open:
            self._connect()
            self.backend_open = True

    def __len__(self) -> int:
        return self.frames if self.frames is not None else 1 << 62

    def _connect(self) -> None:
        """Open the device, retrying with back-off up to ``retries`` times; raises the last error."""
        delay, last = self.retry_delay_s, None
        for attempt in range(self.retries + 1):
            try:
                self.backend.open()
                self.connections += 1
                return
            except (DeviceGone, NoDevice, OSError, RuntimeError) as e:
                last = e
                log.warning("depthai %s: open failed (attempt %d of %d): %s", self.backend.device_id,
                            attempt + 1, self.retries + 1, e)
                if attempt < self.retries:
                    if self.stop is not None and self.stop.wait(delay):
                        raise NoDevice(f"depthai {self.backend.device_id}: stopped while retrying ({e})") from None
                    if self.stop is None:
                        time.sleep(delay)
                    delay = min(delay * 2, 5.0)
        raise NoDevice(f"depthai {self.backend.device_id}: could not open after {self.retries + 1} attempts: {last}")

    def __iter__(self) -> Iterator[RGBDFrame | BadFrame]:
        seq, last_t = 0, 0
        if not self.backend_open:
            self._connect()
        self.backend_open = False  # the next iteration connects again (this one closes it at its end)
        try:
            while self.frames is None or seq < self.frames:
                try:
                    colors, depths = self.backend.read(self.read_timeout_s)
                except DeviceGone as e:
                    t0 = time.monotonic()
                    log.error("depthai %s: device lost after frame %d: %s; reconnecting",
                              self.backend.device_id, seq - 1, e)
                    self.backend.close()
                    self.pairer.reset()
                    self._connect()  # raises NoDevice when the retries run out: the stream ends
                    gap_s = time.monotonic() - t0
                    self.reconnects.append({"after_seq": seq - 1, "seconds": round(gap_s, 3)})
                    yield BadFrame(seq, last_t + 1, f"depthai {self.backend.device_id}",
                                   f"device disconnected ({e}); reconnected after {gap_s:.2f} s, "
                                   "frames were lost")
                    seq += 1
                    continue
                for c, d in self.pairer.add(colors, depths):
                    try:
                        fr = to_rgbd(c, d, seq, self.backend.device_id, self.connections - 1)
                    except FrameError as e:
                        yield BadFrame(seq, last_t + 1, f"depthai {self.backend.device_id}", str(e))
                    else:
                        if fr.timestamp_ns <= last_t:  # host clock went backwards across a reconnect
                            fr.timestamp_ns = last_t + 1
                        last_t = fr.timestamp_ns
                        self.intrinsics = fr.intrinsics
                        yield fr
                    seq += 1
                    if self.frames is not None and seq >= self.frames:
                        return
        finally:
            self.backend.close()

    def __repr__(self) -> str:
        return f"OakSource({self.backend!r}, fps={self.fps:g})"


def open_oak(device: str, options: dict[str, str]) -> OakSource:
    """The source for spec ``depthai[:DEVICE][,key=value...]`` (see the module doc)."""
    o = oak_settings(options)
    w, h, fps = o["width"], o["height"], o["fps"]
    if options.get("fake"):
        try:
            from .stand_in.oak_fake import FakeOakBackend
        except ModuleNotFoundError:
            raise SourceError("depthai: fake= asks for the scripted stand-in camera, a test rig that comes with a "
                              "source checkout (pip install -e .), not with the installed product") from None

        backend: CameraBackend = FakeOakBackend.from_script(options["fake"], width=w, height=h, fps=fps,
                                                            device_id=device or "fake0")
    else:
        from .oak_device import DepthaiBackend

        backend = DepthaiBackend(device or None, w, h, fps, o["tolerance_ms"], stereo=o["stereo"])
    return OakSource(backend, w, h, fps, o["tolerance_ms"], o["retries"], frames=o["frames"])

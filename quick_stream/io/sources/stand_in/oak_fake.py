"""A scripted stand-in for an OAK camera: depthai's message API over synthetic frames.

No hardware here, so the device-specific path is exercised by this backend: it
renders the synthetic scene and hands out colour and depth messages with the
methods the adapter uses from depthai's ``ImgFrame`` (``getCvFrame``,
``getTransformation().getIntrinsicMatrix()``, ``getTimestamp``,
``getTimestampDevice``, ``getSequenceNum``).
Depth is uint16 millimetres aligned to colour, as the device sends it.

Faults are scripted by frame index: ``fake=EVENT:FRAME+EVENT:FRAME...`` in the
source spec (``fake=1``: none). Events:

* ``drop_color`` / ``drop_depth``: that message never arrives;
* ``mismatch``: the depth message carries another sequence number (paired by time);
* ``late_depth``: the depth message arrives one read later than its colour;
* ``intrinsics``: from this frame on the device crops, so fx, fy and cx, cy change;
* ``disconnect``: the device drops before this frame; the next ``open`` fails once,
  then the device comes back with its sequence numbers and clock restarted;
* ``absent`` (frame 0): no device is ever found (every ``open`` fails).
"""
from __future__ import annotations

import datetime
from dataclasses import dataclass
from typing import Any

import numpy as np

from ....core.frame import quantize_depth
from ..oak_options import DeviceGone, NoDevice
from ..synthetic import SyntheticSource

EVENTS = ("drop_color", "drop_depth", "mismatch", "late_depth", "intrinsics", "disconnect", "absent")


class FakeTransformation:
    def __init__(self, K: np.ndarray) -> None:
        self._K = K

    def getIntrinsicMatrix(self) -> list[list[float]]:  # noqa: N802 - depthai's name
        return self._K.tolist()


@dataclass(eq=False)
class FakeImgFrame:
    """The part of ``depthai.ImgFrame`` the adapter uses."""

    data: np.ndarray
    seq: int
    t_host_ns: int
    t_device_ns: int
    K: np.ndarray

    def getCvFrame(self) -> np.ndarray:  # noqa: N802
        return self.data

    def getTransformation(self) -> FakeTransformation:  # noqa: N802
        return FakeTransformation(self.K)

    def getTimestamp(self) -> datetime.timedelta:  # noqa: N802
        return datetime.timedelta(microseconds=self.t_host_ns / 1e3)

    def getTimestampDevice(self) -> datetime.timedelta:  # noqa: N802
        return datetime.timedelta(microseconds=self.t_device_ns / 1e3)

    def getSequenceNum(self) -> int:  # noqa: N802
        return self.seq


def parse_script(text: str) -> dict[int, set[str]]:
    """``EVENT:FRAME+EVENT:FRAME`` (or ``1``/``0``/empty: no events) -> {frame: {events}}."""
    out: dict[int, set[str]] = {}
    if text.strip() in ("", "0", "1", "true"):
        return out
    for item in text.split("+"):
        name, sep, frame = item.partition(":")
        if not sep or name not in EVENTS or not frame.isdigit():
            raise ValueError(f"fake depthai script item {item!r}: expected EVENT:FRAME with EVENT in {EVENTS}")
        out.setdefault(int(frame), set()).add(name)
    return out


class FakeOakBackend:
    """Synthetic frames as depthai messages, with scripted faults (see the module doc)."""

    def __init__(self, width: int = 640, height: int = 400, fps: float = 30.0, frames: int = 100_000,
                 script: dict[int, set[str]] | None = None, device_id: str = "fake0", seed: int = 0) -> None:
        self.device_id = device_id
        self.src = SyntheticSource(width=width, height=height, fps=fps, frames=frames, seed=seed)
        self.script = script or {}
        self.fps = fps
        self.i = 0  # next synthetic frame index
        self.is_open = False
        self._fail_opens = 0
        self._dev_seq0 = 0  # device sequence number restarts after a reconnect
        self._dev_t0 = 0
        self._late: list[Any] = []
        self._disconnected_at: set[int] = set()
        self.t_host0_ns = 1_700_000_000_000_000_000  # host clock (ns) at frame 0

    @classmethod
    def from_script(cls, text: str, **kw: Any) -> "FakeOakBackend":
        return cls(script=parse_script(text), **kw)

    def open(self) -> None:
        if "absent" in self.script.get(0, set()):
            raise NoDevice(f"{self.device_id}: no such device (scripted: absent)")
        if self._fail_opens > 0:
            self._fail_opens -= 1
            raise DeviceGone(f"{self.device_id}: device not ready yet")
        self.is_open = True

    def close(self) -> None:
        self.is_open = False

    def _K(self, i: int) -> np.ndarray:
        K = self.src.intrinsics_at(i).K.copy()
        if any("intrinsics" in ev for f, ev in self.script.items() if f <= i):
            K[0, 0] *= 1.1
            K[1, 1] *= 1.1
            K[0, 2] -= 3.0
            K[1, 2] += 2.0
        return K

    def read(self, timeout_s: float) -> tuple[list[Any], list[Any]]:
        if not self.is_open:
            raise DeviceGone(f"{self.device_id}: not open")
        i = self.i
        if i >= len(self.src):
            raise DeviceGone(f"{self.device_id}: end of the scripted recording")
        ev = self.script.get(i, set())
        if "disconnect" in ev and i not in self._disconnected_at:
            self._disconnected_at.add(i)
            self.is_open = False
            self._fail_opens = 1
            self._dev_seq0 = i + 2  # frames i and i+1 are lost while away; the device restarts at 0
            self._dev_t0 = int(round((i + 2) * 1e9 / self.fps))
            self._late.clear()
            self.i = i + 2
            raise DeviceGone(f"{self.device_id}: X_LINK_ERROR (scripted disconnect before frame {i})")
        self.i = i + 1
        f = self.src.frame(i)
        K = self._K(i)
        t_dev = int(round(i * 1e9 / self.fps)) - self._dev_t0 + 5_000_000
        t_host = self.t_host0_ns + int(round(i * 1e9 / self.fps))
        dseq = i - self._dev_seq0
        color = FakeImgFrame(f.color, dseq, t_host, t_dev, K)
        depth = FakeImgFrame(quantize_depth(f.depth, 1000.0), dseq + (1000 if "mismatch" in ev else 0),
                             t_host + 300_000, t_dev + 300_000, K)
        colors = [] if "drop_color" in ev else [color]
        depths, late, self._late = list(self._late), [], []
        if "drop_depth" not in ev:
            (late if "late_depth" in ev else depths).append(depth)
        self._late = late
        return colors, depths

    def __repr__(self) -> str:
        return f"FakeOakBackend({self.device_id}, {self.src.width}x{self.src.height}@{self.fps:g})"

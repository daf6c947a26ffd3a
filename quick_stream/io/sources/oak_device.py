"""The real OAK backend: a depthai v3 pipeline with colour and stereo depth aligned to it.

Needs the optional extra (``pip install 'quick-stream[depthai]'``); without it every
entry point raises an ImportError naming the extra. Pipeline (depthai v3):

    Camera CAM_A  --requestOutput((W, H), BGR888i, fps)--> colour queue
                  \\--> StereoDepth.inputAlignTo          (depth resampled to the colour view)
    Camera CAM_B/CAM_C --requestOutput--> StereoDepth.left/right --depth (uint16 mm)--> depth queue

Queues are non-blocking with a few messages each, so a slow host drops old frames
on the device side instead of stalling it. A device that stops delivering for
``read`` timeout, or raises from depthai, is reported as :class:`DeviceGone`.
"""
from __future__ import annotations

import logging
import time
from typing import Any

from .oak import DeviceGone, EXTRA_HINT, NoDevice

log = logging.getLogger("quick_stream.io.sources.oak_device")


def import_depthai() -> Any:
    """The depthai module, or ImportError naming the extra to install."""
    try:
        import depthai
    except ImportError as e:
        raise ImportError(f"the depthai source needs the depthai package (3.x): {EXTRA_HINT} ({e})") from None
    major = int(str(getattr(depthai, "__version__", "0")).split(".")[0] or 0)
    if major < 3:
        raise ImportError(f"depthai {depthai.__version__} is too old: the depthai source needs 3.x; {EXTRA_HINT}")
    return depthai


def list_devices() -> list[dict[str, str]]:
    """Connected OAK devices: id, name, state, platform (empty list when none)."""
    dai = import_depthai()
    out = []
    for info in dai.Device.getAllAvailableDevices():
        out.append({"id": info.getDeviceId(), "name": str(getattr(info, "name", "")),
                    "state": str(getattr(info, "state", "")).rsplit(".", 1)[-1],
                    "platform": str(getattr(info, "platform", "")).rsplit(".", 1)[-1]})
    return out


def print_devices() -> int:
    """``quick-stream-capture --list-devices``: one line per OAK device this host sees (id, name,
    state, platform); exit 1 when there is none, 2 without depthai."""
    try:
        found = list_devices()
    except ImportError as e:
        log.error("%s", e)
        return 2
    if not found:
        print("no OAK device found (check the USB cable, the udev rule, or Docker's /dev/bus/usb mapping)")
        return 1
    for d in found:
        print(f"{d['id']}  {d['name']}  {d['state']}  {d['platform']}")
    return 0


class PipelineBackend:
    """A started depthai pipeline with a colour and a depth output queue: ``open``/``read``/``close``.

    Subclasses say how the pipeline is built (:meth:`build`); reading is shared, so the
    device backend and a host-only pipeline (tests, replays) go through the same code."""

    device_id = "pipeline"

    def __init__(self) -> None:
        self.dai = import_depthai()
        self._pipeline = None
        self._qc = self._qd = None

    def build(self) -> tuple[Any, Any, Any]:
        """(pipeline, colour queue, depth queue), not started."""
        raise NotImplementedError

    def open(self) -> None:
        try:
            pipeline, qc, qd = self.build()
            pipeline.start()
        except (NoDevice, DeviceGone):
            raise
        except Exception as e:  # noqa: BLE001 - depthai raises RuntimeError subclasses of its own
            raise DeviceGone(f"cannot start the pipeline on {self.device_id}: {e}") from None
        self._pipeline, self._qc, self._qd = pipeline, qc, qd

    def read(self, timeout_s: float) -> tuple[list[Any], list[Any]]:
        """Whatever colour and depth messages have arrived (waits up to ``timeout_s`` for any)."""
        if self._pipeline is None:
            raise DeviceGone("not open")
        deadline = time.monotonic() + timeout_s
        try:
            while True:
                colors = self._qc.tryGetAll() or []
                depths = self._qd.tryGetAll() or []
                if colors or depths:
                    return list(colors), list(depths)
                if not self._pipeline.isRunning():
                    raise DeviceGone("pipeline stopped")
                if time.monotonic() > deadline:
                    raise DeviceGone(f"no frames for {timeout_s:g} s")
                time.sleep(0.002)
        except DeviceGone:
            raise
        except Exception as e:  # noqa: BLE001 - XLink errors surface as RuntimeError
            raise DeviceGone(str(e)) from None

    def close(self) -> None:
        p, self._pipeline, self._qc, self._qd = self._pipeline, None, None, None
        try:
            if p is not None:
                p.stop()
        except Exception:  # noqa: BLE001 - stopping a dead device may raise; nothing to do
            pass


class DepthaiBackend(PipelineBackend):
    """Colour + aligned stereo depth from one OAK device (``device_id`` None: the first found)."""

    def __init__(self, device_id: str | None, width: int = 640, height: int = 400, fps: float = 30.0,
                 queue_size: int = 4) -> None:
        super().__init__()
        self.device_id = device_id or "first available"
        self._want = device_id
        self.width, self.height, self.fps, self.queue_size = width, height, fps, queue_size

    def _find(self) -> Any:
        dai = self.dai
        found = dai.Device.getAllAvailableDevices()
        if not found:
            raise NoDevice("no OAK device found (check the USB cable, the udev rule, or Docker's "
                           "/dev/bus/usb mapping; `capture --list-devices` lists what is visible)")
        if self._want is None:
            return found[0]
        for info in found:
            if info.getDeviceId() == self._want:
                return info
        ids = ", ".join(i.getDeviceId() for i in found)
        raise NoDevice(f"no OAK device with id {self._want!r} (found: {ids})")

    def build(self) -> tuple[Any, Any, Any]:
        dai = self.dai
        info = self._find()
        self.device_id = info.getDeviceId()
        pipeline = dai.Pipeline(dai.Device(info))
        cam = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_A)
        left = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_B)
        right = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_C)
        stereo = pipeline.create(dai.node.StereoDepth)
        stereo.setLeftRightCheck(True)
        stereo.setRectifyEdgeFillColor(0)
        size = (self.width, self.height)
        rgb = cam.requestOutput(size, dai.ImgFrame.Type.BGR888i, fps=self.fps)
        left.requestOutput(size, fps=self.fps).link(stereo.left)
        right.requestOutput(size, fps=self.fps).link(stereo.right)
        rgb.link(stereo.inputAlignTo)  # depth resampled to the colour camera's view and size
        qc = rgb.createOutputQueue(maxSize=self.queue_size, blocking=False)
        qd = stereo.depth.createOutputQueue(maxSize=self.queue_size, blocking=False)
        log.info("depthai %s: streaming %dx%d at %g fps", self.device_id, self.width, self.height, self.fps)
        return pipeline, qc, qd

    def __repr__(self) -> str:
        return f"DepthaiBackend({self.device_id}, {self.width}x{self.height}@{self.fps:g})"

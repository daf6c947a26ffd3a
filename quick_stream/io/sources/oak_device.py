"""The real OAK backend: a depthai v3 pipeline with colour and stereo depth aligned to it.

Needs the optional extra (``pip install 'quick-stream[depthai]'``); without it every
entry point raises an ImportError naming the extra. Pipeline (depthai v3):

    Camera CAM_A  --requestOutput((W, H), BGR888i, fps)--> Sync.inputs["color"]
                  \\--> StereoDepth.inputAlignTo          (depth resampled to the colour view)
    Camera CAM_B/CAM_C --requestOutput--> StereoDepth.left/right --depth (uint16 mm)--> Sync.inputs["depth"]
    Sync (threshold: the source's tolerance_ms) --MessageGroup--> one output queue

The StereoDepth node gets the source's :class:`~quick_stream.io.sources.oak_options.StereoSettings`
(:func:`configure_stereo`): its preset first, then every setting on the node's ``initialConfig``
(in depthai v3 the node's own ``setLeftRightCheck``/``setSubpixel``/... write to that same config),
so nothing is left to defaults that differ between depthai versions and presets (depthai 3.12's
config defaults to 5 subpixel bits and no median; its DEFAULT preset decimates by 2, which would
halve the depth's size).

Colour and depth are paired on the device: the ``Sync`` node sends a group only when it holds a
colour and a depth frame within the threshold of each other, so a frame whose partner was lost
never reaches the host (it shows as a gap in the device sequence numbers). The queue is
non-blocking on the device side with a few groups, so a slow host drops old groups there instead
of stalling the device; the host waits on it (``get`` with a timeout, no polling). A device that
stops delivering for the ``read`` timeout, or raises from depthai, is reported as
:class:`DeviceGone`.
"""
from __future__ import annotations

import datetime
import logging
from typing import Any

from .oak_options import DeviceGone, EXTRA_HINT, NoDevice, StereoSettings

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


COLOR, DEPTH = "color", "depth"  # the Sync node's inputs, and the names in its MessageGroups


def synced_queue(dai: Any, pipeline: Any, color: Any, depth: Any, tolerance_ms: float, queue_size: int,
                 on_host: bool = False) -> Any:
    """Link the ``color`` and ``depth`` outputs into a ``Sync`` node of ``pipeline`` that pairs them
    within ``tolerance_ms`` (on the device, or on the host for a host-only pipeline) and return
    the queue of its MessageGroups (non-blocking on the sending side, ``queue_size`` groups)."""
    sync = pipeline.create(dai.node.Sync)
    sync.setSyncThreshold(datetime.timedelta(milliseconds=tolerance_ms))
    if on_host:
        sync.setRunOnHost(True)
    color.link(sync.inputs[COLOR])
    depth.link(sync.inputs[DEPTH])
    return sync.out.createOutputQueue(maxSize=queue_size, blocking=False)


MEDIAN_KERNELS = {0: "MEDIAN_OFF", 3: "KERNEL_3x3", 5: "KERNEL_5x5", 7: "KERNEL_7x7"}


def preset_mode(dai: Any, name: str) -> Any:
    """depthai's ``StereoDepth.PresetMode`` called ``name`` (any case); ValueError naming those this
    depthai has when it lacks it."""
    modes = dai.node.StereoDepth.PresetMode
    mode = getattr(modes, name.upper(), None)
    if mode is None:
        have = ", ".join(n.lower() for n in modes.__members__)
        raise ValueError(f"depthai {getattr(dai, '__version__', '?')} has no stereo preset {name!r} (it has: {have})")
    return mode


def stereo_config(dai: Any, config: Any, s: StereoSettings) -> Any:
    """Write the settings ``s`` into a ``StereoDepthConfig`` (a node's ``initialConfig``, or one made
    on the host); returns it. Decimation stays 1 and depth in millimetres, whatever a preset set."""
    config.setLeftRightCheck(s.lr_check)
    config.setExtendedDisparity(s.extended)
    config.setSubpixel(s.subpixel > 0)
    if s.subpixel:
        config.setSubpixelFractionalBits(s.subpixel)
    config.setConfidenceThreshold(s.confidence)
    config.setMedianFilter(getattr(dai.StereoDepthConfig.MedianFilter, MEDIAN_KERNELS[s.median]))
    config.setDepthUnit(dai.StereoDepthConfig.AlgorithmControl.DepthUnit.MILLIMETER)
    post = config.postProcessing
    post.spatialFilter.enable = s.spatial
    post.temporalFilter.enable = s.temporal
    post.speckleFilter.enable = s.speckle
    post.decimationFilter.decimationFactor = 1  # depth keeps the colour's size (to_rgbd checks it)
    return config


def configure_stereo(dai: Any, stereo: Any, s: StereoSettings) -> None:
    """Apply ``s`` to a StereoDepth node: the preset (which rewrites the initial config), then the
    settings on top of it (:func:`stereo_config`); black, not replicated, pixels where rectification
    leaves no data; the post-processing SHAVEs depthai's filtering presets reserve when a SHAVE filter
    (spatial, temporal, speckle) is on."""
    stereo.setDefaultProfilePreset(preset_mode(dai, s.preset))
    stereo_config(dai, stereo.initialConfig, s)
    stereo.setRectifyEdgeFillColor(0)
    if s.spatial or s.temporal or s.speckle:
        stereo.setPostProcessingHardwareResources(3, 3)


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
    """A started depthai pipeline whose one output queue gives colour and depth frames already
    paired (:func:`synced_queue`): ``open``/``read``/``close``.

    Subclasses say how the pipeline is built (:meth:`build`); reading is shared, so the
    device backend and a host-only pipeline (tests, replays) go through the same code."""

    device_id = "pipeline"

    def __init__(self) -> None:
        self.dai = import_depthai()
        self._pipeline = None
        self._queue = None

    def build(self) -> tuple[Any, Any]:
        """(pipeline, queue of colour/depth MessageGroups), not started."""
        raise NotImplementedError

    def open(self) -> None:
        try:
            pipeline, queue = self.build()
            pipeline.start()
        except (NoDevice, DeviceGone):
            raise
        except Exception as e:  # noqa: BLE001 - depthai raises RuntimeError subclasses of its own
            raise DeviceGone(f"cannot start the pipeline on {self.device_id}: {e}") from None
        self._pipeline, self._queue = pipeline, queue

    def read(self, timeout_s: float) -> tuple[list[Any], list[Any]]:
        """The next colour/depth pair as ([colour], [depth]); waits up to ``timeout_s`` for it."""
        if self._pipeline is None:
            raise DeviceGone("not open")
        try:
            group = self._queue.get(datetime.timedelta(seconds=timeout_s))  # None when it timed out
            if group is None:
                raise DeviceGone("pipeline stopped" if not self._pipeline.isRunning()
                                 else f"no frames for {timeout_s:g} s")
            return [group[COLOR]], [group[DEPTH]]
        except DeviceGone:
            raise
        except Exception as e:  # noqa: BLE001 - XLink errors (a closed queue too) surface as RuntimeError
            raise DeviceGone(str(e)) from None

    def close(self) -> None:
        p, self._pipeline, self._queue = self._pipeline, None, None
        try:
            if p is not None:
                p.stop()
        except Exception:  # noqa: BLE001 - stopping a dead device may raise; nothing to do
            pass


class DepthaiBackend(PipelineBackend):
    """Colour + aligned stereo depth from one OAK device (``device_id`` None: the first found)."""

    def __init__(self, device_id: str | None, width: int = 640, height: int = 400, fps: float = 30.0,
                 tolerance_ms: float = 10.0, queue_size: int = 4, stereo: StereoSettings | None = None) -> None:
        super().__init__()
        self.device_id = device_id or "first available"
        self._want = device_id
        self.width, self.height, self.fps, self.queue_size = width, height, fps, queue_size
        self.tolerance_ms = tolerance_ms
        self.stereo = stereo or StereoSettings()
        preset_mode(self.dai, self.stereo.preset)  # a preset this depthai lacks fails before any device is opened

    def _find(self) -> Any:
        dai = self.dai
        found = dai.Device.getAllAvailableDevices()
        if not found:
            raise NoDevice("no OAK device found (check the USB cable, the udev rule, or Docker's "
                           "/dev/bus/usb mapping; `quick-stream-capture --list-devices` lists what is visible)")
        if self._want is None:
            return found[0]
        for info in found:
            if info.getDeviceId() == self._want:
                return info
        ids = ", ".join(i.getDeviceId() for i in found)
        raise NoDevice(f"no OAK device with id {self._want!r} (found: {ids})")

    def build(self) -> tuple[Any, Any]:
        dai = self.dai
        info = self._find()
        self.device_id = info.getDeviceId()
        pipeline = dai.Pipeline(dai.Device(info))
        cam = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_A)
        left = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_B)
        right = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_C)
        stereo = pipeline.create(dai.node.StereoDepth)
        configure_stereo(dai, stereo, self.stereo)
        size = (self.width, self.height)
        rgb = cam.requestOutput(size, dai.ImgFrame.Type.BGR888i, fps=self.fps)
        left.requestOutput(size, fps=self.fps).link(stereo.left)
        right.requestOutput(size, fps=self.fps).link(stereo.right)
        rgb.link(stereo.inputAlignTo)  # depth resampled to the colour camera's view and size
        queue = synced_queue(dai, pipeline, rgb, stereo.depth, self.tolerance_ms, self.queue_size)
        log.info("depthai %s: streaming %dx%d at %g fps; stereo %s", self.device_id, self.width, self.height,
                 self.fps, self.stereo)
        return pipeline, queue

    def __repr__(self) -> str:
        return f"DepthaiBackend({self.device_id}, {self.width}x{self.height}@{self.fps:g})"

"""The depthai (OAK) source: adapter, pairing, faults and reconnection (docs/usage.md, "Live OAK (depthai) cameras").

No camera is attached here, so the adapter runs on (a) the scripted fake device
(quick_stream/io/sources/stand_in/oak_fake.py) and (b) real ``depthai.ImgFrame`` objects coming
out of a host-only depthai pipeline (``ReplayVideo`` replaying an MP4, no device).
"""
from __future__ import annotations

import datetime
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from quick_stream.core.frame import BadFrame, RGBDFrame, dequantize_depth, quantize_depth
from quick_stream.io.sources import SourceError, open_source
from quick_stream.io.sources.oak import FramePairer, OakSource
from quick_stream.io.sources.oak_options import DeviceGone, NoDevice
from quick_stream.io.sources.stand_in.oak_fake import FakeImgFrame, FakeOakBackend, parse_script
from quick_stream.io.sources.synthetic import SyntheticSource
from quick_stream.stream.wire import decode, encode_frame

W, H = 160, 120


def fake_spec(script: str = "1", frames: int = 20) -> str:
    return f"depthai:fake0,fake={script},frames={frames},width={W},height={H}"


def test_clean_fake_device_gives_metric_depth_per_frame_intrinsics_and_capture_metadata():
    frames = list(open_source(fake_spec(frames=6)))
    truth = SyntheticSource(width=W, height=H, frames=6)
    assert [f.seq for f in frames] == list(range(6)) and all(isinstance(f, RGBDFrame) for f in frames)
    for f in frames:
        t = truth.frame(f.seq)
        assert np.array_equal(f.color, t.color)
        assert np.array_equal(f.depth, dequantize_depth(quantize_depth(t.depth)))  # mm -> m, 0 stays invalid
        assert f.intrinsics == truth.intrinsics_at(f.seq)
        c = f.capture
        assert c["device_id"] == "fake0" and c["seq_color"] == c["seq_depth"] == f.seq
        assert c["t_host_ns"] == f.timestamp_ns and c["depth_skew_ns"] == 300_000
    assert np.all(np.diff([f.timestamp_ns for f in frames]) > 0)


def test_scripted_faults_cost_single_frames_and_the_stream_goes_on():
    script = "drop_color:3+drop_depth:5+mismatch:7+late_depth:9+intrinsics:12+disconnect:15"
    src = open_source(fake_spec(script, frames=25))
    out = list(src)
    seqs = [f.seq for f in out]
    assert seqs == list(range(25))
    colour_seq = [f.capture.get("seq_color") if isinstance(f, RGBDFrame) else None for f in out]
    # frame 3's colour and frame 5's depth never arrived: those device frames are missing
    assert 3 not in colour_seq[:12] and 5 not in colour_seq[:12]
    assert src.pairer.stats.unpaired_color == 1 and src.pairer.stats.paired_by_time == 1  # the mismatch
    assert src.pairer.stats.unpaired_depth == 1  # frame 3's depth, whose colour never came
    gaps = [f for f in out if isinstance(f, BadFrame)]
    assert len(gaps) == 1 and "disconnected" in gaps[0].error and "reconnected after" in gaps[0].error
    assert src.reconnects and src.connections == 2
    after = out[out.index(gaps[0]) + 1]
    assert after.capture["seq_color"] == 0 and after.capture["connection"] == 1  # the device restarted
    fx = [f.intrinsics.fx for f in out if isinstance(f, RGBDFrame)]
    assert fx[0] == pytest.approx(fx[9]) and fx[-1] == pytest.approx(1.1 * fx[0])  # new K from the frames
    stamps = [f.timestamp_ns for f in out if isinstance(f, RGBDFrame)]
    assert np.all(np.diff(stamps) > 0)


def test_reconnection_gives_up_after_bounded_retries():
    class Dead(FakeOakBackend):
        attempts = 0

        def open(self):
            Dead.attempts += 1
            raise DeviceGone("X_LINK_DEVICE_NOT_FOUND")

    src = OakSource(Dead(W, H), W, H, retries=2, retry_delay_s=0.01)
    with pytest.raises(NoDevice, match="could not open after 3 attempts"):
        next(iter(src))
    assert Dead.attempts == 3  # the first try and 2 retries, then it gives up


def test_pairing_by_sequence_then_time_and_giving_up_on_lost_partners():
    K = np.eye(3)
    img, dep = np.zeros((4, 4, 3), np.uint8), np.zeros((4, 4), np.uint16)

    def c(seq, t_ms):
        return FakeImgFrame(img, seq, 0, int(t_ms * 1e6), K)

    def d(seq, t_ms):
        return FakeImgFrame(dep, seq, 0, int(t_ms * 1e6), K)

    p = FramePairer(tolerance_ms=5)
    assert [(a.seq, b.seq) for a, b in p.add([c(0, 0), c(1, 33)], [d(1, 33), d(0, 0)])] == [(0, 0), (1, 1)]
    assert p.add([c(2, 66)], [d(99, 67)])[0][1].seq == 99  # other seq, within tolerance: by time
    assert p.add([c(3, 100)], []) == []  # waits for its depth ...
    assert p.add([], [d(5, 166)]) == []  # ... which is gone: a newer depth arrived
    assert p.stats.unpaired_color == 1
    assert p.add([c(5, 166)], [])[0][1].seq == 5
    assert (p.stats.paired_by_seq, p.stats.paired_by_time) == (3, 1)


def test_bad_options_and_missing_extra_are_named(monkeypatch):
    with pytest.raises(SourceError, match="unknown option"):
        open_source("depthai:,bogus=1")
    with pytest.raises(SourceError, match="fake depthai script"):
        open_source("depthai:,fake=explode:3")
    monkeypatch.setitem(sys.modules, "depthai", None)  # as if the extra were not installed
    with pytest.raises(SourceError, match=r"quick-stream\[depthai\]"):
        open_source("depthai")


def test_capture_metadata_travels_on_the_wire():
    f = next(iter(open_source(fake_spec(frames=1))))
    g = decode(encode_frame(f, "cam0")).obj
    assert g.capture == f.capture


def test_parse_script():
    assert parse_script("1") == {}
    assert parse_script("drop_color:3+disconnect:3") == {3: {"drop_color", "disconnect"}}


# --- real depthai objects, host-only pipeline (no device) ----------------------------------------

import depthai as dai  # noqa: E402 - a test dependency (the `test` extra): the adapter on real depthai objects


from quick_stream.io.sources.oak_device import PipelineBackend, synced_queue  # noqa: E402 - needs depthai


class DeviceEmulator(dai.node.HostNode):
    """A host node standing in for the device's outputs: it stamps each replayed colour frame
    as the device would (camera matrix as its transformation, sequence number, device and
    host timestamps) and sends it with a RAW16 depth frame on two outputs. Depth 6 is
    dropped and depth 4 carries another sequence number, to drive the pairing."""

    def __init__(self) -> None:
        super().__init__()
        kind = [dai.Node.DatatypeHierarchy(dai.DatatypeEnum.ImgFrame, True)]
        self.color_out = self.createOutput(possibleDatatypes=kind)
        self.depth_out = self.createOutput(possibleDatatypes=kind)
        self.i = 0

    def build(self, src, depth_mm, K):
        self.link_args(src)
        self.depth_mm, self.K = depth_mm, K
        return self

    def process(self, m):
        i, self.i = self.i, self.i + 1
        h, w = self.depth_mm[i].shape
        m.setTransformation(dai.ImgTransformation(w, h, self.K.tolist()))
        m.setSequenceNum(i)
        m.setTimestampDevice(datetime.timedelta(milliseconds=33 * i))
        m.setTimestamp(datetime.timedelta(seconds=100, milliseconds=33 * i))
        d = dai.ImgFrame()
        d.setCvFrame(self.depth_mm[i], dai.ImgFrame.Type.RAW16)
        d.setSequenceNum(i + (500 if i == 4 else 0))
        d.setTimestampDevice(datetime.timedelta(milliseconds=33 * i + 1))
        d.setTimestamp(datetime.timedelta(seconds=100, milliseconds=33 * i + 1))
        d.setTransformation(dai.ImgTransformation(w, h, self.K.tolist()))
        self.color_out.send(m)
        if i != 6:
            self.depth_out.send(d)


class HostReplayBackend(PipelineBackend):
    """The real backend's pairing and reading code on a host-only pipeline: ReplayVideo ->
    DeviceEmulator -> the same Sync node as on the device (run on the host here)."""

    device_id = "host-replay"

    def __init__(self, mp4: Path, depth_mm: list[np.ndarray], K: np.ndarray, size: tuple[int, int]) -> None:
        super().__init__()
        self.mp4, self.depth_mm, self.K, self.size = mp4, depth_mm, K, size

    def build(self):
        p = dai.Pipeline(createImplicitDevice=False)
        r = p.create(dai.node.ReplayVideo)
        r.setReplayVideoFile(self.mp4)
        r.setOutFrameType(dai.ImgFrame.Type.BGR888i)
        r.setSize(*self.size)
        r.setFps(30)
        r.setLoop(False)
        dev = p.create(DeviceEmulator).build(r.out, self.depth_mm, self.K)
        return p, synced_queue(dai, p, dev.color_out, dev.depth_out, 10.0, 64, on_host=True)


def test_adapter_on_real_depthai_imgframes_from_a_host_only_pipeline(tmp_path):
    syn = SyntheticSource(width=W, height=H, frames=10)
    mp4 = tmp_path / "colour.mp4"
    vw = cv2.VideoWriter(str(mp4), cv2.VideoWriter_fourcc(*"mp4v"), 30, (W, H))
    for i in range(10):
        vw.write(syn.frame(i).color)
    vw.release()
    depth = [quantize_depth(syn.frame(i).depth) for i in range(10)]
    K = syn.intrinsics.K
    backend = HostReplayBackend(mp4, depth, K, (W, H))
    src = OakSource(backend, W, H, retries=0, read_timeout_s=5.0, frames=9)
    got = list(src)
    frames = [f for f in got if isinstance(f, RGBDFrame)]
    assert len(frames) == 9  # 10 colour frames; the one whose depth was dropped is skipped
    # paired by the Sync node: the colour without depth never leaves it, the mismatched sequence
    # number is paired by time (within the threshold), so the host has nothing left to pair
    assert src.pairer.stats.paired_by_time == 1 and src.pairer.stats.unpaired_color == 0
    for f in frames:
        i = f.capture["seq_color"]
        assert f.intrinsics.K == pytest.approx(K) and (f.intrinsics.width, f.intrinsics.height) == (W, H)
        assert np.array_equal(f.depth, dequantize_depth(depth[i]))
        assert f.color.shape == (H, W, 3) and f.color.dtype == np.uint8
        assert np.abs(f.color.astype(int) - syn.frame(i).color).mean() < 12  # mp4 round trip
        assert f.capture["t_device_ns"] == 33_000_000 * i and f.capture["depth_skew_ns"] == 1_000_000
    assert 6 not in [f.capture["seq_color"] for f in frames]


# --- stereo settings: parsed from the spec, written into the StereoDepth node the device backend builds ----

from unittest import mock  # noqa: E402

from quick_stream.io.sources import check_source  # noqa: E402
from quick_stream.io.sources.oak_options import PRESETS, StereoSettings, oak_settings  # noqa: E402
from quick_stream.io.sources.oak_device import DepthaiBackend, preset_mode, stereo_config  # noqa: E402


def test_stereo_options_have_measured_defaults_and_bad_values_are_named():
    s = oak_settings({})["stereo"]
    assert s == StereoSettings(preset="fast_accuracy", subpixel=3, lr_check=True, confidence=55, median=7,
                               spatial=False, temporal=False, speckle=False, extended=False)
    got = oak_settings({"preset": "ROBOTICS", "subpixel": "off", "median": "5", "lr_check": "0", "confidence": "200",
                        "spatial": "on", "temporal": "true", "speckle": "1", "extended": "yes"})["stereo"]
    assert got == StereoSettings("robotics", 0, False, 200, 5, True, True, True, True)
    assert oak_settings({"subpixel": "5", "median": "off"})["stereo"].subpixel == 5
    for spec, message in [("preset=turbo", "preset='turbo' must be one of fast_accuracy, fast_density"),
                          ("subpixel=2", "subpixel='2' must be one of 0, 3, 4, 5"),
                          ("median=9", "median='9' must be one of 0, 3, 5, 7"),
                          ("confidence=300", r"confidence='300' must be an integer in \[0, 255\]"),
                          ("confidence=-1", "confidence='-1' must be an integer"),
                          ("lr_check=maybe", "lr_check='maybe' must be 1 or 0"),
                          ("subpixel=5", "median=7 runs only with subpixel=3 or subpixel=0")]:
        with pytest.raises(SourceError, match=message):
            open_source(f"depthai:,{spec}")
        with pytest.raises(SourceError, match=message):  # the launcher's check, before any process starts
            check_source(f"depthai:,{spec}")
    assert len(list(open_source(fake_spec(frames=2) + ",median=5,subpixel=3"))) == 2  # the fake has no matcher


def test_every_preset_name_is_one_of_the_installed_depthai():
    assert {preset_mode(dai, p).name for p in PRESETS} == set(dai.node.StereoDepth.PresetMode.__members__)
    with pytest.raises(ValueError, match="has no stereo preset 'turbo' .it has: fast_accuracy"):
        preset_mode(dai, "turbo")


def _config_as_a_preset_leaves_it():
    """A StereoDepthConfig as depthai's DEFAULT preset leaves it (filters on, decimation 2, 5 bits)."""
    c = dai.StereoDepthConfig()
    c.setConfidenceThreshold(15)
    c.setSubpixelFractionalBits(5)
    c.setMedianFilter(dai.StereoDepthConfig.MedianFilter.MEDIAN_OFF)
    c.setDepthUnit(dai.StereoDepthConfig.AlgorithmControl.DepthUnit.METER)
    for f in (c.postProcessing.spatialFilter, c.postProcessing.temporalFilter, c.postProcessing.speckleFilter):
        f.enable = True
    c.postProcessing.decimationFilter.decimationFactor = 2
    return c


def _stereo_state(c) -> dict:
    pp = c.postProcessing
    return {"lr_check": c.getLeftRightCheck(), "extended": c.getExtendedDisparity(), "subpixel": c.getSubpixel(),
            "bits": c.getSubpixelFractionalBits(), "confidence": c.getConfidenceThreshold(),
            "median": c.getMedianFilter().name, "unit": c.getDepthUnit().name, "spatial": pp.spatialFilter.enable,
            "temporal": pp.temporalFilter.enable, "speckle": pp.speckleFilter.enable,
            "decimation": pp.decimationFilter.decimationFactor}


def test_stereo_settings_overwrite_what_a_preset_left_in_a_real_depthai_config():
    c = stereo_config(dai, _config_as_a_preset_leaves_it(), StereoSettings())
    assert _stereo_state(c) == {"lr_check": True, "extended": False, "subpixel": True, "bits": 3, "confidence": 55,
                                "median": "KERNEL_7x7", "unit": "MILLIMETER", "spatial": False, "temporal": False,
                                "speckle": False, "decimation": 1}
    c = stereo_config(dai, dai.StereoDepthConfig(), StereoSettings(subpixel=0, median=3, lr_check=False, spatial=True))
    assert (c.getSubpixel(), c.getMedianFilter().name, c.getLeftRightCheck(), c.postProcessing.spatialFilter.enable) \
        == (False, "KERNEL_3x3", False, True)


class StandInDevice:
    """depthai with its device side stood in, for building the device backend's pipeline without a
    camera: depthai makes device nodes (Camera, StereoDepth, Sync) only on a pipeline that holds a
    device. ``Pipeline.create`` gives stand-ins specced on the real node classes (a method depthai's
    node lacks fails); the StereoDepth stand-in holds a real ``StereoDepthConfig`` as its
    ``initialConfig``, and its ``setDefaultProfilePreset`` rewrites that config as a depthai preset
    does. Everything else is the real depthai."""

    def __init__(self) -> None:
        self.nodes: dict[str, list] = {}
        info = mock.Mock()
        info.getDeviceId.return_value = "14442C10D13EABCE00"
        owner = self

        class Device:
            getAllAvailableDevices = staticmethod(lambda: [info])

            def __init__(self, found) -> None:
                self.info = found

        class Pipeline:
            def __init__(self, device) -> None:
                self.device = device

            def create(self, kind):
                node = mock.create_autospec(kind, instance=True)
                if kind is dai.node.StereoDepth:
                    node.initialConfig = dai.StereoDepthConfig()

                    def preset(mode, node=node):
                        node.initialConfig = _config_as_a_preset_leaves_it()

                    node.setDefaultProfilePreset.side_effect = preset
                owner.nodes.setdefault(kind.__name__, []).append(node)
                return node

        self.Device, self.Pipeline = Device, Pipeline

    def __getattr__(self, name):
        return getattr(dai, name)


@pytest.mark.parametrize("options, preset, state, shaves", [
    ("", "FAST_ACCURACY", {"subpixel": True, "bits": 3, "median": "KERNEL_7x7", "confidence": 55, "spatial": False,
                           "temporal": False}, False),
    (",preset=robotics,subpixel=0,median=5,confidence=200,speckle=1", "ROBOTICS",
     {"subpixel": False, "median": "KERNEL_5x5", "confidence": 200, "speckle": True, "temporal": False}, True),
])
def test_the_device_backend_builds_its_stereo_node_with_the_specs_settings(options, preset, state, shaves):
    src = open_source(f"depthai:14442C10D13EABCE00,width=640,height=400{options}")
    backend = src.backend
    assert isinstance(backend, DepthaiBackend)
    backend.dai = device = StandInDevice()
    backend.build()
    (stereo,) = device.nodes["StereoDepth"]
    assert stereo.setDefaultProfilePreset.call_args == mock.call(getattr(dai.node.StereoDepth.PresetMode, preset))
    got = _stereo_state(stereo.initialConfig)  # the config the node was left with, after its preset
    assert {k: got[k] for k in state} == state
    assert (got["lr_check"], got["decimation"], got["unit"]) == (True, 1, "MILLIMETER")
    assert stereo.setRectifyEdgeFillColor.call_args == mock.call(0)
    assert stereo.setPostProcessingHardwareResources.called == shaves
    colour, left, right = (c.build.return_value for c in device.nodes["Camera"])
    assert [c.build.call_args for c in device.nodes["Camera"]] == \
        [mock.call(s) for s in (dai.CameraBoardSocket.CAM_A, dai.CameraBoardSocket.CAM_B, dai.CameraBoardSocket.CAM_C)]
    rgb = colour.requestOutput.return_value
    assert mock.call(stereo.inputAlignTo) in rgb.link.call_args_list  # depth aligned to the colour output
    assert left.requestOutput.return_value.link.call_args == mock.call(stereo.left)
    assert right.requestOutput.return_value.link.call_args == mock.call(stereo.right)
    (sync,) = device.nodes["Sync"]
    assert stereo.depth.link.call_args == mock.call(sync.inputs["depth"])


# --- end to end: the fake device feeds capture, the pipeline stabilizes, the recording replays -------


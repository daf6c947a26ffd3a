"""End to end: the services as separate processes over Zenoh on loopback (docs/architecture.md).

* ``quick-stream up`` on a synthetic clip gives stabilized frames bit-identical to
  the in-process :class:`~quick_stream.core.stabilizer.Stabilizer` with the same settings;
* replaying its recording (``--source mcap:FILE``) gives them again;
* the recording opens with the ``mcap`` reader and its Foxglove channels are valid;
* a flow service killed mid-stream is restarted, the stream recovers within 2 s,
  the affected frames are flagged and nothing hangs.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np
import pytest
from tests.helpers import UP, offline_images, sent, up_and_kill, wait_for_status
from mcap.reader import make_reader

from quick_stream.cli import build_parser
from quick_stream.core.settings import settings_digest
from quick_stream.io.recording import read_messages
from quick_stream.io.settings_file import recording_settings, settings_toml
from quick_stream.io.stabilizer_flags import default_settings, stabilizer_params
from quick_stream.stream.wire import decode

SPEC = "synthetic:frames=75,width=320,height=240"
# settings other than the defaults, for every stage (flow, motion, render), from a file and a flag: the
# recording carries them, so replay and rerun need neither
SETTINGS_TOML = """
[flow]
max_points = 2500

[planner]
lookahead = 8

[planner.keyframes]
interval = 20

[warp]
alpha = 0.2
"""
SETTINGS_FLAGS = ("--max-zoom", "1.2")


def run_up(out: Path, *extra: str, timeout: float = 120) -> subprocess.CompletedProcess:
    p = subprocess.run([*UP, "--out", str(out), *extra], capture_output=True, text=True, timeout=timeout)
    assert p.returncode == 0, p.stdout + p.stderr
    return p


def pngs(folder: Path) -> dict[int, np.ndarray]:
    return {int(f.stem): cv2.imread(str(f), cv2.IMREAD_UNCHANGED) for f in sorted(folder.glob("*.png"))}


@pytest.fixture(scope="module")
def settings_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("settings") / "settings.toml"
    path.write_text(SETTINGS_TOML)
    return path


@pytest.fixture(scope="module")
def defaults_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("settings") / "defaults.toml"
    path.write_text(settings_toml(default_settings()))
    return path


@pytest.fixture(scope="module")
def offline(settings_file) -> dict[int, np.ndarray]:
    return offline_images(SPEC, "--settings", str(settings_file), *SETTINGS_FLAGS)


@pytest.fixture(scope="module")
def live_run(tmp_path_factory, settings_file) -> Path:
    out = tmp_path_factory.mktemp("up")
    # paced by the pipeline (--pace fast), not a 60 fps camera: on a loaded machine (a second suite
    # beside this one) a live capture sheds what the stages cannot take (counted, and tested in
    # test_backpressure.py / test_shedding.py), and a shed frame changes the path
    run_up(out, "--source", SPEC, "--pace", "fast", "--color", "raw", "--png", str(out / "png"),
           "--settings", str(settings_file), *SETTINGS_FLAGS)
    return out


def test_services_match_offline_bit_for_bit(live_run, offline):
    got = pngs(live_run / "png")
    assert sorted(got) == sorted(offline) == list(range(75))
    differ = [s for s in offline if not np.array_equal(got[s], offline[s])]
    assert differ == []
    assert (live_run / "stabilized.avi").stat().st_size > 0


def test_replaying_the_recording_reproduces_the_output(live_run, tmp_path):
    # with no settings given: the recording's; paced by the pipeline like the live run (a realtime
    # replay on a loaded machine sheds frames)
    run_up(tmp_path, "--source", f"mcap:{live_run / 'recording.mcap'}", "--pace", "fast",
           "--png", str(tmp_path / "png"))
    a, b = pngs(live_run / "png"), pngs(tmp_path / "png")
    assert sorted(a) == sorted(b)
    assert all(np.array_equal(a[s], b[s]) for s in a)


def test_a_tum_folder_streamed_as_jpeg_is_stabilized_as_its_recording_is_offline(tmp_path):
    # the capture streams a TUM folder (its own ``stop`` is not the device's stop event) with the colour as JPEG
    # (the default): the flow service decodes each JPEG's own grey only, the in-process stabilizer reads the
    # recorded frames with that grey too (mcap source), and the output agrees bit for bit; frame 12 is one
    # flat grey (no flow into or out of it): the flow service reaches over it, as the stabilizer does; frame
    # 20 is flat grey but for a 26 px patch: the flow into it keeps a few dozen pairs lifted loose
    # (docs/method.md (1c)), so it is held, and the flow out of it starves: reached back over it, the flow
    # from 19 to 21 (docs/method.md 2.4)
    from tests.unit.test_cli_motion import write_tum_clip

    names = [line.split()[1] for line in write_tum_clip(tmp_path / "clip", n=30)]
    cv2.imwrite(str(tmp_path / "clip" / names[12]), np.full((240, 320, 3), 128, np.uint8))
    img = cv2.imread(str(tmp_path / "clip" / names[20]))
    patch = np.full_like(img, 128)
    patch[100:126, 150:176] = img[100:126, 150:176]
    cv2.imwrite(str(tmp_path / "clip" / names[20]), patch)
    out = tmp_path / "up"
    run_up(out, "--source", f"tum:{tmp_path / 'clip'}", "--pace", "fast", "--png", str(out / "png"))
    got, offline = pngs(out / "png"), offline_images(f"mcap:{out / 'recording.mcap'}")
    assert sorted(got) == sorted(offline) == list(range(30))
    assert [s for s in offline if not np.array_equal(got[s], offline[s])] == []
    recorded = [decode(data) for _, _, data in read_messages(out / "recording.mcap",
                                                              ["quick/@v1/cam0/flow", "quick/@v1/cam0/motion"])]
    flows = [d.obj for d in recorded if d.type == "flow"]
    assert [(f.seq, f.seq_next, f.over) for f in flows if f.over] == [(11, 13, (12,)), (19, 21, (20,))]
    motions = [d.obj for d in recorded if d.type == "motion"]
    assert [(m.seq, m.seq_next) for m in motions] == [(s, s + 1) for s in range(29)]
    assert all(m.kind == "fit" for m in motions)


def test_recording_has_every_stage_and_valid_foxglove_channels(live_run):
    from quick_stream.io import foxglove as fx

    with open(live_run / "recording.mcap", "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        channels = {c.topic: c for c in summary.channels.values()}
        schemas = summary.schemas
        for stage in ("frame", "flow", "motion", "correction", "stabilized", "stats"):
            assert channels[f"quick/@v1/cam0/{stage}"].message_encoding == "msgpack"
        expect = {"/cam0/color": "foxglove.CompressedImage", "/cam0/stabilized": "foxglove.CompressedImage",
                  "/cam0/calibration": "foxglove.CameraCalibration", "/cam0/camera_pose": "foxglove.PoseInFrame",
                  "/cam0/stabilized_pose": "foxglove.PoseInFrame", "/cam0/tf": "foxglove.FrameTransform"}
        for topic, name in expect.items():
            ch = channels[topic]
            assert ch.message_encoding == "protobuf"
            sc = schemas[ch.schema_id]
            assert sc.name == name and sc.encoding == "protobuf" and sc.data == fx.schema_bytes(name)
        counts: dict[str, int] = {}
        for _, ch, msg in reader.iter_messages(topics=list(expect)):
            counts[ch.topic] = counts.get(ch.topic, 0) + 1
            body = fx.parse(schemas[ch.schema_id].name, msg.data)
            assert abs(body.timestamp.seconds - msg.log_time / 1e9) < 60  # wall clock, as the log times
            if ch.topic == "/cam0/color" and counts[ch.topic] == 1:
                img = cv2.imdecode(np.frombuffer(body.data, np.uint8), cv2.IMREAD_COLOR)
                assert img.shape == (240, 320, 3)
        assert counts["/cam0/color"] == counts["/cam0/stabilized"] == 75
        assert counts["/cam0/stabilized_pose"] == counts["/cam0/camera_pose"] == 75
        assert counts["/cam0/tf"] == 150


def _flow_log_times(recording: Path) -> list[int]:
    with open(recording, "rb") as f:
        return [m.log_time for _, _, m in make_reader(f).iter_messages(topics=["quick/@v1/cam0/flow"])]


def test_killed_flow_is_restarted_and_the_stream_recovers(tmp_path):
    out = tmp_path
    frames = 240  # 8 s at 30 fps
    killed_at, st, text = up_and_kill(out, f"synthetic:frames={frames},width=320,height=240", "flow")
    assert st["services"]["flow"]["restarts"] == 1
    assert any(e["service"] == "flow" and "restarted" in e["event"] for e in st["events"])
    assert "exit codes" not in text  # every service stopped cleanly on SIGTERM
    # recovery: flow publishes again after the kill (how soon: `python -m tests.tools.faults`)
    times = np.array(_flow_log_times(out / "recording.mcap"))
    after = times[times > killed_at]
    assert after.size > 0, "no flow after the kill"
    # every frame came out, none flagged: the restarted flow took over after the last flow out,
    # from the frames' history (the capture's publisher cache)
    assert "taking over from the frames' history" in (out / "logs" / "flow.log").read_text()
    flagged, seqs = [], []
    from quick_stream.io.recording import read_messages

    for _, _, data in read_messages(out / "recording.mcap", topics=["quick/@v1/cam0/stabilized"]):
        d = decode(data)
        if d.type == "stabilized":
            seqs.append(d.seq)
            if d.obj.flags:
                flagged.append(d.seq)
    assert sorted(seqs) == list(range(frames))
    assert flagged == []


def test_recorder_killed_with_sigkill_leaves_a_recoverable_file(tmp_path):
    """SIGKILL the recorder mid-stream: `quick-stream recover` repairs the file and keeps every
    message logged more than ~1 s (the flush period) before the kill."""
    from quick_stream.io.recording import RecordingError, read_messages
    from quick_stream.stream.wire import Stats, encode_stats

    rec_path = tmp_path / "rec.mcap"
    with router_and_recorder(tmp_path, "--output", str(rec_path)) as (sup, session, _):
        pub = session.declare_publisher("quick/@v1/cam0/stats")
        sent_at = []
        for i in range(60):  # 3 s at 20 Hz
            pub.put(encode_stats(Stats("probe", {"i": i}), "cam0", i))
            sent_at.append(time.monotonic())
            time.sleep(0.05)
        os.kill(sup.pid("recorder"), signal.SIGKILL)
        killed = time.monotonic()
    with pytest.raises(RecordingError, match="recover"):
        list(read_messages(rec_path))
    fixed = tmp_path / "fixed.mcap"
    r = subprocess.run([sys.executable, "-m", "quick_stream", "recover", str(rec_path), str(fixed)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    got = {decode(d).seq for t, _, d in read_messages(fixed) if t == "quick/@v1/cam0/stats"
           and decode(d).obj.service == "probe"}
    old_enough = {i for i, t in enumerate(sent_at) if killed - t > 1.3}
    assert old_enough and old_enough <= got


@contextmanager
def router_and_recorder(tmp_path: Path, *recorder_args: str) -> Iterator[tuple[object, object, dict]]:
    """A router and a recorder (not restarted) plus a session of the test's own, once the recorder
    is up; yields (supervisor, session, exit codes filled in on leaving)."""
    from quick_stream.stream.launcher import ServiceSpec, Supervisor, free_port, open_when_up

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    sup = Supervisor([ServiceSpec("router", ["-m", "quick_stream", "router", "-l", endpoint]),
                      ServiceSpec("recorder", ["-m", "quick_stream.services.recorder", "-e", endpoint,
                                               "--no-multicast-scouting", *recorder_args], restart=False)],
                     tmp_path / "logs")
    sup.start("router")
    session = open_when_up(endpoint, 20)
    codes: dict = {}
    try:
        sup.start("recorder")
        deadline = time.monotonic() + 30
        while "recorder" not in _alive(session) and time.monotonic() < deadline:
            time.sleep(0.1)
        yield sup, session, codes
    finally:
        session.close()
        codes.update(sup.stop())


def _until_received(session, service: str, stage: str, seq: int, timeout_s: float = 60) -> None:
    """Until ``service``'s cursor reports ``seq`` of ``stage`` received (what it then writes on a
    clean stop), instead of a sleep that a loaded machine outlasts."""
    from quick_stream.stream.wire import decode as wire_decode

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for reply in session.get(f"quick/@v1/cam0/cursor/{service}", timeout=1.0):
            try:
                got = wire_decode(reply.ok.payload.to_bytes()).obj.values.get(stage, -1)
            except Exception:  # noqa: BLE001 - an error reply: ask again
                continue
            if got >= seq:
                return
        time.sleep(0.05)
    raise AssertionError(f"{service} never reported {stage} {seq}")


def _alive(session) -> set[str]:
    out = set()
    for reply in session.liveliness().get("quick/@v1/cam0/health/*", timeout=1.0):
        try:
            out.add(str(reply.ok.key_expr).rsplit("/", 1)[-1])
        except Exception:  # noqa: BLE001 - an error reply is just not alive
            pass
    return out


@pytest.mark.parametrize("stage", ["flow", "motion", "render"])
def test_each_stage_reruns_from_the_recording_to_the_same_output(live_run, defaults_file, stage):
    # no flags: the settings come from the recording (the defaults would not reproduce it)
    r = subprocess.run([sys.executable, "-m", "quick_stream", "rerun", stage, str(live_run / "recording.mcap")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "OK" in r.stdout and "note: " not in r.stdout, r.stdout
    # with the defaults instead, the stage does not reproduce it (the recording's settings are what it ran with)
    d = subprocess.run([sys.executable, "-m", "quick_stream", "rerun", stage, str(live_run / "recording.mcap"),
                        "--settings", str(defaults_file)], capture_output=True, text=True, timeout=120)
    assert d.returncode == 1, d.stdout + d.stderr
    assert "ran with settings" in d.stdout


def test_the_recording_holds_the_settings_every_service_ran_with(live_run, settings_file):
    params = stabilizer_params(build_parser().parse_args(["stabilize", "--settings", str(settings_file),
                                                          *SETTINGS_FLAGS]))
    assert recording_settings(live_run / "recording.mcap") == params
    digests = {}
    for _, _, data in read_messages(live_run / "recording.mcap", topics=["quick/@v1/cam0/stats"]):
        st = decode(bytes(data)).obj
        digests.setdefault(st.service, set()).add(st.values.get("settings"))
    want = {settings_digest(params)}
    assert {s: digests.get(s) for s in ("flow", "motion", "render", "recorder")} == dict.fromkeys(
        ("flow", "motion", "render", "recorder"), want)


def test_ctrl_c_stops_every_process_and_leaves_a_complete_recording(tmp_path):
    p = subprocess.Popen([*UP, "--out", str(tmp_path), "--source", "synthetic:frames=900,width=320,height=240"],
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    status = tmp_path / "logs" / "status.json"
    try:
        wait_for_status(status, lambda st: sent(st) >= 40)
        p.send_signal(signal.SIGINT)
        text, _ = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 0, text
    assert "stopped: Ctrl-C" in text and "exit codes" not in text
    st = json.loads(status.read_text())
    for name, svc in st["services"].items():
        assert not svc["running"], name
        if svc["pid"]:
            assert not Path(f"/proc/{svc['pid']}").exists() or "zombie" in Path(f"/proc/{svc['pid']}/status").read_text()
    with open(tmp_path / "recording.mcap", "rb") as f:  # closed with its footer: the indexed reader opens it
        n = sum(1 for _ in make_reader(f).iter_messages(topics=["quick/@v1/cam0/frame"]))
    assert 40 <= n < 900


def test_recorder_splits_long_runs_into_finished_files_losing_nothing(tmp_path):
    """``--split-mb``: each file is finished (readable through its footer), the next keeps the
    Foxglove channels, and every frame is in exactly one file, in order."""
    from quick_stream.io.recording import read_messages
    from quick_stream.io.sources import open_source
    from quick_stream.stream.wire import encode_frame

    split = ("--output", str(tmp_path / "rec.mcap"), "--split-mb", "0.1")
    with router_and_recorder(tmp_path, *split) as (_, session, codes):
        pub = session.declare_publisher("quick/@v1/cam0/frame")
        for f in open_source("synthetic:frames=40,width=96,height=72"):  # ~35 KB a message, views included
            pub.put(encode_frame(f, "cam0", color="raw", depth="raw"))
            time.sleep(0.03)
        _until_received(session, "recorder", "frame", 39)
    assert codes["recorder"] == 0, codes
    files = sorted(tmp_path.glob("rec*.mcap"), key=lambda p: int(p.stem.partition("-")[2] or 0))
    assert len(files) >= 5, files
    seqs = []
    for path in files:
        frames = [decode(d).seq for t, _, d in read_messages(path) if t == "quick/@v1/cam0/frame"]
        seqs += frames
        with open(path, "rb") as fh:
            summary = make_reader(fh).get_summary()
        views = [c for c in summary.channels.values() if not c.topic.startswith("quick/")]
        assert views and all(c.schema_id for c in views), path  # Foxglove channels, with schemas, in every file
    assert seqs == list(range(40))
    assert "split: finished" in (tmp_path / "logs" / "recorder.log").read_text()

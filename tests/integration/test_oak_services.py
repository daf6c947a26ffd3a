"""The depthai (OAK) source in the services: the fake device through `up` and a replay, no camera attached."""
from __future__ import annotations

import signal
import subprocess
import sys

import cv2
import numpy as np
import pytest

from quick_stream.io.sources import SourceError, open_source
from quick_stream.io.sources.oak_options import NoDevice


def test_fake_device_through_the_services_and_replay_gives_the_same_output(tmp_path):
    spec = "depthai:fake0,fake=drop_depth:12+disconnect:40,frames=70,width=320,height=240"
    # paced by the pipeline: a live capture on a loaded machine sheds frames the stages cannot take,
    # and the replay would not shed the same ones
    up = [sys.executable, "-m", "quick_stream", "up", "--quiet", "--pace", "fast"]
    a, b = tmp_path / "live", tmp_path / "replay"
    r = subprocess.run([*up, "--out", str(a), "--source", spec, "--png", str(a / "png")],
                       capture_output=True, text=True, timeout=180)
    assert r.returncode == 0, r.stdout + r.stderr
    log = (a / "logs" / "capture.log").read_text()
    assert "device lost" in log and "reconnected after" in log
    r = subprocess.run([*up, "--out", str(b), "--source", f"mcap:{a / 'recording.mcap'}", "--png", str(b / "png")],
                       capture_output=True, text=True, timeout=180)
    assert r.returncode == 0, r.stdout + r.stderr
    pa, pb = sorted((a / "png").glob("*.png")), sorted((b / "png").glob("*.png"))
    assert [p.name for p in pa] == [p.name for p in pb] and len(pa) >= 60
    assert all(np.array_equal(cv2.imread(str(x)), cv2.imread(str(y))) for x, y in zip(pa, pb))


def test_real_backend_without_a_camera_says_no_device_found():
    from quick_stream.io.sources.oak_device import list_devices

    assert list_devices() == []  # no OAK on these machines
    src = open_source("depthai:,retries=0")
    with pytest.raises(NoDevice, match="no OAK device found") as e:
        next(iter(src))
    assert "`quick-stream-capture --list-devices`" in str(e.value)  # a command that exists (checked below)
    r = subprocess.run([sys.executable, "-m", "quick_stream.services.capture", "--list-devices"], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 1 and "no OAK device found" in r.stdout


def test_up_refuses_a_camera_that_is_not_connected_before_starting_anything(tmp_path, monkeypatch):
    from quick_stream.io.sources import check_source, oak_device

    r = subprocess.run([sys.executable, "-m", "quick_stream", "up", "--quiet", "--out", str(tmp_path / "o"),
                        "--source", "depthai"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "no OAK device found" in r.stderr, r.stdout + r.stderr
    assert "`quick-stream-capture --list-devices`" in r.stderr
    assert not (tmp_path / "o" / "logs").exists()  # no process was started
    monkeypatch.setattr(oak_device, "list_devices", lambda: [{"id": "184430101153051300", "name": "oak-d"}])
    check_source("depthai")  # one is connected: fine
    with pytest.raises(SourceError, match="no OAK device '1944301011'; connected: 184430101153051300"):
        check_source("depthai:1944301011")


def test_a_capture_that_cannot_open_its_camera_fails_up_and_is_not_restarted(tmp_path):
    spec = "depthai:fake0,fake=absent:0,retries=1"
    r = subprocess.run([sys.executable, "-m", "quick_stream", "up", "--quiet", "--out", str(tmp_path), "--source", spec],
                       capture_output=True, text=True, timeout=180)
    assert r.returncode == 1 and "stopped: capture failed (see logs/capture.log)" in r.stdout, r.stdout + r.stderr
    assert "capture exited 2 (cannot go on, see its log), not restarted" in r.stdout and "restarted" not in \
        r.stdout.replace("not restarted", "")
    log = (tmp_path / "logs" / "capture.log").read_text()
    assert "cannot be opened" in log and "no such device" in log


def test_a_capture_retrying_its_camera_stops_at_once_on_sigterm():
    spec = "depthai:fake0,fake=absent:0,retries=1000"  # would retry for more than an hour
    p = subprocess.Popen([sys.executable, "-m", "quick_stream.services.capture", "--source", spec],
                         stderr=subprocess.PIPE, text=True)
    try:
        for line in p.stderr:  # wait for the event itself: a second attempt has failed
            if "open failed (attempt 2 of 1001)" in line:
                break
        p.send_signal(signal.SIGTERM)
        rest = p.communicate(timeout=120)[1]  # a hang guard only: it stops within its next wait
    finally:
        p.kill()
    assert p.returncode == 0 and "stopped while opening" in rest, rest

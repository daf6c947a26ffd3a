"""Recordings written by processes that die: a SIGKILLed writer, a full disk under `up`."""
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from quick_stream.io.recording import RecordingError, read_messages, recover

REPO = Path(__file__).resolve().parents[2]


WRITER = textwrap.dedent("""
    import sys, time
    from quick_stream.io.recording import Recorder
    rec = Recorder(sys.argv[1], flush_s=float(sys.argv[2]))
    i = 0
    while True:
        t = time.time_ns()
        rec.write("quick/@v1/cam0/stats", i.to_bytes(8, "little"), log_time_ns=t)
        print(i, t, flush=True)
        i += 1
        time.sleep(0.005)
""")


def test_sigkilled_writer_loses_at_most_about_a_second_and_recovers(tmp_path):
    path = tmp_path / "killed.mcap"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(path), "1.0"], stdout=subprocess.PIPE,
                            text=True, env=env)
    lines = []
    deadline = time.time() + 30
    while time.time() < deadline:
        lines.append(proc.stdout.readline())
        if len(lines) > 50 and int(lines[-1].split()[1]) - int(lines[0].split()[1]) > 3.5e9:
            break
    kill_ns = time.time_ns()
    proc.send_signal(signal.SIGKILL)
    proc.wait(10)
    written = [(int(a), int(b)) for a, b in (ln.split() for ln in lines if ln.strip())]
    with pytest.raises(RecordingError, match="recover"):
        list(read_messages(path))  # no footer: the seeking reader refuses
    report = recover(path, tmp_path / "fixed.mcap")
    assert not report.complete and report.channels == 1
    got = {int.from_bytes(d, "little"): t for _, t, d in read_messages(tmp_path / "fixed.mcap")}
    # everything written more than ~1 s (the flush interval, plus margin) before the kill survived
    old = [i for i, t in written if t < kill_ns - 1.3e9]
    assert old and all(i in got for i in old)
    assert report.messages == len(got) <= len(written) + 5


def test_a_full_disk_stops_the_run_with_one_clear_error_and_a_recoverable_file(tmp_path):
    """A file size limit (as a full disk): the recorder's flush thread died, every message printed a
    traceback and its stats kept saying `running`. Now: one error naming the file and the cause,
    `state: error` in its stats and in up's status, exit 2 (not restarted), up stops with exit 1,
    and what reached the disk is recoverable."""
    import json
    import resource

    limit = 4 << 20  # bytes per file: the recording passes it within seconds, the logs do not

    def limit_files() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    out = tmp_path / "o"
    r = subprocess.run([sys.executable, "-m", "quick_stream", "up", "--quiet", "--out", str(out), "--source",
                        "synthetic:frames=3000,width=320,height=240"], capture_output=True, text=True,
                       timeout=300, preexec_fn=limit_files)
    assert r.returncode == 1 and "stopped: recorder failed (see logs/recorder.log)" in r.stdout, r.stdout + r.stderr
    assert "recorder exited 2 (cannot go on, see its log), not restarted" in r.stdout
    log = (out / "logs" / "recorder.log").read_text()
    assert log.count("cannot write") == 1 and "File too large" in log and "Traceback" not in log, log
    rec = json.loads((out / "logs" / "status.json").read_text())["services"]["recorder"]["stats"]
    assert rec["state"] == "error" and "File too large" in rec["error"], rec
    rep = recover(out / "recording.mcap", tmp_path / "fixed.mcap")
    assert rep.messages > 100 and not rep.complete  # the chunks flushed before the failure survive


def test_recording_stats_per_channel_rates(tmp_path, capsys):
    """`quick-stream recording-stats`: bytes per channel over the log-time span, per frame, at a nominal fps."""
    import json

    from quick_stream.cli import main
    from quick_stream.io.recording import Recorder
    from quick_stream.io.recording_stats import recording_stats

    path = tmp_path / "s.mcap"
    with Recorder(path, chunk_size=2000) as rec:
        rec.channel("/cam0/color", encoding="json", schema_name="foxglove.CompressedImage", schema=b"{}",
                    schema_encoding="jsonschema")
        for i in range(11):  # 10 s of log time, 11 frames
            t = 1_000_000_000 * (i + 1)
            rec.write("quick/@v1/cam0/frame", b"f" * 1000, log_time_ns=t)
            rec.write("/cam0/color", b"c" * 250, log_time_ns=t)
    s = recording_stats(path)
    assert s.duration_s == 10.0 and s.frames == 11 and s.streams == 1 and not s.stopped_at
    frame, color = s.channels["quick/@v1/cam0/frame"], s.channels["/cam0/color"]
    assert (frame.messages, frame.bytes, frame.message_encoding) == (11, 11000, "msgpack")
    assert (color.bytes, color.schema) == (2750, "foxglove.CompressedImage")
    assert s.rate(frame.bytes) == 1100.0 and s.per_frame(color.bytes) == 250.0
    assert s.file_bytes == path.stat().st_size > s.message_bytes == 13750
    d = s.as_dict(fps=30)
    assert d["channels"][0]["topic"] == "quick/@v1/cam0/frame" and d["channels"][0]["share"] == 0.8
    assert d["channels"][0]["bytes_per_s_at_fps"] == 30000.0
    assert main(["recording-stats", str(path), "--fps", "30"]) == 0
    text = capsys.readouterr().out
    assert "quick/@v1/cam0/frame" in text and "80.0%" in text and "MB/s@30fps" in text
    assert main(["recording-stats", "--json", "-", str(path)]) == 0
    assert json.loads(capsys.readouterr().out)[0]["frames"] == 11
    # a file cut short (a killed writer) is measured up to where it stops; a non-MCAP file is an error
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    c = recording_stats(cut)
    assert c.stopped_at and 0 < c.channels["quick/@v1/cam0/frame"].messages < 11
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    assert main(["recording-stats", str(junk)]) == 2
    assert "junk.mcap" in capsys.readouterr().err

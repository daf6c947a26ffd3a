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

    limit = 12 << 20  # bytes per file: the recording passes it within seconds, the logs do not

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

"""MCAP recording: round trip, bounded loss when the writer is SIGKILLed, recovery."""
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from quick_stream.recording import Recorder, RecordingError, read_messages, recover

REPO = Path(__file__).resolve().parents[1]


def test_round_trip_in_log_time_order(tmp_path):
    path = tmp_path / "a.mcap"
    with Recorder(path) as rec:
        for i in range(50):
            rec.write(f"quick/@v1/cam0/{'frame' if i % 2 else 'motion'}", bytes([i]) * 10, log_time_ns=1000 + i)
    got = list(read_messages(path))
    assert [t for _, t, _ in got] == [1000 + i for i in range(50)]
    assert got[3] == ("quick/@v1/cam0/frame", 1003, bytes([3]) * 10)
    assert len(list(read_messages(path, topics=["quick/@v1/cam0/motion"]))) == 25


WRITER = textwrap.dedent("""
    import sys, time
    from quick_stream.recording import Recorder
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


def test_recover_command(tmp_path, capsys):
    from quick_stream.cli import main

    src = tmp_path / "a.mcap"
    with Recorder(src) as rec:
        rec.write("quick/@v1/cam0/stats", b"x", log_time_ns=1)
    assert main(["recover", str(src)]) == 0
    out = capsys.readouterr().out
    assert "intact" in out and "1 messages" in out and (tmp_path / "a.recovered.mcap").exists()
    (tmp_path / "junk.mcap").write_bytes(b"junk")
    assert main(["recover", str(tmp_path / "junk.mcap")]) == 2
    assert "junk.mcap" in capsys.readouterr().err


def test_recover_refuses_garbage_and_same_file(tmp_path):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"this is not an mcap file at all")
    with pytest.raises(RecordingError, match="bad.mcap"):
        recover(bad, tmp_path / "out.mcap")
    with pytest.raises(RecordingError, match="different output"):
        recover(bad, bad)

"""MCAP recording: round trip, bounded loss when the writer is SIGKILLed, recovery."""
from pathlib import Path

import pytest

from quick_stream.io.recording import Recorder, RecordingError, read_messages, recover

REPO = Path(__file__).resolve().parents[2]


def test_round_trip_in_log_time_order(tmp_path):
    path = tmp_path / "a.mcap"
    with Recorder(path) as rec:
        for i in range(50):
            rec.write(f"quick/@v1/cam0/{'frame' if i % 2 else 'motion'}", bytes([i]) * 10, log_time_ns=1000 + i)
    got = list(read_messages(path))
    assert [t for _, t, _ in got] == [1000 + i for i in range(50)]
    assert got[3] == ("quick/@v1/cam0/frame", 1003, bytes([3]) * 10)
    assert len(list(read_messages(path, topics=["quick/@v1/cam0/motion"]))) == 25


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
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.mcap"]  # no empty or partial output left


def test_recover_writes_its_output_whole_or_not_at_all(tmp_path):
    src = tmp_path / "a.mcap"
    with Recorder(src) as rec:
        rec.write("quick/@v1/cam0/stats", b"x", log_time_ns=1)
    dst = tmp_path / "b.mcap"
    dst.write_bytes(b"an earlier recovery")
    with pytest.raises(RecordingError, match="b.mcap: exists"):
        recover(src, dst)
    assert dst.read_bytes() == b"an earlier recovery"
    assert recover(src, dst, overwrite=True).messages == 1 and len(list(read_messages(dst))) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.mcap", "b.mcap"]  # no .part left


def test_split_recorder_finishes_each_file_and_loses_nothing_at_the_seams(tmp_path):
    from quick_stream.io.recording import SplitRecorder

    opened = []

    def on_open(rec):
        opened.append(rec.path.name)
        rec.channel("/view", encoding="json", schema_name="V", schema=b"{}", schema_encoding="jsonschema")

    base = tmp_path / "rec.mcap"
    with SplitRecorder(base, base, split_bytes=10_500, on_open=on_open) as rec:
        for i in range(100):
            payload = i.to_bytes(4, "little") * 250  # 1000 bytes
            rec.rec.write("quick/@v1/cam0/frame", payload, log_time_ns=i)
            rec.wrote(len(payload))
        assert rec.messages == 100
    names = ["rec.mcap"] + [f"rec-{n}.mcap" for n in range(1, 10)]
    assert opened == names and len(rec.done) == 9  # a new file once 10,500 bytes are in, each with a footer
    seen = []
    for name, n in zip(names, [11] * 9 + [1]):
        msgs = list(read_messages(tmp_path / name))  # the seeking reader: needs the footer
        assert len(msgs) == n
        seen += [int.from_bytes(d[:4], "little") for _, _, d in msgs]
    assert seen == list(range(100))


def test_split_recorder_splits_by_age(tmp_path, monkeypatch):
    import quick_stream.io.recording as recording

    now = [1000.0]
    monkeypatch.setattr(recording.time, "monotonic", lambda: now[0])
    base = tmp_path / "rec.mcap"
    with recording.SplitRecorder(base, base, split_s=60.0) as rec:
        rec.rec.write("t", b"a", log_time_ns=1)
        assert rec.wrote(1) is None
        now[0] += 61.0
        assert rec.wrote(0) == base  # due even when nothing arrives
        rec.rec.write("t", b"b", log_time_ns=2)
    assert [len(list(read_messages(p))) for p in (base, tmp_path / "rec-1.mcap")] == [1, 1]



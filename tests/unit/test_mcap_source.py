"""MCAP replay source: exact replay, damaged messages become BadFrames, footer-less files, stream choice."""
import logging

import numpy as np
import pytest

from quick_stream.core.frame import BadFrame, RGBDFrame
from quick_stream.io.recording import Recorder
from quick_stream.io.sources import SOURCE_KINDS, Source, SourceError, open_source
from quick_stream.io.sources.mcap_replay import McapSource, recorded_streams
from quick_stream.stream.keys import key
from quick_stream.stream.wire import decode, encode_frame

SPEC = "synthetic:frames=5,width=160,height=120"


@pytest.fixture(scope="module")
def originals():
    return list(open_source(SPEC))


def _record(path, frames, streams=("cam0",), corrupt=None, depth_scale=1000.0, **kw):
    """Write frames (raw colour + raw depth) per stream; message index ``corrupt`` is garbled."""
    with Recorder(path) as rec:
        for i, f in enumerate(frames):
            for s in streams:
                data = encode_frame(f, s, color="raw", depth="raw", depth_scale=depth_scale)
                if i == corrupt:
                    data = data[: len(data) // 2]  # truncated msgpack: a WireError
                rec.write(key(s, "frame"), data, log_time_ns=10**9 + f.timestamp_ns)
                rec.write(key(s, "motion"), b"not a frame", log_time_ns=10**9 + f.timestamp_ns)
    return path


def _same(got: RGBDFrame, original: RGBDFrame, depth_scale=1000.0):
    want = decode(encode_frame(original, "cam0", color="raw", depth="raw", depth_scale=depth_scale)).obj
    assert isinstance(got, RGBDFrame)
    assert (got.seq, got.timestamp_ns, got.origin) == (original.seq, original.timestamp_ns, original.origin)
    assert got.intrinsics == original.intrinsics
    np.testing.assert_array_equal(got.color, original.color)
    assert got.depth.dtype == np.float32
    np.testing.assert_array_equal(got.depth, want.depth)
    np.testing.assert_array_equal(got.pose, original.pose)


def test_replay_is_exact(tmp_path, originals):
    path = _record(tmp_path / "rec.mcap", originals, depth_scale=5000.0)
    src = open_source(f"mcap:{path}")
    assert "mcap" in SOURCE_KINDS and isinstance(src, Source) and isinstance(src, McapSource)
    assert len(src) == 5 and src.indexed and src.stream == "cam0"
    assert src.intrinsics == originals[0].intrinsics and src.has_ground_truth
    assert src.depth_scale == 5000.0 and src.color_encoding == "raw"
    assert src.fps == pytest.approx(open_source(SPEC).fps)
    got = list(src)
    assert len(got) == 5
    for g, o in zip(got, originals):
        _same(g, o, depth_scale=5000.0)
    assert list(open_source(f"mcap:{path},stream=cam0"))[4].seq == 4  # iterable again, stream explicit


def test_corrupted_message_gives_a_badframe_and_the_stream_goes_on(tmp_path, originals, caplog):
    path = _record(tmp_path / "bad.mcap", originals, corrupt=2)
    src = open_source(f"mcap:{path}")
    with caplog.at_level(logging.WARNING):
        got = list(src)
    assert [type(g) for g in got] == [RGBDFrame, RGBDFrame, BadFrame, RGBDFrame, RGBDFrame]
    bad = got[2]
    assert str(path) in bad.error and "message 2" in bad.error and "log time" in bad.error
    assert "wire:" in bad.error and "truncated" in bad.error
    assert bad.seq == 2  # unreadable envelope: the next expected seq and time
    assert abs(bad.timestamp_ns - originals[2].timestamp_ns) <= 1000
    assert str(path) in bad.origin and str(path) in caplog.text
    for g, o in zip(got[3:], originals[3:]):
        _same(g, o)


def test_first_message_corrupt_still_opens(tmp_path, originals):
    path = _record(tmp_path / "bad0.mcap", originals, corrupt=0)
    src = open_source(f"mcap:{path}")
    assert src.intrinsics == originals[1].intrinsics and len(src) == 5
    got = list(src)
    assert isinstance(got[0], BadFrame) and got[0].seq == 0 and all(isinstance(g, RGBDFrame) for g in got[1:])


def test_recording_without_footer_is_streamed(tmp_path, originals):
    path = tmp_path / "full.mcap"
    with Recorder(path, chunk_size=1) as rec:  # one chunk per message, as flushes would make
        for f in originals:
            rec.write(key("cam0", "frame"), encode_frame(f, "cam0", color="raw", depth="raw"),
                      log_time_ns=f.timestamp_ns)
    data = path.read_bytes()
    cut = tmp_path / "killed.mcap"
    cut.write_bytes(data[: len(data) - 200])  # footer and summary gone, every chunk intact
    src = open_source(f"mcap:{cut}")
    assert not src.indexed and "footer" in src.problem and len(src) == 5
    got = list(src)
    assert len(got) == 5
    for g, o in zip(got, originals):
        _same(g, o)
    # torn inside the last chunk: the complete chunks before it are replayed
    cut.write_bytes(data[: len(data) * 9 // 10])
    src = open_source(f"mcap:{cut}")
    got = list(src)
    assert len(src) == len(got) == 4 and src.stopped_at
    for g, o in zip(got, originals):
        _same(g, o)


def test_two_streams_need_a_choice(tmp_path, originals):
    path = _record(tmp_path / "two.mcap", originals[:2], streams=("left", "right"))
    assert recorded_streams(path) == {"left": 2, "right": 2}
    with pytest.raises(SourceError) as e:
        open_source(f"mcap:{path}")
    assert "left (2 frames)" in str(e.value) and "right (2 frames)" in str(e.value) and "stream=" in str(e.value)
    src = open_source(f"mcap:{path},stream=right")
    assert src.stream == "right" and len(src) == 2 and src.name.endswith("stream=right")
    assert all(isinstance(g, RGBDFrame) for g in src)
    with pytest.raises(SourceError, match="left"):
        open_source(f"mcap:{path},stream=middle")


def test_open_errors(tmp_path):
    with pytest.raises(SourceError, match="not found"):
        open_source(f"mcap:{tmp_path / 'nope.mcap'}")
    with pytest.raises(SourceError, match="unknown option"):
        open_source(f"mcap:{tmp_path / 'nope.mcap'},fps=3")
    with pytest.raises(SourceError, match="needs a recording"):
        open_source("mcap:")
    empty = tmp_path / "empty.mcap"
    with Recorder(empty) as rec:
        rec.write(key("cam0", "stats"), b"x", log_time_ns=1)
    with pytest.raises(SourceError, match="no frame messages"):
        open_source(f"mcap:{empty}")
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"this is not an mcap file")
    with pytest.raises(SourceError, match="no frame messages"):
        open_source(f"mcap:{junk}")


def test_frames_whose_jpeg_was_stored_apart_replay_byte_for_byte(tmp_path, originals):
    """As the recorder stores them: each JPEG in its Foxglove image record, the frame message
    referencing it; the source hands out the exact wire bytes, indexed or streamed (no footer)."""
    from quick_stream.io import foxglove
    from quick_stream.io.recording_images import write_message

    path = tmp_path / "apart.mcap"
    sent = [encode_frame(f, "cam0", color="jpeg", depth="zstd", pub_ns=5 + i) for i, f in enumerate(originals)]
    with Recorder(path, chunk_size=1) as rec:
        foxglove.register_channels(rec, "cam0")
        for i, data in enumerate(sent):
            t = 10**9 + originals[i].timestamp_ns
            write_message(lambda topic, d: rec.write(topic, d, log_time_ns=t), key("cam0", "frame"), data, t)
    src = open_source(f"mcap:{path}")
    assert src.indexed and src.color_encoding == "jpeg"
    assert [d for _, d in src.iter_with_messages()] == sent
    data = path.read_bytes()
    cut = tmp_path / "killed.mcap"
    cut.write_bytes(data[: len(data) - 200])  # footer and summary gone
    src = open_source(f"mcap:{cut}")
    assert not src.indexed
    items = list(src.iter_with_messages())
    assert [d for _, d in items] == sent and all(isinstance(f, RGBDFrame) for f, _ in items)

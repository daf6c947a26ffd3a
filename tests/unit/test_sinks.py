"""The render's file sinks: the background writer keeps every frame and reports what is on disk."""
from __future__ import annotations

import re
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from quick_stream.io.sinks import BackgroundSink, VideoSink
from quick_stream.io.video_check import video_frames


class GatedSink(VideoSink):
    """A PNG sink whose writes wait until the test opens the gate."""

    def __init__(self, png_dir: Path) -> None:
        super().__init__(None, png_dir, 30.0)
        self.gate = threading.Event()

    def write(self, seq: int, image: np.ndarray, jpeg: bytes | None = None) -> None:
        self.gate.wait()
        super().write(seq, image, jpeg)


def test_drain_returns_once_every_accepted_frame_is_on_disk(tmp_path):
    sink = GatedSink(tmp_path)
    on_disk_at_return: list[int] = []
    with BackgroundSink(sink) as bg:
        for seq in range(5):
            bg.write(seq, np.full((8, 8, 3), seq, np.uint8))
        assert bg.frames == 5  # accepted, none written yet: the gate is closed

        def drain() -> None:
            bg.drain()
            on_disk_at_return.append(len(list(tmp_path.glob("*.png"))))

        t = threading.Thread(target=drain)
        t.start()
        sink.gate.set()
        t.join()
    assert on_disk_at_return == [5]


def test_drain_reports_the_writers_error(tmp_path):
    blocker = tmp_path / "not-a-dir"
    blocker.write_text("a file where the PNG folder should be")
    sink = VideoSink(None, tmp_path / "png", 30.0)
    sink.png_dir = blocker  # every write fails
    bg = BackgroundSink(sink)
    bg.write(0, np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(OSError, match="cannot write"):
        bg.drain()
    with pytest.raises(OSError):
        bg.close()


def _frames(n: int, h: int = 48, w: int = 64) -> list[np.ndarray]:
    rng = np.random.default_rng(7)
    return [cv2.GaussianBlur(rng.integers(0, 256, (h, w, 3), dtype=np.uint8), (9, 9), 0) for _ in range(n)]


def _packets(path: Path) -> list[bytes]:
    """The video's frames as stored (encoded packets, not decoded)."""
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    assert cap.set(cv2.CAP_PROP_FORMAT, -1)
    out = []
    while (got := cap.read())[0]:
        out.append(got[1].tobytes())
    return out


def test_mjpeg_stores_the_jpegs_it_is_given_as_they_are(tmp_path):
    frames = _frames(6)
    given = [cv2.imencode(".jpg", f, [cv2.IMWRITE_JPEG_QUALITY, 60])[1].tobytes() for f in frames]
    with BackgroundSink(VideoSink(tmp_path / "v.mp4", None, 30.0, "mjpeg", quality=95)) as bg:
        for seq, (f, j) in enumerate(zip(frames, given)):
            bg.write(seq, f, j if seq != 3 else None)  # frame 3 without its JPEG: encoded by the sink
    stored = _packets(tmp_path / "v.mp4")
    assert len(stored) == 6
    assert [s == g for s, g in zip(stored, given)] == [True, True, True, False, True, True]
    assert stored[3] == cv2.imencode(".jpg", frames[3], [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
    cap = cv2.VideoCapture(str(tmp_path / "v.mp4"))
    assert cap.get(cv2.CAP_PROP_FPS) == pytest.approx(30.0)
    for f, jpeg in zip(frames, stored):
        ok, img = cap.read()  # FFmpeg's decoder, as players decode: the JPEG's image, to its rounding
        assert ok and img.shape == f.shape and cv2.PSNR(img, cv2.imdecode(np.frombuffer(jpeg, np.uint8), 1)) > 30


@pytest.mark.parametrize("suffix,tag", [(".avi", "MJPG"), (".mkv", "[0][0][0][0]"), (".mov", "jpeg")])
def test_mjpeg_goes_under_its_own_tag_with_no_notice(tmp_path, capfd, suffix, tag):
    """Motion JPEG in its containers is tagged as such (Matroska names it by its codec id, no tag), with
    no OpenCV notice: ``up`` logged "tag 'MJPG' is not supported ... fallback to use tag 'mp4v'" on every
    run, its .mp4 holding Motion JPEG under 'mp4v' (now its video is .avi); the .mov got the notice too."""
    import shutil
    import subprocess

    path = tmp_path / f"v{suffix}"
    with VideoSink(path, None, 30.0, "mjpeg") as sink:
        for seq, f in enumerate(_frames(3)):
            sink.write(seq, f)
    assert "OpenCV" not in capfd.readouterr().err
    assert video_frames(path) == 3
    if shutil.which("ffprobe"):
        probe = subprocess.run(["ffprobe", "-v", "error", "-show_entries", "stream=codec_name,codec_tag_string",
                                "-of", "csv=p=0", str(path)], capture_output=True, text=True, check=True)
        assert probe.stdout.strip() == f"mjpeg,{tag}"


def test_each_codec_has_a_container_named_by_its_tag():
    from quick_stream.io.sinks import MJPEG_TAGS, VIDEO_SUFFIX

    assert VIDEO_SUFFIX == {"mjpeg": ".avi", "mp4v": ".mp4"}
    assert MJPEG_TAGS[VIDEO_SUFFIX["mjpeg"]] == "MJPG"


def test_a_frame_of_another_size_is_letterboxed_into_the_video_whatever_its_codec(tmp_path):
    for codec in ("mjpeg", "mp4v"):
        big, small = _frames(1)[0], _frames(1, 24, 32)[0]
        jpeg = cv2.imencode(".jpg", small)[1].tobytes()  # of the small frame: not what the video can store
        sink = VideoSink(tmp_path / f"{codec}.mp4", tmp_path / codec, 25.0, codec)
        sink.write(0, big)
        sink.write(1, small, jpeg)
        sink.close()
        assert sink.resized == 1
        assert cv2.imread(str(tmp_path / codec / "000001.png")).shape == small.shape  # a PNG keeps its size
        cap = cv2.VideoCapture(str(tmp_path / f"{codec}.mp4"))
        shapes = [img.shape for ok, img in iter(cap.read, (False, None)) if ok]
        assert shapes == [big.shape, big.shape], codec


def test_an_unknown_video_codec_is_refused():
    with pytest.raises(ValueError, match="video codec must be one of"):
        VideoSink("x.mp4", None, 30.0, "h264")


# ---------------------------------------------------------------- a write that fails is an error

CHILD = r"""
import json, resource, sys
from pathlib import Path
import cv2, numpy as np
from quick_stream.io import sinks
limit, path, codec, n, blind = int(sys.argv[1]), Path(sys.argv[2]), sys.argv[3], int(sys.argv[4]), sys.argv[5] == "1"
if blind:  # a failure the free space does not show (a quota, an I/O error): only the file can tell
    sinks.room_left = lambda p, size: (1 << 40, "blind")
resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))  # Python ignores SIGXFSZ: writes fail with EFBIG
rng = np.random.default_rng(3)
error = None
bg = sinks.BackgroundSink(sinks.VideoSink(path, None, 30.0, codec))
try:
    for seq in range(n):
        bg.write(seq, cv2.GaussianBlur(rng.integers(0, 256, (240, 320, 3), dtype=np.uint8), (3, 3), 0))
    bg.close()
except OSError as e:
    error = str(e)
print(json.dumps({"error": error, "written": getattr(bg, "written", None)}))
"""


def write_under_limit(tmp_path: Path, limit: int, codec: str, n: int, blind: bool = False) -> tuple[Path, dict]:
    """``n`` noisy 320x240 frames (~25 KB each in mp4v, ~40 KB in Motion JPEG) to a video in a child
    process whose files may not grow past ``limit`` bytes; ``blind``: the sink cannot see the limit
    (only the file tells)."""
    import json
    import subprocess
    import sys

    video = tmp_path / f"v-{codec}.mp4"
    done = subprocess.run([sys.executable, "-c", CHILD, str(limit), str(video), codec, str(n), str(int(blind))],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return video, json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("codec", ["mp4v", "mjpeg"])
def test_a_video_that_reaches_the_file_size_limit_stops_with_a_complete_file(codec, tmp_path):
    video, got = write_under_limit(tmp_path, 1_000_000, codec, 80)
    assert got["error"] is not None, "80 frames of 25-40 KB cannot fit in 1 MB: the sink must say so"
    assert got["error"].startswith(f"{video}: writing stopped at frame ")
    assert "bytes left under the file-size limit of 1000000 bytes" in got["error"]
    # stopped with room for what the encoder held and the index: the frames before are kept, playable
    assert 0 < got["written"] < 80 and f"closed complete with its first {got['written']} frames" in got["error"]
    assert video_frames(video) == got["written"]


def test_a_failure_the_free_space_does_not_show_is_found_in_the_file(tmp_path):
    # mp4v: the encoder's output size is not known, so the file is checked when it is closed
    video, got = write_under_limit(tmp_path, 1_000_000, "mp4v", 80, blind=True)
    assert got["error"] is not None and got["written"] == 0
    assert got["error"].startswith(f"{video}: incomplete video file (1000000 bytes): no 'moov' box")
    # Motion JPEG: the sink knows each frame's bytes and sees the file stop growing while it writes
    video, got = write_under_limit(tmp_path, 1_000_000, "mjpeg", 80, blind=True)
    assert got["error"] is not None
    stopped = re.match(rf"{re.escape(str(video))}: writing stopped at frame (\d+): the file stopped growing",
                       got["error"])
    assert stopped and int(stopped[1]) < 79, got["error"]  # while writing, not only when closed
    assert "incomplete video file" in got["error"]
    assert got["written"] == 0

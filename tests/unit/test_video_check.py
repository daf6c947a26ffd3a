"""A video file is complete only when its container says so: sizes that add up to the file, the
index written on close (MP4 'moov', AVI 'idx1', MKV 'Cues') and the frames counted from it."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from quick_stream.io.video_check import IncompleteVideo, video_frames

CASES = [("mp4v", ".mp4"), ("mjpeg", ".mp4"), ("mp4v", ".avi"), ("mjpeg", ".avi"), ("mp4v", ".mkv"),
         ("mjpeg", ".mkv"), ("mp4v", ".mov"), ("mp4v", ".m4v")]


def make_video(path: Path, codec: str, n: int = 23) -> Path:
    rng = np.random.default_rng(5)
    base = cv2.GaussianBlur(rng.integers(0, 256, (48, 64, 3), dtype=np.uint8), (5, 5), 0)
    if codec == "mp4v":
        w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (64, 48))
    else:
        w = cv2.VideoWriter(str(path), cv2.CAP_FFMPEG, cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (64, 48),
                            [cv2.VIDEOWRITER_PROP_RAW_VIDEO, 1])
    assert w.isOpened()
    for i in range(n):
        f = np.roll(base, 2 * i, axis=1)
        w.write(f if codec == "mp4v" else cv2.imencode(".jpg", f)[1].reshape(1, -1))
    w.release()
    return path


@pytest.mark.parametrize("codec,suffix", CASES)
def test_a_complete_file_counts_its_frames_and_any_cut_is_refused(codec, suffix, tmp_path):
    video = make_video(tmp_path / f"v{suffix}", codec)
    assert video_frames(video) == 23
    data = video.read_bytes()
    cut = tmp_path / f"cut{suffix}"
    for n in sorted({0, 7, 8, 100, len(data) // 2, len(data) - 1, *range(0, len(data), max(1, len(data) // 40))}):
        cut.write_bytes(data[:n])
        with pytest.raises(IncompleteVideo, match=f"{cut}: "):
            video_frames(cut)
    cut.write_bytes(data + bytes(10))  # zeros after the end (blocks allocated, never written)
    with pytest.raises(IncompleteVideo, match="incomplete video file"):
        video_frames(cut)


def test_an_mp4_never_closed_says_its_index_is_missing(tmp_path):
    data = make_video(tmp_path / "v.mp4", "mp4v").read_bytes()
    moov = data.index(b"moov") - 4
    (tmp_path / "open.mp4").write_bytes(data[:moov])  # what a writer that never finished leaves
    with pytest.raises(IncompleteVideo, match="no 'moov' box"):
        video_frames(tmp_path / "open.mp4")


def test_a_missing_file_is_named(tmp_path):
    with pytest.raises(IncompleteVideo, match="nothing.mp4: the video file is missing"):
        video_frames(tmp_path / "nothing.mp4")

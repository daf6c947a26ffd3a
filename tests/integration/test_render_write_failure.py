"""The render's video on a full disk (a file-size limit here, which fails the same way): the first
write that fails stops the render as the recorder's does (exit 2, not restarted), logged with the
file and the frame; its last stats say ``state`` ``error``, carry the message in ``error`` and
count in ``frames_written`` the frames the file holds, a complete file (issue 30 row 2). Before,
OpenCV logged hundreds of "Failed to write frame" lines, the render "N frames written" and exit 0."""
from __future__ import annotations

import time

from quick_stream.io.video_check import video_frames
from tests.helpers import pipeline, recorded

LIMIT = 1_000_000  # 120 frames of ~20 KB (320x240 JPEG) do not fit


def test_a_video_that_cannot_be_written_stops_the_render_and_says_so(tmp_path):
    video = tmp_path / "v.mp4"
    capture = ["--source", "synthetic:frames=120,width=320,height=240", "--fps", "15"]
    sup, _ = pipeline(tmp_path, render=["--output", str(video), "--fsize", str(LIMIT)], capture=capture,
                      render_module="tests.tools.fsize_render")
    try:
        render, log = sup.children["render"], tmp_path / "logs" / "render.log"
        deadline = time.monotonic() + 240  # a failure guard only: the render stops on its own
        while not render.finished and time.monotonic() < deadline:
            if log.exists() and "end of stream" in log.read_text():
                break  # went on to the end of the stream: the failure went unnoticed
            sup.poll()
            time.sleep(0.2)
    finally:
        codes = sup.stop()
    text = log.read_text()
    assert render.exits and render.exits[-1][1] == 2, (codes, text[-2000:])
    assert render.restarts == 0
    assert f"{video}: writing stopped at frame " in text and "the service stops" in text
    stats, _ = recorded(tmp_path / "rec.mcap")
    r = stats["render"]
    assert r["state"] == "error" and r["error"].startswith(f"{video}: writing stopped at frame ")
    assert "file-size limit" in r["error"]
    assert 0 < r["frames_written"] == video_frames(video) < 120  # the frames before, in a complete file

"""The render's file sinks: the background writer keeps every frame and reports what is on disk."""
from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from quick_stream.io.sinks import BackgroundSink, VideoSink


class GatedSink(VideoSink):
    """A PNG sink whose writes wait until the test opens the gate."""

    def __init__(self, png_dir: Path) -> None:
        super().__init__(None, png_dir, 30.0)
        self.gate = threading.Event()

    def write(self, seq: int, image: np.ndarray) -> None:
        self.gate.wait()
        super().write(seq, image)


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

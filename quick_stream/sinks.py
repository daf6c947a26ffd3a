"""Where stabilized frames go on disk: an MP4 file and/or numbered PNGs (offline and render service)."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np


class VideoSink:
    """Writes BGR frames to ``mp4`` (opened at the first frame, its size) and/or ``png_dir``."""

    def __init__(self, mp4: str | Path | None, png_dir: str | Path | None, fps: float) -> None:
        self.mp4 = Path(mp4) if mp4 else None
        self.png_dir = Path(png_dir) if png_dir else None
        self.fps = fps
        self.frames = 0
        self._writer: cv2.VideoWriter | None = None
        if self.png_dir:
            self.png_dir.mkdir(parents=True, exist_ok=True)

    def write(self, seq: int, image: np.ndarray) -> None:
        if self.mp4 is not None:
            if self._writer is None:
                self.mp4.parent.mkdir(parents=True, exist_ok=True)
                h, w = image.shape[:2]
                self._writer = cv2.VideoWriter(str(self.mp4), cv2.VideoWriter_fourcc(*"mp4v"), self.fps, (w, h))
                if not self._writer.isOpened():
                    raise OSError(f"cannot open video writer for {self.mp4}")
            self._writer.write(image)
        if self.png_dir is not None:
            path = self.png_dir / f"{seq:06d}.png"
            if not cv2.imwrite(str(path), image):
                raise OSError(f"cannot write {path}")
        self.frames += 1

    def close(self) -> None:
        if self._writer is not None:
            self._writer.release()
            self._writer = None

    def __enter__(self) -> "VideoSink":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

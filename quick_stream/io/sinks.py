"""Where stabilized frames go on disk: an MP4 file and/or numbered PNGs (offline and render service).

The video's codec (:data:`VIDEO_CODECS`): ``mp4v`` (MPEG-4 Part 2) encodes every frame here,
about 2.5 ms of CPU a 640x480 frame; ``mjpeg`` (Motion JPEG) stores each frame as a JPEG, and
a frame given with its JPEG (the render service's, the one it publishes) is stored as it is,
with no second encode (about 0.03 ms). Measured on 7-Scenes frames at JPEG quality 90: mp4v
files are a third of the size; mjpeg frames are 44 dB from the rendered frame (PSNR, decoded by
FFmpeg) against 36 dB for mp4v. Both play in FFmpeg-based players (VLC, mpv); neither in a web
browser. OpenCV names the MP4's Motion JPEG tag itself: it prints one notice on stderr when it
opens the file ("tag ... 'MJPG' is not supported ... fallback to use tag 'mp4v'")."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..stream.wire import WireError, encode_image

VIDEO_CODECS = ("mjpeg", "mp4v")
MJPEG_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv")  # the video files FFmpeg writes Motion JPEG into (not .m4v)


def check_video(path: str | Path | None, codec: str, flag: str = "--output") -> None:
    """ValueError naming ``flag`` when the video file ``path`` (None or "": none) cannot hold ``codec``."""
    if codec not in VIDEO_CODECS:
        raise ValueError(f"video codec must be one of {VIDEO_CODECS}, got {codec!r}")
    if path and codec == "mjpeg" and Path(path).suffix.lower() not in MJPEG_SUFFIXES:
        raise ValueError(f"{flag} {path}: a {Path(path).suffix} file cannot hold Motion JPEG; name it "
                         f"{'/'.join(MJPEG_SUFFIXES)} or give --video-codec mp4v")


def fit(image: np.ndarray, w: int, h: int) -> np.ndarray:
    """``image`` scaled to fit ``w`` x ``h`` keeping its aspect, centred on black (letterbox)."""
    ih, iw = image.shape[:2]
    s = min(w / iw, h / ih)
    nw, nh = max(1, min(w, round(iw * s))), max(1, min(h, round(ih * s)))
    out = np.zeros((h, w, 3), np.uint8)
    x, y = (w - nw) // 2, (h - nh) // 2
    out[y:y + nh, x:x + nw] = cv2.resize(image, (nw, nh), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
    return out


class VideoSink:
    """Writes BGR frames to ``mp4`` (opened at the first frame, its size) and/or ``png_dir``.

    A video file has one frame size: a frame of another size (the camera's resolution
    changed mid-stream) is letterboxed into it and counted in ``resized``; PNGs keep
    every frame's own size. ``codec``: one of :data:`VIDEO_CODECS` (module docstring); ``quality``:
    the JPEG quality of the frames ``mjpeg`` encodes itself."""

    def __init__(self, mp4: str | Path | None, png_dir: str | Path | None, fps: float, codec: str = "mp4v",
                 quality: int = 90) -> None:
        check_video(mp4, codec)
        self.mp4 = Path(mp4) if mp4 else None
        self.png_dir = Path(png_dir) if png_dir else None
        self.fps = fps
        self.codec = codec
        self.quality = int(quality)
        self.frames = 0
        self.resized = 0
        self._size: tuple[int, int] | None = None
        self._writer: cv2.VideoWriter | None = None
        if self.png_dir:
            self.png_dir.mkdir(parents=True, exist_ok=True)

    def write(self, seq: int, image: np.ndarray, jpeg: bytes | None = None) -> None:
        """Frame ``seq``; ``jpeg``: the same image as a JPEG, which ``mjpeg`` stores as it is."""
        if self.mp4 is not None:
            if self._writer is None:
                self._open(image.shape[1], image.shape[0])
            frame = image
            if (image.shape[1], image.shape[0]) != self._size:
                self.resized += 1
                frame, jpeg = fit(image, *self._size), None  # the PNG keeps the frame's own size
            if self.codec == "mp4v":
                self._writer.write(frame)
            else:
                if jpeg is None:  # the wire's JPEG of the frame, at the sink's quality
                    try:
                        jpeg = encode_image(frame, "jpeg", self.quality)["data"]
                    except WireError as e:
                        raise OSError(f"cannot encode frame {seq} as JPEG for {self.mp4}: {e}") from None
                self._writer.write(np.frombuffer(jpeg, np.uint8).reshape(1, -1))
        if self.png_dir is not None:
            path = self.png_dir / f"{seq:06d}.png"
            if not cv2.imwrite(str(path), image):
                raise OSError(f"cannot write {path}")
        self.frames += 1

    def _open(self, w: int, h: int) -> None:
        self.mp4.parent.mkdir(parents=True, exist_ok=True)
        if self.codec == "mp4v":
            self._writer = cv2.VideoWriter(str(self.mp4), cv2.VideoWriter_fourcc(*"mp4v"), self.fps, (w, h))
        else:  # each frame an encoded JPEG, muxed as it is
            self._writer = cv2.VideoWriter(str(self.mp4), cv2.CAP_FFMPEG, cv2.VideoWriter_fourcc(*"MJPG"), self.fps,
                                           (w, h), [cv2.VIDEOWRITER_PROP_RAW_VIDEO, 1])
        if not self._writer.isOpened():
            raise OSError(f"cannot open a {self.codec} video writer for {self.mp4}")
        self._size = (w, h)

    def close(self) -> None:
        if self._writer is not None:
            self._writer.release()
            self._writer = None

    def __enter__(self) -> "VideoSink":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class BackgroundSink:
    """A :class:`VideoSink` written from a worker thread (OpenCV encodes without the GIL), so
    publishing a frame never waits for the file. The queue is bounded; when it is full
    ``write`` waits (frames are never dropped from the file). Errors surface on close."""

    def __init__(self, sink: VideoSink, max_queued: int = 64) -> None:
        import queue
        import threading

        self.sink = sink
        self._q: "queue.Queue[tuple[int, np.ndarray, bytes | None] | None]" = queue.Queue(max_queued)
        self._error: BaseException | None = None
        self._accepted = 0
        self._thread = threading.Thread(target=self._run, name="video-sink", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while (item := self._q.get()) is not None:
            if self._error is None:
                try:
                    self.sink.write(*item)
                except BaseException as e:  # noqa: BLE001 - reported on close
                    self._error = e
            self._q.task_done()

    @property
    def frames(self) -> int:
        """Frames accepted for the file (written, or queued: none is dropped); the worker may be
        behind until :meth:`drain` returns."""
        return self._accepted

    @property
    def resized(self) -> int:
        return self.sink.resized

    def write(self, seq: int, image: np.ndarray, jpeg: bytes | None = None) -> None:
        if self._error is not None:
            raise self._error
        self._q.put((seq, image, jpeg))
        self._accepted += 1

    def drain(self) -> None:
        """Wait until every accepted frame has reached the sink (a PNG is on disk; an MP4 frame is
        in the encoder, finished on close), so what is reported written is readable. Raises the
        worker's error, if any."""
        if self._thread.is_alive():
            self._q.join()
        if self._error is not None:
            raise self._error

    def close(self) -> None:
        if self._thread.is_alive():
            self._q.put(None)
            self._thread.join()
        self.sink.close()
        if self._error is not None:
            raise self._error

    def __enter__(self) -> "BackgroundSink":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

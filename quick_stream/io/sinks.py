"""Where stabilized frames go on disk: an MP4 file and/or numbered PNGs (offline and render service).

The video's codec (:data:`VIDEO_CODECS`): ``mp4v`` (MPEG-4 Part 2) encodes every frame here,
about 2.5 ms of CPU a 640x480 frame; ``mjpeg`` (Motion JPEG) stores each frame as a JPEG, and
a frame given with its JPEG (the render service's, the one it publishes) is stored as it is,
with no second encode (about 0.03 ms). Measured on 7-Scenes frames at JPEG quality 90: mp4v
files are a third of the size; mjpeg frames are 44 dB from the rendered frame (PSNR, decoded by
FFmpeg) against 36 dB for mp4v. Both play in FFmpeg-based players (VLC, mpv); neither in a web
browser.

Each codec has its container (:data:`VIDEO_SUFFIX`, the name ``up`` gives its video): Motion JPEG
goes under its own tag into ``.avi`` and ``.mkv`` (``MJPG``) and ``.mov`` (``jpeg``), with no
notice from OpenCV. An ``.mp4`` has no Motion JPEG tag: FFmpeg stores it under MP4's generic
``mp4v`` sample entry (object type JPEG, which FFmpeg-based players read), and OpenCV prints a
notice on stderr when it opens the file ("tag ... 'MJPG' is not supported ... fallback to use tag
'mp4v'"); mp4v is what an ``.mp4`` is for.

A write that fails is an error naming the file and the frame, never a silent success. OpenCV's
``VideoWriter.write`` returns nothing (FFmpeg only warns "Failed to write frame" on stderr), so the
sink watches the file: after each frame, the room it has left (free space on its filesystem, the
process's file-size limit) must stay above :data:`RESERVE_BYTES`, and a Motion JPEG file must have
grown by what it was given (less FFmpeg's buffer, 256 KiB measured: :data:`STALL_BYTES`). When
either fails the video is closed at once, so the frames before are kept in a complete file where
the room allows. On close the container is read back (:mod:`.video_check`): a file that is not
complete, or holds fewer frames than were given, is an error. PNGs are encoded here and written
by Python (:func:`.files.write_file`), whose write raises on a short write."""
from __future__ import annotations

import logging
import os
import resource
import threading
from pathlib import Path

import cv2
import numpy as np

from ..stream.wire import WireError, encode_image
from .files import write_file
from .video_check import IncompleteVideo, video_frames

VIDEO_CODECS = ("mjpeg", "mp4v")
MJPEG_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv")  # the video files FFmpeg writes Motion JPEG into (not .m4v)
# Motion JPEG's own tag in each container (FFmpeg's tables); .mp4 has none (OpenCV's notice, then 'mp4v')
MJPEG_TAGS = {".avi": "MJPG", ".mkv": "MJPG", ".mov": "jpeg", ".mp4": "MJPG"}
VIDEO_SUFFIX = {"mjpeg": ".avi", "mp4v": ".mp4"}  # each codec's container, whose tag names it
# The video stops when less room than this is left: FFmpeg's buffer (256 KiB) and the index it writes
# on close (~16 B a frame) still fit, so the file closes complete with the frames before.
RESERVE_BYTES = 512 * 1024
STALL_BYTES = 1 << 20  # a Motion JPEG file this far (plus 4 frames) behind what it was given has stopped growing


class VideoWriteError(OSError):
    """A frame the video (or PNG) sink could not write; the message names the file, the frame and
    what the file holds now."""


def room_left(path: Path, size: int) -> tuple[int, str]:
    """Bytes the file ``path`` (now ``size`` bytes) may still grow by, and what bounds it: its
    filesystem's free space (root's, reserved blocks included, for root) or the process's
    file-size limit (``RLIMIT_FSIZE``, e.g. ``prlimit --fsize``)."""
    st = os.statvfs(path.parent)
    free = (st.f_bfree if os.geteuid() == 0 else st.f_bavail) * st.f_frsize
    room, why = free, f"{free} bytes free on its filesystem"
    soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    if soft != resource.RLIM_INFINITY and soft - size < room:
        room, why = soft - size, f"{max(soft - size, 0)} bytes left under the file-size limit of {soft} bytes"
    return room, why


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
    the JPEG quality of the frames ``mjpeg`` encodes itself. ``frames``: the frames written (after a
    failure, those the video file holds); ``failed``: the first write error (the sink writes no more)."""

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
        self.failed: VideoWriteError | None = None
        self._size: tuple[int, int] | None = None
        self._writer: cv2.VideoWriter | None = None
        self._given = self._largest = 0  # Motion JPEG bytes given to the writer, the largest frame's
        if self.png_dir:
            self.png_dir.mkdir(parents=True, exist_ok=True)

    def write(self, seq: int, image: np.ndarray, jpeg: bytes | None = None) -> None:
        """Frame ``seq``; ``jpeg``: the same image as a JPEG, which ``mjpeg`` stores as it is.
        :class:`VideoWriteError` when it cannot be written (and on every call after)."""
        if self.failed is not None:
            raise self.failed
        if self.mp4 is not None:
            self._write_video(seq, image, jpeg)
        if self.png_dir is not None:
            self._write_png(seq, image)
        self.frames += 1

    def _write_video(self, seq: int, image: np.ndarray, jpeg: bytes | None) -> None:
        if self._writer is None:
            self._open(image.shape[1], image.shape[0])
        frame = image
        if (image.shape[1], image.shape[0]) != self._size:
            self.resized += 1
            frame, jpeg = fit(image, *self._size), None  # the PNG keeps the frame's own size
        try:
            if self.codec == "mp4v":
                self._writer.write(frame)
            else:
                if jpeg is None:  # the wire's JPEG of the frame, at the sink's quality
                    try:
                        jpeg = encode_image(frame, "jpeg", self.quality)["data"]
                    except WireError as e:
                        self._fail(seq, f"cannot encode it as JPEG: {e}")
                self._writer.write(np.frombuffer(jpeg, np.uint8).reshape(1, -1))
                self._given += len(jpeg)
                self._largest = max(self._largest, len(jpeg))
        except cv2.error as e:
            self._fail(seq, f"OpenCV: {e}")
        try:
            size = self.mp4.stat().st_size
            room, why = room_left(self.mp4, size)
        except OSError as e:
            self._fail(seq, f"cannot see the file: {e.strerror or e}")
        if room < RESERVE_BYTES:
            self._fail(seq, f"{why}, less than the {RESERVE_BYTES} bytes the video keeps in reserve")
        if self.codec == "mjpeg" and self._given - size > STALL_BYTES + 4 * self._largest:
            self._fail(seq, f"the file stopped growing: {self._given} bytes of frames given, {size} on disk")

    def _write_png(self, seq: int, image: np.ndarray) -> None:
        path = self.png_dir / f"{seq:06d}.png"
        ok, buf = cv2.imencode(".png", image)
        if not ok:
            self._fail(seq, "cannot encode the PNG", path)
        try:
            write_file(path, buf.tobytes())  # never a cut-off PNG
        except OSError as e:
            self._fail(seq, f"cannot write the PNG: {e.strerror or e}", path)

    def _fail(self, seq: int, why: str, target: Path | None = None) -> None:
        """Stop writing at frame ``seq`` (``target``: the file that failed, default the video): close
        the video with what it holds (checked on disk) and raise."""
        target = target or self.mp4
        state = ""
        if self._writer is not None:
            self._release()
            name = "the file" if target == self.mp4 else str(self.mp4)
            try:
                self.frames = video_frames(self.mp4)
                state = f"; {name} was closed complete with its first {self.frames} frames"
            except IncompleteVideo as e:
                self.frames = 0
                state = f"; {e}"
        self.failed = VideoWriteError(f"{target}: writing stopped at frame {seq}: {why}{state}")
        raise self.failed

    def _open(self, w: int, h: int) -> None:
        self.mp4.parent.mkdir(parents=True, exist_ok=True)
        if self.codec == "mp4v":
            self._writer = cv2.VideoWriter(str(self.mp4), cv2.VideoWriter_fourcc(*"mp4v"), self.fps, (w, h))
        else:  # each frame an encoded JPEG, muxed as it is
            tag = MJPEG_TAGS[self.mp4.suffix.lower()]
            self._writer = cv2.VideoWriter(str(self.mp4), cv2.CAP_FFMPEG, cv2.VideoWriter_fourcc(*tag), self.fps,
                                           (w, h), [cv2.VIDEOWRITER_PROP_RAW_VIDEO, 1])
        if not self._writer.isOpened():
            self._writer = None
            self.failed = VideoWriteError(f"cannot open a {self.codec} video writer for {self.mp4}")
            raise self.failed
        self._size = (w, h)

    def _release(self) -> None:
        if self._writer is not None:
            self._writer.release()
            self._writer = None

    def close(self) -> None:
        """Close the video and check it on disk: :class:`VideoWriteError` when the file is not a
        complete container or holds fewer frames than were written (a failure already raised is
        not raised again)."""
        if self._writer is None:
            return
        self._release()
        if self.failed is not None:
            return
        try:
            held = video_frames(self.mp4)
        except IncompleteVideo as e:
            held, why = 0, str(e)
        else:
            why = f"{self.mp4}: the file holds {held} frames"
        if held != self.frames:
            given, self.frames = self.frames, held
            self.failed = VideoWriteError(f"{why}; {given} were written to it")
            raise self.failed

    def __enter__(self) -> "VideoSink":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

class BackgroundSink:
    """A :class:`VideoSink` written from a worker thread (OpenCV encodes without the GIL), so
    publishing a frame never waits for the file. The queue is bounded; when it is full
    ``write`` waits (frames are never dropped from the file). The worker's first error (it writes
    nothing after it) is :attr:`error` at once, and raised by the next ``write``, ``drain`` and ``close``."""

    def __init__(self, sink: VideoSink, max_queued: int = 64) -> None:
        import queue

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
    def written(self) -> int:
        """Frames the sink has written (after a failure: those the video file holds)."""
        return self.sink.frames

    @property
    def error(self) -> BaseException | None:
        """The first write error (None while every frame was written)."""
        return self._error

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
        try:
            self.sink.close()  # the video checked on disk
        except BaseException as e:  # noqa: BLE001 - raised below, after an earlier error if any
            if self._error is None:
                self._error = e
        if self._error is not None:
            raise self._error

    def __enter__(self) -> "BackgroundSink":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class FileOutput:
    """A service's files (``--output``, ``--png``) written from a :class:`BackgroundSink`: the first
    write that fails is logged once on ``log`` and sets ``stop`` (the service's stop event)."""

    def __init__(self, sink: BackgroundSink, stop: threading.Event, log: logging.Logger) -> None:
        self.sink, self.stop, self.log, self.reported = sink, stop, log, False

    def write(self, seq: int, image: np.ndarray, jpeg: bytes | None) -> None:
        if self.sink.error is None:
            self._then_check(self.sink.write, seq, image, jpeg)
        else:
            self.check()

    def check(self) -> None:
        if self.sink.error is not None and not self.reported:
            self.reported = True
            self.log.error("%s; the service stops: the file is not what was rendered (%d frames on disk)",
                           self.sink.error, self.sink.written)
            self.stop.set()

    def drain(self) -> None:
        self._then_check(self.sink.drain)

    def close(self) -> None:
        """Close the video (checked on disk)."""
        self._then_check(self.sink.close)

    def _then_check(self, call, *args: object) -> None:
        """``call(*args)`` on the sink; an error it raises is the sink's own (:attr:`error`), reported by
        :meth:`check`."""
        try:
            call(*args)
        except Exception:  # noqa: BLE001 - the sink's error, taken up by check()
            pass
        self.check()

    @property
    def frames(self) -> int:
        return self.sink.written

    @property
    def error(self) -> BaseException | None:
        return self.sink.error

    def stats(self) -> dict[str, object]:
        files = self.sink.sink.mp4 is not None or self.sink.sink.png_dir is not None
        return {"resized_frames": self.sink.resized, **({"frames_written": self.sink.written} if files else {}),
                **({"error": str(self.sink.error)} if self.sink.error is not None else {})}

"""Whether an output file on disk is whole, read back after its writer closed it (``quick-stream up``
says "wrote" only for those).

* Videos (MP4/MOV/M4V, AVI, MKV): the container read back by :func:`.video_check.video_frames`
  (its boxes, chunks or elements add up to the file and the index its writer adds last is there).
* MCAP: the magic bytes, then a footer and summary the reader can read
  (:func:`quick_stream.io.recording.read_messages`' own check).
* Anything else: it exists and is not empty.
"""
from __future__ import annotations

from pathlib import Path

from .video_check import IncompleteVideo, video_frames

VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".avi", ".mkv")


def incomplete(path: str | Path) -> str | None:
    """None when ``path`` is a whole file of its kind, else why not (in words, without the path)."""
    p = Path(path)
    try:
        size = p.stat().st_size
        if size == 0:
            return "empty"
        if p.suffix.lower() in VIDEO_SUFFIXES:
            video_frames(p)
            return None
        if p.suffix.lower() == ".mcap":
            return _mcap(p)
    except IncompleteVideo as e:
        return str(e).removeprefix(f"{p}: ")
    except FileNotFoundError:
        return "not there"
    except OSError as e:
        return f"cannot read it back: {e.strerror or e}"
    return None


def _mcap(p: Path) -> str | None:
    from .recording import RecordingError, _indexed_reader, open_recording

    try:
        with open_recording(p) as f:
            _indexed_reader(p, f)
    except RecordingError as e:
        return str(e).removeprefix(f"{p}: ")
    return None

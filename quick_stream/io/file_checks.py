"""Whether an output file on disk is whole, read back after its writer closed it (``quick-stream up``
says "wrote" only for those).

* MP4/MOV/M4V: the top-level boxes tile the file (a box that runs past the end: cut off) and one is
  the ``moov`` index, which the writer adds last (none: never closed, or the disk filled first).
* MCAP: the magic bytes, then a footer and summary the reader can read
  (:func:`quick_stream.io.recording.read_messages`' own check).
* Anything else: it exists and is not empty.
"""
from __future__ import annotations

import struct
from pathlib import Path

MP4_SUFFIXES = (".mp4", ".mov", ".m4v")


def incomplete(path: str | Path) -> str | None:
    """None when ``path`` is a whole file of its kind, else why not (in words, without the path)."""
    p = Path(path)
    try:
        size = p.stat().st_size
        if size == 0:
            return "empty"
        if p.suffix.lower() in MP4_SUFFIXES:
            return _mp4(p, size)
        if p.suffix.lower() == ".mcap":
            return _mcap(p)
    except FileNotFoundError:
        return "not there"
    except OSError as e:
        return f"cannot read it back: {e.strerror or e}"
    return None


def _mp4(p: Path, size: int) -> str | None:
    kinds = []
    with p.open("rb") as f:
        pos = 0
        while pos < size:
            f.seek(pos)
            head = f.read(16)
            if len(head) < 8:
                return f"cut off inside a box header at byte {pos}"
            n, kind = struct.unpack(">I4s", head[:8])
            if n == 1:
                if len(head) < 16:
                    return f"cut off inside a box header at byte {pos}"
                n = struct.unpack(">Q", head[8:16])[0]
            elif n == 0:  # "to the end of the file": what a writer that never finished leaves
                n = size - pos
            if n < 8 or pos + n > size:
                return f"box {kind!r} at byte {pos} declares {n} bytes, {size - pos} are there (cut off)"
            kinds.append(kind)
            pos += n
    if b"moov" not in kinds:
        return "no moov atom (the index a writer adds when it closes the file: never closed, or the disk filled)"
    return None


def _mcap(p: Path) -> str | None:
    from .recording import RecordingError, _indexed_reader, open_recording

    try:
        with open_recording(p) as f:
            _indexed_reader(p, f)
    except RecordingError as e:
        return str(e).removeprefix(f"{p}: ")
    return None

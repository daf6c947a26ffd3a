"""Is a video file complete? Its container's structure read back from disk, after the writer closed it.

OpenCV's ``VideoWriter.write`` returns nothing: a write FFmpeg could not make (a full disk, a file-size
limit) is a warning on stderr, and ``release`` writes the index it can. What is on disk decides:

* MP4/MOV/M4V: top-level boxes (``ftyp`` first, ``mdat`` and ``moov``) whose sizes add up to the file
  size; the frames are the video track's ``stsz`` sample count. A file cut off before it was closed
  has no ``moov`` (FFmpeg writes it last) or a box that runs past the end.
* AVI: ``RIFF`` chunks (``AVI ``, then ``AVIX`` past 1 GiB) whose sizes add up to the file size, an
  ``idx1`` index in a single-RIFF file; the frames are ``dmlh``'s (or ``avih``'s) total.
* MKV: the EBML header and one ``Segment`` of known size that add up to the file size, its elements
  of known sizes, ``Cues`` present; the frames are the clusters' blocks.
"""
from __future__ import annotations

import struct
from pathlib import Path
from typing import BinaryIO, Iterator


class IncompleteVideo(OSError):
    """The video file on disk is not a complete container (the message names the file and what is wrong)."""


def video_frames(path: str | Path) -> int:
    """The frames the complete video file ``path`` holds; :class:`IncompleteVideo` when it is missing,
    cut off, never closed or not the container its suffix names."""
    p = Path(path)
    try:
        size = p.stat().st_size
        with p.open("rb") as f:
            kind = p.suffix.lower()
            if kind in (".mp4", ".mov", ".m4v"):
                return _mp4(f, size)
            if kind == ".avi":
                return _avi(f, size)
            if kind == ".mkv":
                return _mkv(f, size)
            raise _Bad(f"cannot check a {kind or 'suffix-less'} file")
    except _Bad as e:
        raise IncompleteVideo(f"{p}: incomplete video file ({size} bytes): {e}") from None
    except FileNotFoundError:
        raise IncompleteVideo(f"{p}: the video file is missing") from None
    except OSError as e:
        raise IncompleteVideo(f"{p}: cannot read the video file back: {e.strerror or e}") from None


class _Bad(Exception):
    pass


def _read(f: BinaryIO, pos: int, n: int) -> bytes:
    f.seek(pos)
    b = f.read(n)
    if len(b) < n:
        raise _Bad(f"cut off at byte {pos + len(b)} (a header of {n} bytes at {pos})")
    return b


# --- MP4 / QuickTime -------------------------------------------------------------------------------

def _boxes(f: BinaryIO, start: int, end: int) -> Iterator[tuple[bytes, int, int]]:
    """(type, payload start, end) of each box from ``start`` to ``end``, checking that they tile it."""
    pos = start
    while pos < end:
        size, kind = struct.unpack(">I4s", _read(f, pos, 8))
        head = 8
        if size == 1:
            size, head = struct.unpack(">Q", _read(f, pos + 8, 8))[0], 16
        name = kind.decode("latin-1") if all(32 <= c < 127 for c in kind) else "0x" + kind.hex()
        if size == 0 and kind == b"mdat":  # to the end of the file (an unfinished FFmpeg file says so)
            size = end - pos
        if size < head:
            raise _Bad(f"box '{name}' at byte {pos} declares {size} bytes")
        if pos + size > end:
            raise _Bad(f"box '{name}' at byte {pos} declares {size} bytes, {end - pos} are there (cut off)")
        yield kind, pos + head, pos + size
        pos += size


def _child(f: BinaryIO, start: int, end: int, kind: bytes) -> tuple[int, int] | None:
    return next(((a, b) for k, a, b in _boxes(f, start, end) if k == kind), None)


def _mp4(f: BinaryIO, size: int) -> int:
    top = list(_boxes(f, 0, size))
    kinds = [k for k, _, _ in top]
    if not kinds or kinds[0] != b"ftyp":
        raise _Bad("it does not start with an 'ftyp' box")
    if b"mdat" not in kinds:
        raise _Bad("no 'mdat' box (no frame data)")
    if b"moov" not in kinds:
        raise _Bad("no 'moov' box (the index written when the file is closed: the writer never finished it)")
    _, a, b = top[kinds.index(b"moov")]
    for _, ta, tb in ((k, x, y) for k, x, y in _boxes(f, a, b) if k == b"trak"):
        mdia = _child(f, ta, tb, b"mdia")
        hdlr = mdia and _child(f, *mdia, b"hdlr")
        if hdlr is None or _read(f, hdlr[0] + 8, 4) != b"vide":
            continue
        minf = _child(f, *mdia, b"minf")
        stbl = minf and _child(f, *minf, b"stbl")
        stsz = stbl and _child(f, *stbl, b"stsz")
        if stsz is None:
            raise _Bad("the video track has no sample sizes ('stsz')")
        return struct.unpack(">I", _read(f, stsz[0] + 8, 4))[0]
    raise _Bad("no video track in 'moov'")


# --- AVI (RIFF) ----------------------------------------------------------------------------------

def _chunks(f: BinaryIO, start: int, end: int) -> Iterator[tuple[bytes, int, int]]:
    """(id, payload start, payload end) of each RIFF chunk from ``start`` to ``end`` (padded to even sizes)."""
    pos = start
    while pos < end:
        cid, n = struct.unpack("<4sI", _read(f, pos, 8))
        if pos + 8 + n > end:
            raise _Bad(f"chunk {cid!r} at byte {pos} declares {n} bytes, {end - pos - 8} are "
                       "there (cut off, or never closed)")
        yield cid, pos + 8, pos + 8 + n
        pos += 8 + n + (n & 1)


def _avi(f: BinaryIO, size: int) -> int:
    riffs = list(_chunks(f, 0, size))
    if not riffs or any(cid != b"RIFF" for cid, _, _ in riffs):
        raise _Bad("not a sequence of 'RIFF' chunks")
    _, a, b = riffs[0]
    if _read(f, a, 4) != b"AVI ":
        raise _Bad("the first RIFF chunk is not 'AVI '")
    kids = list(_chunks(f, a + 4, b))
    if len(riffs) == 1 and not any(cid == b"idx1" for cid, _, _ in kids):
        raise _Bad("no 'idx1' index (written when the file is closed)")
    frames = None
    for cid, ka, kb in kids:
        if cid == b"LIST" and _read(f, ka, 4) == b"hdrl":
            for hid, ha, hb in _chunks(f, ka + 4, kb):
                if hid == b"avih" and frames is None:
                    frames = struct.unpack("<I", _read(f, ha + 16, 4))[0]
                if hid == b"LIST" and _read(f, ha, 4) == b"odml":
                    dmlh = next(((x, y) for i, x, y in _chunks(f, ha + 4, hb) if i == b"dmlh"), None)
                    if dmlh is not None:
                        frames = struct.unpack("<I", _read(f, dmlh[0], 4))[0]
    if frames is None:
        raise _Bad("no 'avih' header")
    return frames


# --- Matroska (EBML) -------------------------------------------------------------------------------

_EBML, _SEGMENT, _CLUSTER, _CUES = 0x1A45DFA3, 0x18538067, 0x1F43B675, 0x1C53BB6B
_SIMPLE_BLOCK, _BLOCK_GROUP = 0xA3, 0xA0


def _vint(f: BinaryIO, pos: int, keep_marker: bool) -> tuple[int, int, bool]:
    """(value, length, all value bits set: an unknown size) of the EBML variable-size integer at ``pos``."""
    first = _read(f, pos, 1)[0]
    if first == 0:
        raise _Bad(f"a malformed element header at byte {pos}")
    n = 9 - first.bit_length()
    raw = int.from_bytes(_read(f, pos, n), "big")
    value = raw if keep_marker else raw & ((1 << (7 * n)) - 1)
    return value, n, (raw & ((1 << (7 * n)) - 1)) == (1 << (7 * n)) - 1


def _elements(f: BinaryIO, start: int, end: int) -> Iterator[tuple[int, int, int]]:
    """(id, payload start, payload end) of each EBML element from ``start`` to ``end``."""
    pos = start
    while pos < end:
        eid, n_id, _ = _vint(f, pos, keep_marker=True)
        n, n_size, unknown = _vint(f, pos + n_id, keep_marker=False)
        if unknown:
            raise _Bad(f"element {eid:#x} at byte {pos} has an unknown size (the writer never closed it)")
        a = pos + n_id + n_size
        if a + n > end:
            raise _Bad(f"element {eid:#x} at byte {pos} declares {n} bytes, {end - a} are there (cut off)")
        yield eid, a, a + n
        pos = a + n


def _mkv(f: BinaryIO, size: int) -> int:
    top = list(_elements(f, 0, size))
    if [e for e, _, _ in top] != [_EBML, _SEGMENT]:
        raise _Bad("not an EBML header followed by one Segment")
    _, a, b = top[1]
    frames, cues = 0, False
    for eid, ca, cb in _elements(f, a, b):
        cues |= eid == _CUES
        if eid == _CLUSTER:
            frames += sum(k in (_SIMPLE_BLOCK, _BLOCK_GROUP) for k, _, _ in _elements(f, ca, cb))
    if not cues:
        raise _Bad("no 'Cues' index (written when the file is closed)")
    return frames

"""``python -m tests.tools.fuzz_mcap`` (= ``python -m tests.tools.fuzz --target mcap``): damaged
recordings through every reader entry point.

Three small valid recordings (chunk compression none, zstd and lz4; 6 synthetic 32x24 frame
messages in JPEG+zstd (its JPEG stored apart, in its Foxglove image record) and raw+raw
alternately, the Foxglove channels, an ``end`` message,
a chunk closed every two frames) are mutated one input at a time, deterministically for a seed:
bit flips, byte overwrites, truncation at random offsets and at (or inside) every kind of
record field, insertions, deletions, duplicated ranges, damaged chunk data with a stale CRC, a
field of a record (its length, a string length, a chunk's sizes, a summary offset, ...) set to
a boundary value, record lengths set huge, garbage files and empty or magic-only files.

Every file goes through the three entry points that read recordings:

* ``quick_stream.io.recording.read_messages`` (all messages): success or :class:`RecordingError`;
* ``quick_stream.io.recording.recover`` (to a temporary output): a report, whose output must read
  back with exactly the messages it claims, or :class:`RecordingError`;
* ``open_source("mcap:FILE")`` then iteration: :class:`SourceError` at open, else frames and
  :class:`BadFrame` items whose error names the file and the message index; iteration never
  raises.

Anything else is a bug: a crash (any other exception, the innermost frame reported), an
unclear error (one that does not name the file), a hang (an entry point still running after
``hang_s``, interrupted by a SIGALRM watchdog in the main thread) or memory (peak RSS growing
by more than ``mem_mb`` in one entry point, e.g. a buffer sized by a forged length).
"""
from __future__ import annotations

import contextlib
import random
import re
import resource
import signal
import sys
import tempfile
import threading
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

from quick_stream.io import foxglove
from quick_stream.io.foxglove_view import FoxgloveView
from quick_stream.core.frame import BadFrame
from quick_stream.stream.keys import key
from quick_stream.io.recording import MAGIC, Recorder, RecordingError, read_messages, recover
from quick_stream.io.recording_images import write_message
from quick_stream.io.sources import SourceError, open_source
from quick_stream.stream.wire import EndOfStream, encode, encode_frame

FRAMES_SPEC = "synthetic:frames=6,width=32,height=24"
COMPRESSIONS = ("none", "zstd", "lz4")
ENTRIES = ("read_messages", "recover", "mcap source")


# --- the valid recordings ------------------------------------------------------------------------

def _record(path: Path, compression: str) -> None:
    """6 frames (alternately JPEG+zstd, stored apart from its JPEG, and raw+raw), their Foxglove views
    and an end message."""
    view = FoxgloveView("cam0")
    t = 10**9
    with Recorder(path, compression=compression) as rec:
        foxglove.register_channels(rec, "cam0")
        for i, f in enumerate(open_source(FRAMES_SPEC)):
            data = encode_frame(f, "cam0", color=("jpeg", "raw")[i % 2], depth=("zstd", "raw")[i % 2])
            t = 10**9 + f.timestamp_ns
            # as the recorder writes it: a JPEG stored once, in its Foxglove image record
            write_message(lambda topic, d: rec.write(topic, d, log_time_ns=t), key("cam0", "frame"), data, t)
            for topic, payload in view.convert("frame", data, t, jpeg=False):
                rec.write(topic, payload, log_time_ns=t)
            if i % 2:
                rec.flush()  # a chunk every two frames
        rec.write(key("cam0", "frame"), encode(EndOfStream(5, "source exhausted"), "cam0"), log_time_ns=t + 1)


def base_recordings(folder: Path) -> dict[str, bytes]:
    """{compression: bytes of a valid recording} written in ``folder``."""
    out = {}
    for comp in COMPRESSIONS:
        path = folder / f"base-{comp}.mcap"
        _record(path, comp)
        out[comp] = path.read_bytes()
    return out


# --- where the fields are ----------------------------------------------------------------------

@dataclass(frozen=True)
class Field:
    """``size`` bytes at ``offset`` of a recording: a record's opcode, length or body field."""

    offset: int
    size: int
    name: str


_OPCODES = {0x01: "header", 0x02: "footer", 0x03: "schema", 0x04: "channel", 0x05: "message", 0x06: "chunk",
            0x07: "message_index", 0x08: "chunk_index", 0x0B: "statistics", 0x0E: "summary_offset",
            0x0F: "data_end"}
_BODY = {  # opcode: (offset in the body, size, name) of its fixed-position fields (MCAP spec)
    0x01: [(0, 4, "profile_length")],
    0x02: [(0, 8, "summary_start"), (8, 8, "summary_offset_start"), (16, 4, "summary_crc")],
    0x03: [(0, 2, "id"), (2, 4, "name_length")],
    0x04: [(0, 2, "id"), (2, 2, "schema_id"), (4, 4, "topic_length")],
    0x05: [(0, 2, "channel_id"), (2, 4, "sequence"), (6, 8, "log_time"), (14, 8, "publish_time")],
    0x06: [(0, 8, "message_start_time"), (8, 8, "message_end_time"), (16, 8, "uncompressed_size"),
           (24, 4, "uncompressed_crc"), (28, 4, "compression_length")],
    0x07: [(0, 2, "channel_id"), (2, 4, "records_length")],
    0x08: [(0, 8, "message_start_time"), (8, 8, "message_end_time"), (16, 8, "chunk_start_offset"),
           (24, 8, "chunk_length"), (32, 4, "message_index_offsets_length")],
    0x0B: [(0, 8, "message_count"), (8, 2, "schema_count"), (10, 4, "channel_count"), (22, 4, "chunk_count"),
           (26, 8, "message_start_time"), (34, 8, "message_end_time"), (42, 4, "channel_message_counts_length")],
    0x0E: [(0, 1, "group_opcode"), (1, 8, "group_start"), (9, 8, "group_length")],
    0x0F: [(0, 4, "data_section_crc")],
}


def _records(data: bytes, start: int, end: int, prefix: str) -> Iterator[tuple[int, int, int, str]]:
    """(offset, opcode, body length, name) of the records in ``data[start:end]``."""
    pos = start
    while pos + 9 <= end:
        op, length = data[pos], int.from_bytes(data[pos + 1:pos + 9], "little")
        yield pos, op, length, prefix + _OPCODES.get(op, f"op{op:#04x}")
        pos += 9 + length
        if op == 0x02:
            return


def layout(data: bytes) -> list[Field]:
    """Every record's opcode, length and fixed body fields, records inside uncompressed chunks too,
    and each chunk's ``records`` region (its compressed or raw message data)."""
    fields = [Field(0, 8, "magic"), Field(len(data) - 8, 8, "magic (end)")]
    todo = [(8, len(data), "")]
    while todo:
        start, end, prefix = todo.pop()
        for pos, op, length, name in _records(data, start, end, prefix):
            fields += [Field(pos, 1, f"{name}.opcode"), Field(pos + 1, 8, f"{name}.length")]
            body = pos + 9
            fields += [Field(body + o, s, f"{name}.{n}") for o, s, n in _BODY.get(op, ())]
            if op == 0x06:
                clen = int.from_bytes(data[body + 28:body + 32], "little")
                fields.append(Field(body + 32 + clen, 8, f"{name}.records_length"))
                rstart = body + 40 + clen
                fields.append(Field(rstart, max(1, body + length - rstart), f"{name}.records"))
                if clen == 0:
                    todo.append((rstart, body + length, "chunk/"))
    return [f for f in fields if 0 <= f.offset and f.offset + f.size <= len(data)]


# --- mutators ----------------------------------------------------------------------------------

Mutator = Callable[[random.Random, bytes, list[Field], dict[str, bytes]], bytes]


def _boundary(rng: random.Random, size: int, data: bytes, old: int) -> int:
    top = (1 << (8 * size)) - 1
    return rng.choice([0, 1, top, top >> 1, (top >> 1) + 1, old + 1, max(old - 1, 0), old * 2, len(data),
                       len(data) + 1, rng.randrange(top + 1)]) & top


def _put(data: bytes, f: Field, value: int) -> bytes:
    return data[:f.offset] + value.to_bytes(f.size, "little") + data[f.offset + f.size:]


def _old(data: bytes, f: Field) -> int:
    return int.from_bytes(data[f.offset:f.offset + f.size], "little")


def _bitflip(rng, data, fields, bases):
    b = bytearray(data)
    for _ in range(rng.randint(1, 8)):
        b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
    return bytes(b)


def _overwrite(rng, data, fields, bases):
    b = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        b[rng.randrange(len(b))] = rng.choice((0x00, 0xFF, 0x7F, 0x80, rng.randrange(256)))
    return bytes(b)


def _truncate(rng, data, fields, bases):
    return data[:rng.randrange(len(data))]


def _truncate_field(rng, data, fields, bases):
    """Cut at a field's start, inside it or right after it: every kind of offset."""
    f = rng.choice(fields)
    return data[:f.offset + rng.choice((0, 1, f.size // 2, f.size - 1, f.size))]


def _insert(rng, data, fields, bases):
    i = rng.choice((rng.randrange(len(data)), rng.choice(fields).offset))
    return data[:i] + rng.randbytes(rng.randint(1, 64)) + data[i:]


def _delete(rng, data, fields, bases):
    i = rng.choice((rng.randrange(len(data)), rng.choice(fields).offset))
    return data[:i] + data[i + rng.randint(1, 64):]


def _duplicate(rng, data, fields, bases):
    """A range (often a whole record) copied to another place of this or another recording."""
    other = bases[rng.choice(sorted(bases))]
    i = rng.randrange(len(other))
    piece = other[i:i + rng.randint(1, 4096)]
    j = rng.randrange(len(data))
    return data[:j] + piece + data[j:]


def _field(rng, data, fields, bases):
    f = rng.choice(fields)
    if f.size > 8:  # a region (chunk records): one byte of it set
        i = f.offset + rng.randrange(f.size)
        return data[:i] + bytes([rng.randrange(256)]) + data[i + 1:]
    return _put(data, f, _boundary(rng, f.size, data, _old(data, f)))


def _huge_length(rng, data, fields, bases):
    """A record length, string length, records length or size set to a huge (or zero) value."""
    lengths = [f for f in fields if f.size in (4, 8) and ("length" in f.name or "size" in f.name)]
    f = rng.choice(lengths)
    top = (1 << (8 * f.size)) - 1
    return _put(data, f, rng.choice([top, top >> 1, 1 << (8 * f.size - 2), 2**31 & top, len(data), 0]))


def _chunk_data(rng, data, fields, bases):
    """Bytes of a chunk's records (message data, compressed or not) damaged; its CRC is now stale."""
    chunks = [f for f in fields if f.name.endswith("chunk.records")]
    f = rng.choice(chunks)
    b = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        b[f.offset + rng.randrange(f.size)] ^= 1 << rng.randrange(8)
    return bytes(b)


def _crc(rng, data, fields, bases):
    crcs = [f for f in fields if "crc" in f.name]
    return _put(data, rng.choice(crcs), rng.randrange(1 << 32))


def _garbage(rng, data, fields, bases):
    body = rng.randbytes(rng.randint(0, 4096))
    return rng.choice((body, MAGIC + body, MAGIC + body + MAGIC))


def _empty(rng, data, fields, bases):
    header_end = 8 + 9 + _old(data, Field(9, 8, "header.length"))
    return rng.choice((b"", MAGIC, MAGIC * 2, data[:header_end], data[:header_end] + MAGIC, MAGIC + b"\0" * 32))


MUTATORS: dict[str, Mutator] = {
    "bitflip": _bitflip, "overwrite": _overwrite, "truncate": _truncate, "truncate_field": _truncate_field,
    "insert": _insert, "delete": _delete, "duplicate": _duplicate, "field": _field, "huge_length": _huge_length,
    "chunk_data": _chunk_data, "crc": _crc, "garbage": _garbage, "empty": _empty,
}


# --- running the entry points --------------------------------------------------------------------

class Hang(BaseException):
    """Raised by the watchdog; a BaseException so that no ``except Exception`` swallows it."""


@contextlib.contextmanager
def watchdog(seconds: float) -> Iterator[None]:
    """Interrupt the body after ``seconds`` (SIGALRM; only in the main thread, else timing only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def fire(_sig, _frame):
        raise Hang(f"still running after {seconds:g} s")

    old = signal.signal(signal.SIGALRM, fire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


class Unclear(Exception):
    """An accepted error type whose message does not say where (file, message index)."""


def _named(err: str, path: Path, what: str) -> None:
    if str(path) not in err:
        raise Unclear(f"{what} does not name the file: {err}")


Outcome = tuple[str, "str | None"]  # (outcome label, the accepted error's message if one was raised)


def entry_read(path: Path, out: Path) -> Outcome:
    """read_messages over the whole file."""
    try:
        n = sum(1 for _ in read_messages(path))
    except RecordingError as e:
        _named(str(e), path, "RecordingError")
        return "RecordingError", str(e)
    return ("ok" if n else "ok (no messages)"), None


def entry_recover(path: Path, out: Path) -> Outcome:
    """recover into ``out``; its output must read back with exactly the messages it reports."""
    try:
        rep = recover(path, out, overwrite=True)  # one output file reused for every input
    except RecordingError as e:
        _named(str(e), path, "RecordingError")
        return "RecordingError", str(e)
    got = sum(1 for _ in read_messages(out))
    if got != rep.messages:
        raise AssertionError(f"recover reported {rep.messages} messages but its output holds {got}")
    return ("ok (complete)" if rep.complete else "ok (partial)"), None


def entry_source(path: Path, out: Path) -> Outcome:
    """open_source('mcap:FILE') and iterate: frames or BadFrames naming file and message index."""
    try:
        src = open_source(f"mcap:{path}")
    except SourceError as e:
        _named(str(e), path, "SourceError")
        return "SourceError", str(e)
    bad = 0
    for item in src:
        if isinstance(item, BadFrame):
            bad += 1
            if str(path) not in item.error or not re.search(r"message \d+", item.error):
                raise Unclear(f"BadFrame does not name the file and message index: {item.error}")
    return ("opened, BadFrames" if bad else "opened"), None


_ENTRY_FUNCS: dict[str, Callable[[Path, Path], Outcome]] = {
    "read_messages": entry_read, "recover": entry_recover, "mcap source": entry_source,
}


@dataclass
class McapFuzzReport:
    """Outcome counts per entry point and per mutator, and every bug found."""

    files: int = 0
    outcomes: dict[str, dict[str, int]] = field(default_factory=dict)  # entry -> outcome -> count
    per_mutator: dict[str, dict[str, int]] = field(default_factory=dict)  # mutator -> files, rejected, accepted
    errors: dict[str, dict[str, int]] = field(default_factory=dict)  # entry -> error text (path/digits elided)
    crashes: list[dict] = field(default_factory=list)  # crashes, unclear errors, hangs, memory: kind in each
    hangs: int = 0
    max_ms: dict[str, float] = field(default_factory=dict)
    rss_growth_mb: float = 0.0
    seconds: float = 0.0


def _shape_of(err: str, path: Path) -> str:
    return re.sub(r"\d+", "N", err.replace(str(path), "FILE"))[:160]


def _run_entry(rep: McapFuzzReport, entry: str, path: Path, out: Path, hang_s: float, mem_mb: float,
               where: dict) -> Outcome:
    """One entry point on one file; returns its outcome, records bugs in ``rep``."""
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    outcome: Outcome = ("bug", None)
    try:
        with watchdog(hang_s):
            outcome = _ENTRY_FUNCS[entry](path, out)
    except Hang:
        rep.hangs += 1
        rep.crashes.append(dict(where, kind="hang", entry=entry, error=f"still running after {hang_s} s"))
    except Unclear as e:
        rep.crashes.append(dict(where, kind="unclear", entry=entry, error=str(e)))
    except Exception as e:  # noqa: BLE001 - this is what the fuzzer looks for
        tb = traceback.extract_tb(e.__traceback__)[-1]
        rep.crashes.append(dict(where, kind="crash", entry=entry, error=f"{type(e).__name__}: {e}",
                                at=f"{Path(tb.filename).name}:{tb.lineno} in {tb.name}"))
    ms = (time.perf_counter() - t0) * 1e3
    rep.max_ms[entry] = max(rep.max_ms.get(entry, 0.0), ms)
    growth = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0) / 1024
    rep.rss_growth_mb = max(rep.rss_growth_mb, growth)
    if growth > mem_mb:
        rep.crashes.append(dict(where, kind="memory", entry=entry, error=f"peak RSS grew by {growth:.0f} MB"))
    return outcome


def _check_file(rep: McapFuzzReport, name: str, data: bytes, workdir: Path, where: dict, hang_s: float,
                mem_mb: float, keep: Path | None) -> None:
    path, out = workdir / "input.mcap", workdir / "recovered.mcap"
    path.write_bytes(data)
    per = rep.per_mutator.setdefault(name, {"files": 0, "rejected": 0, "accepted": 0})
    per["files"] += 1
    bugs = len(rep.crashes)
    for entry in ENTRIES:
        outcome, text = _run_entry(rep, entry, path, out, hang_s, mem_mb, where)
        counts = rep.outcomes.setdefault(entry, {})
        counts[outcome] = counts.get(outcome, 0) + 1
        if text is not None:
            per["rejected"] += 1
            errs = rep.errors.setdefault(entry, {})
            errs[_shape_of(text, path)] = errs.get(_shape_of(text, path), 0) + 1
        elif outcome != "bug":
            per["accepted"] += 1
    if keep is not None and len(rep.crashes) > bugs:
        keep.mkdir(parents=True, exist_ok=True)
        saved = keep / f"input-{where['input']}.mcap"
        saved.write_bytes(data)
        for c in rep.crashes[bugs:]:
            c["file"] = str(saved)
    rep.files += 1


def run(n: int = 10_000, seed: int = 0, hang_s: float = 5.0, mem_mb: float = 256.0,
        keep: str | Path | None = None) -> McapFuzzReport:
    """``n`` damaged recordings (mutators round robin over the three bases), deterministic for ``seed``;
    files that find a bug are kept in ``keep`` (if given) as ``input-<i>.mcap``."""
    rng = random.Random(seed)
    rep = McapFuzzReport()
    names = list(MUTATORS)
    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="qs-fuzz-mcap-") as tmp:
        workdir = Path(tmp)
        bases = base_recordings(workdir)
        layouts = {c: layout(b) for c, b in bases.items()}
        for i in range(n):
            name, comp = names[i % len(names)], COMPRESSIONS[(i // len(names)) % len(COMPRESSIONS)]
            data = MUTATORS[name](rng, bases[comp], layouts[comp], bases)
            where = {"input": i, "mutator": name, "base": comp, "seed": seed}
            _check_file(rep, name, data, workdir, where, hang_s, mem_mb, None if keep is None else Path(keep))
    rep.seconds = time.perf_counter() - t_start
    return rep


def format_report(r: McapFuzzReport, top: int = 8) -> str:
    """Totals, outcomes per entry point, per mutator, the commonest error messages and every bug."""
    rejected = sum(p["rejected"] for p in r.per_mutator.values())
    accepted = sum(p["accepted"] for p in r.per_mutator.values())
    kinds = {k: sum(c["kind"] == k for c in r.crashes) for k in ("crash", "unclear", "hang", "memory")}
    lines = [f"MCAP fuzz: {r.files} damaged recordings x {len(ENTRIES)} entry points in {r.seconds:.1f} s, "
             f"{rejected} rejected with a named error, {accepted} accepted, {kinds['crash']} crashes, "
             f"{kinds['unclear']} unclear errors, {r.hangs} hangs, {kinds['memory']} memory blow-ups; "
             f"slowest {max(r.max_ms.values(), default=0):.0f} ms, peak RSS growth {r.rss_growth_mb:.0f} MB"]
    for entry in ENTRIES:
        counts = ", ".join(f"{k} {v}" for k, v in sorted(r.outcomes.get(entry, {}).items()))
        lines.append(f"  {entry:<14} slowest {r.max_ms.get(entry, 0):6.1f} ms  {counts}")
    for name, p in r.per_mutator.items():
        lines.append(f"  {name:<15} {p['files']:>6} files  {p['rejected']:>6} rejected  {p['accepted']:>6} accepted"
                     " (entry-point runs)")
    for entry, errs in r.errors.items():
        lines.append(f"  commonest {entry} errors:")
        lines += [f"    {v:>6} x {k}" for k, v in sorted(errs.items(), key=lambda kv: -kv[1])[:top]]
    for c in r.crashes[:20]:
        lines.append(f"  {c['kind'].upper()} in {c['entry']} (input {c['input']}, mutator {c['mutator']}, base "
                     f"{c['base']}, --seed {c['seed']}): {c['error']} {c.get('at', '')} {c.get('file', '')}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """``python -m tests.tools.fuzz --target mcap`` with ``argv`` (--n, --seed, --keep)."""
    from .fuzz import main as fuzz_main

    return fuzz_main(["--target", "mcap", *(sys.argv[1:] if argv is None else argv)],
                     prog="python -m tests.tools.fuzz_mcap")


if __name__ == "__main__":
    raise SystemExit(main())

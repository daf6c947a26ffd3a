"""``python -m tests.tools.fuzz``: the wire decoder against malformed input, deterministically.

Seeds are valid messages of every type (small images so each decode is cheap); each
input is one seed mutated by one of: bit flips, byte overwrites, truncation,
insertion or deletion of bytes, structured field changes (a field of the msgpack map
replaced by a value of another type, NaN/inf, a huge or negative number, a long
string, a deep nesting, a wrong version), or plain random bytes. The only acceptable
outcomes are a decoded message or :class:`~quick_stream.stream.wire.WireError`; any other
exception is a crash, and a decode slower than ``hang_ms`` is a hang. Prints counts per
mutator, the slowest decode and every crash (with the input, hex, for a reproduction).

Other engines and targets share :class:`FuzzReport`, :func:`check` and :func:`format_report`:
``--engine hypothesis`` (:mod:`.fuzz_hypothesis`, Hypothesis strategies) and ``--target mcap``
(:mod:`.fuzz_mcap`, corrupted recordings through every reader entry point); :func:`main` runs
any of them (exit 0 when nothing but the named errors came out, 1 on any crash or hang).
``--target live`` (:mod:`.fuzz_live`) puts these mutations, and forged ``end`` markers, on a running
pipeline's keys and reports what became of the real frames (exit 1 if any was lost).
"""
from __future__ import annotations

import argparse
import contextlib
import logging
import os
import random
import sys
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator

import msgpack
import numpy as np

from quick_stream.core.frame import Intrinsics, RGBDFrame
from quick_stream.core.motion import MotionEstimate
from quick_stream.core.path.planner import Correction
from quick_stream.core.sceneflow import SceneFlowResult, quantized_flow
from quick_stream.stream import argtypes as at
from quick_stream.stream.wire import EndOfStream, StabilizedImage, Stats, WireError, decode, encode, encode_frame, encode_stabilized


def seeds() -> list[bytes]:
    """Valid messages of every type and encoding."""
    rng = np.random.default_rng(0)
    k = Intrinsics(30.0, 30.0, 15.5, 11.5, 32, 24)
    color = rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)
    depth = rng.uniform(0.5, 3, (24, 32)).astype(np.float32)
    f = RGBDFrame(color, depth, k, 1_000, 7, np.eye(4), "fuzz", capture={"device_id": "x", "t_device_ns": 5})
    n = 12
    pts = rng.normal(size=(n, 3))
    flow = SceneFlowResult(7, 8, pts, pts * 0.01, np.ones(n), rng.uniform(0, 30, (n, 2)), rng.uniform(0, 30, (n, 2)),
                           k, k, {"kept": n}, "")
    # a flow as the scene flow makes it: the compact layout (format version 2, wire/flowpack.py)
    grid = np.array([(4 + 3 * i, 2 + 3 * j) for j in range(5) for i in range(8) if (i + j) % 3][:n], float)
    compact = quantized_flow(7, 8, grid, rng.uniform(0.5, 3, n).astype(np.float32), grid + rng.normal(0, 0.7, (n, 2)),
                             rng.uniform(0.5, 3, n), k, k, {"kept": n})
    m = MotionEstimate(7, 8, "se3", "exact", np.eye(4), np.zeros(6), True, "", n, 0.9, 0.3, np.zeros(6))
    c = Correction(7, np.eye(4), 2, False, True, "", zoom=1.1)
    s = StabilizedImage(7, 1_000, color, 1.05, ["flag"])
    return [
        encode_frame(f, "cam0", color="jpeg"), encode_frame(f, "cam0", color="raw", depth="zstd"),
        encode_frame(f, "cam0", color="raw", depth="raw", pub_ns=12),
        encode(flow, "cam0"), encode(compact, "cam0"), encode(m, "cam0"), encode(c, "cam0", tag=(3, 0, 2)),
        encode_stabilized(s, "cam0"), encode_stabilized(s, "cam0", color="raw", src_pub_ns=1, ready_pub_ns=2),
        encode(Stats("flow", {"fps": 30.0, "n": 3, "ok": True, "why": None}), "cam0", seq=4),
        encode(EndOfStream(7, "done"), "cam0"),
    ]


_WEIRD: list[Any] = [None, True, -1, 0, 2**63 - 1, -(2**63), 2**64 - 1, 1e308, float("nan"), float("inf"), "",
                     "x" * 70_000, b"", b"\x00" * 5, [], {}, [1, 2, 3], {"a": 1}, [[[[[[[[[[1]]]]]]]]]], 1.5, "cam0"]


def _structured(rng: random.Random, data: bytes) -> bytes:
    d = msgpack.unpackb(data, raw=False, strict_map_key=False)

    def pick(obj: Any, depth: int = 0) -> tuple[Any, Any] | None:
        if isinstance(obj, dict) and obj:
            k = rng.choice(list(obj))
            if depth < 3 and isinstance(obj[k], (dict, list)) and obj[k] and rng.random() < 0.5:
                return pick(obj[k], depth + 1) or (obj, k)
            return obj, k
        if isinstance(obj, list) and obj:
            i = rng.randrange(len(obj))
            return obj, i
        return None

    where = pick(d)
    if where is None:
        return data
    container, k = where
    r = rng.random()
    if r < 0.15 and isinstance(container, dict):
        del container[k]
    else:
        container[k] = rng.choice(_WEIRD)
    return msgpack.packb(d, use_bin_type=True)


def _bitflip(rng: random.Random, data: bytes) -> bytes:
    b = bytearray(data)
    for _ in range(rng.randint(1, 8)):
        i = rng.randrange(len(b))
        b[i] ^= 1 << rng.randrange(8)
    return bytes(b)


def _overwrite(rng: random.Random, data: bytes) -> bytes:
    b = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        i = rng.randrange(len(b))
        b[i] = rng.choice((0x00, 0xFF, 0x7F, 0x80, 0xC1, 0xDC, 0xDD, 0xDE, 0xDF, 0xCF, rng.randrange(256)))
    return bytes(b)


def _truncate(rng: random.Random, data: bytes) -> bytes:
    return data[:rng.randrange(len(data))]


def _insert(rng: random.Random, data: bytes) -> bytes:
    i = rng.randrange(len(data) + 1)
    return data[:i] + bytes(rng.randrange(256) for _ in range(rng.randint(1, 16))) + data[i:]


def _delete(rng: random.Random, data: bytes) -> bytes:
    i = rng.randrange(len(data))
    return data[:i] + data[i + rng.randint(1, 16):]


def _random(rng: random.Random, data: bytes) -> bytes:
    return bytes(rng.randrange(256) for _ in range(rng.randint(0, 64)))


MUTATORS: dict[str, Callable[[random.Random, bytes], bytes]] = {
    "bitflip": _bitflip, "overwrite": _overwrite, "truncate": _truncate, "insert": _insert, "delete": _delete,
    "structured": _structured, "random": _random,
}


NET_PREFIX = "malformed message:"  # how decode's safety net (wire/messages.py) words an unexpected internal error


@dataclass
class FuzzReport:
    """Counts of one fuzz run; ``per_mutator`` splits them by mutator (or strategy family)."""

    inputs: int = 0
    rejected: int = 0
    accepted: int = 0
    crashes: list[dict] = field(default_factory=list)
    hangs: int = 0
    max_ms: float = 0.0
    per_mutator: dict[str, dict[str, int]] = field(default_factory=dict)
    seconds: float = 0.0
    engine: str = "mutate"
    slowest: str = ""  # the mutator (family) of the slowest input
    net: list[str] = field(default_factory=list)  # rejections by decode's catch-all: unexpected internal errors


def check(rep: FuzzReport, name: str, data: bytes, hang_ms: float) -> None:
    """Decode one input and count it: decoded, rejected with WireError, crash (anything else), hang."""
    per = rep.per_mutator.setdefault(name, {"inputs": 0, "rejected": 0, "accepted": 0})
    t0 = time.perf_counter()
    try:
        decode(data)
        per["accepted"] += 1
        rep.accepted += 1
    except WireError as e:
        per["rejected"] += 1
        rep.rejected += 1
        if e.problem.startswith(NET_PREFIX):
            rep.net.append(f"{name}: {e.problem}")
    except Exception as e:  # noqa: BLE001 - this is what the fuzzer looks for
        rep.crashes.append({"mutator": name, "error": f"{type(e).__name__}: {e}", "input_hex": data.hex()})
    ms = (time.perf_counter() - t0) * 1e3
    if ms > rep.max_ms:
        rep.max_ms, rep.slowest = ms, name
    rep.hangs += ms > hang_ms
    per["inputs"] += 1
    rep.inputs += 1


@contextlib.contextmanager
def muted() -> Iterator[None]:
    """Silence stderr (libjpeg prints "Corrupt JPEG data" for damaged images) and log records below
    CRITICAL for the duration of a run: millions of expected warnings would bury the report."""
    sys.stderr.flush()
    saved = os.dup(2)
    logging.disable(logging.ERROR)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        sys.stderr.flush()
        os.dup2(saved, 2)
        os.close(saved)
        logging.disable(logging.NOTSET)


def run(n: int = 100_000, seed: int = 0, hang_ms: float = 1000.0) -> FuzzReport:
    """``n`` inputs, each one seed mutated by one mutator (round robin), deterministic for ``seed``."""
    rng = random.Random(seed)
    base = seeds()
    names = list(MUTATORS)
    rep = FuzzReport()
    t_start = time.perf_counter()
    for i in range(n):
        name = names[i % len(names)]
        check(rep, name, MUTATORS[name](rng, rng.choice(base)), hang_ms)
    rep.seconds = time.perf_counter() - t_start
    return rep


def format_report(r: FuzzReport) -> str:
    """The printed report: totals, one line per mutator, every crash with its input as hex."""
    what = "mutations" if r.engine == "mutate" else "Hypothesis"
    lines = [f"wire decoder fuzz ({what}): {r.inputs} inputs in {r.seconds:.1f} s, {r.rejected} rejected with "
             f"WireError, {r.accepted} decoded, {len(r.crashes)} crashes, {r.hangs} hangs, "
             f"slowest decode {r.max_ms:.1f} ms ({r.slowest})",
             f"  {len(r.net)} of the rejections came from decode's catch-all (an unexpected internal error)"
             + "".join(f"\n    e.g. {x}" for x in r.net[:3])]
    for name, p in r.per_mutator.items():
        lines.append(f"  {name:<17} {p['inputs']:>7} inputs  {p['rejected']:>7} rejected  {p['accepted']:>7} decoded")
    for c in r.crashes[:10]:
        lines.append(f"  CRASH ({c['mutator']}): {c['error']}\n    reproduce: quick_stream.stream.wire.decode(bytes.fromhex("
                     f"'{c['input_hex']}'))")
    if len(r.crashes) > 10:
        lines.append(f"  ... and {len(r.crashes) - 10} more crashes")
    return "\n".join(lines)


def build_parser(prog: str = "python -m tests.tools.fuzz") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description="The wire decoder (or MCAP readers) against malformed "
                                "input: crashes, hangs.")
    p.add_argument("--n", type=at.positive_int, default=None,
                   help="inputs (default 100000; --target mcap: 10000 damaged recordings)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--engine", choices=("mutate", "hypothesis"), default="mutate",
                   help="wire target: 'mutate' (hand-written mutators, default) or 'hypothesis' (Hypothesis "
                        "strategies: message-shaped maps with wrong fields, byte edits of valid messages; "
                        "needs pip install 'quick-stream[test]')")
    p.add_argument("--target", choices=("wire", "mcap", "live"), default="wire",
                   help="'wire' (wire.decode, default), 'mcap' (damaged recordings through read_messages, "
                        "recover and the mcap: source) or 'live' (mutated and forged messages put on a running "
                        "`quick-stream up`'s keys, tests/tools/fuzz_live.py)")
    p.add_argument("--keep", default="out/fuzz-mcap", metavar="DIR",
                   help="--target mcap: where recordings that find a bug are kept (default out/fuzz-mcap); "
                        "--target live: the run's folder (default out/fuzz-live)")
    p.add_argument("--keys", default="frame", help="--target live: comma-separated stages whose keys get --n "
                   "messages each, or 'all' (default frame)")
    p.add_argument("--forged-ends", type=int, default=10,
                   help="--target live: valid end markers among each key's messages (default 10)")
    p.add_argument("--after", type=at.positive_int, default=150,
                   help="--target live: frames the stream goes on for after the messages (default 150)")
    return p


def main(argv: list[str] | None = None, prog: str = "python -m tests.tools.fuzz") -> int:
    """Exit 0 when nothing but the named errors came out, 1 on any crash or hang, 2 on a usage error."""
    args = build_parser(prog).parse_args(argv)
    if args.target == "live":
        from pathlib import Path

        from . import fuzz_live

        chosen = fuzz_live.KEYS if args.keys == "all" else tuple(args.keys.split(","))
        if not set(chosen) <= set(fuzz_live.KEYS):
            print(f"{prog}: --keys: stages of {', '.join(fuzz_live.KEYS)}, got {args.keys!r}", file=sys.stderr)
            return 2
        keep = args.keep if args.keep != "out/fuzz-mcap" else "out/fuzz-live"
        r = fuzz_live.run(Path(keep), args.n or 2000, args.seed, after=args.after, forged_ends=args.forged_ends,
                          keys_=chosen)
        print(fuzz_live.format_report(r))
        return 0 if fuzz_live.ok(r) else 1
    if args.target == "mcap":
        if args.engine != "mutate":
            print(f"{prog}: --target mcap mutates recordings itself; --engine applies to the wire target only",
                  file=sys.stderr)
            return 2
        from . import fuzz_mcap

        with muted():
            m = fuzz_mcap.run(args.n or 10_000, args.seed, keep=args.keep)
        print(fuzz_mcap.format_report(m))
        return 1 if m.crashes else 0
    if args.engine == "hypothesis":
        try:
            from . import fuzz_hypothesis as engine
        except ImportError as e:
            if not (e.name or "").startswith("hypothesis"):
                raise
            print(f"{prog} --engine hypothesis needs hypothesis (a test dependency): "
                  "pip install 'quick-stream[test]'", file=sys.stderr)
            return 2
    else:
        engine = sys.modules[__name__]
    with muted():
        r = engine.run(args.n or 100_000, args.seed)
    print(format_report(r))
    return 1 if r.crashes or r.hangs else 0


if __name__ == "__main__":
    sys.exit(main())

"""``python -m tests.tools.fuzz_hypothesis`` (= ``python -m tests.tools.fuzz --engine hypothesis``): the
wire decoder against Hypothesis-built input.

Three strategy families, drawn 60/30/10 % (:data:`FAMILY_WEIGHTS`):

* ``fields:<type>``: msgpack maps shaped like each message type (envelope ``v``/``type``/
  ``stream``/``seq`` and every field by name, with valid values: small JPEG or raw images,
  raw or zstd depth, float32 arrays of one row count, matrices of their group; numbers within the
  wire's ranges, wire/ranges.py), built fresh or taken
  from :func:`~tests.tools.fuzz.seeds`, then 0-3 corruptions at any depth: a field
  deleted or replaced by an arbitrary msgpack value (nested containers, NaN/inf, huge ints,
  long strings, deep nesting), retyped (int <-> float, str <-> bin, ...), resized (bin blobs
  and lists longer or shorter than their dtype x shape), given a boundary number, a wrong
  ``dtype`` or a wrong ``shape``; sometimes unknown keys are added (decoders ignore them);
* ``bytes``: a valid seed message with 1-4 byte-level edits (bit flip, byte set, insertion,
  deletion, truncation, a splice of another seed, a duplicated run);
* ``random``: arbitrary bytes.

The run is deterministic and counts exactly ``n`` inputs: Hypothesis runs the ``@given``
body in batches (``settings(max_examples=batch, database=None, deadline=None,
phases=[Phase.generate])``, seeded with ``@seed(seed, batch number)``, no shrinking) until ``n``
bodies have decoded one input each. Needs ``hypothesis`` (``pip install 'quick-stream[test]'``).
"""
from __future__ import annotations

import copy
import functools
import math
import sys
import time
from typing import Any

import cv2
import msgpack
import numpy as np
import zstandard
from hypothesis import HealthCheck, Phase, given, settings, strategies as st
from hypothesis import seed as hypothesis_seed

from quick_stream.stream.wire import flowpack
from quick_stream.core.lie import get_group
from quick_stream.stream.wire.estimates import GROUP_DIMS
from .fuzz import FuzzReport, check, seeds

BATCH = 5_000  # examples per Hypothesis run; bounds the memory of its example tree
FAMILY_WEIGHTS = ("fields",) * 6 + ("bytes",) * 3 + ("random",)  # drawn uniformly: 60/30/10 %
MAX_SIDE = 8  # generated images are at most 8x8 so each decode stays cheap

_INT = st.integers(-(2**63), 2**64 - 1)  # every int msgpack can carry
_BOUNDARY = [0, 1, -1, 2**31 - 1, 2**31, 2**32, 2**53 + 1, 2**63 - 1, -(2**63), 2**64 - 1,
             float("nan"), float("inf"), float("-inf"), -0.0, 1e308, 5e-324, -1e308, 0.5]
_DTYPES = ["<f4", ">f4", "<f8", "|u1", "<u2", ">u2", "<i2", "<i4", "f4", "float32", "uint8", "", "O", "V8",
           "<U4", "S3", "|b1", "<c8", "x" * 300]
_FINITE = st.floats(allow_nan=False, allow_infinity=False)
_F32 = st.floats(width=32, allow_nan=False, allow_infinity=False)
_STREAM = st.text(alphabet="abcAZ09_-", min_size=1, max_size=12)


def _nested(depth: int) -> Any:
    v: Any = 1
    for i in range(depth):
        v = [v] if i % 2 else {"k": v}
    return v


_SCALARS = st.one_of(
    st.none(), st.booleans(), _INT, st.sampled_from(_BOUNDARY), st.floats(), st.text(max_size=40),
    st.binary(max_size=64), st.sampled_from(["x" * 70_000, "frame", "cam0", "<f4", "jpeg", "raw", "zstd", "se3"]),
    st.integers(1, 400).map(_nested),
)
VALUES = st.recursive(
    _SCALARS,
    lambda inner: st.one_of(st.lists(inner, max_size=5),
                            st.dictionaries(st.one_of(st.text(max_size=8), st.integers(-3, 3)), inner, max_size=5)),
    max_leaves=12,
)  # any msgpack-able value


# --- valid parts ------------------------------------------------------------------------------

def _floats(draw: st.DrawFn, n: int, elements: st.SearchStrategy = _FINITE) -> list[float]:
    return draw(st.lists(elements, min_size=n, max_size=n))


def _intrinsics(draw: st.DrawFn, w: int, h: int) -> dict[str, Any]:
    """In the wire's ranges (wire/ranges.py): a field of view of 1-178 degrees, the principal point
    within the image give or take its size."""
    fx, fy = (side / (2 * math.tan(math.radians(draw(st.floats(1.0, 178.0))) / 2)) for side in (w, h))
    cx, cy = draw(st.floats(-w, 2 * w)), draw(st.floats(-h, 2 * h))
    return {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "width": w, "height": h}


_TIME = st.integers(0, 2**63 - 1)  # timestamps, ns
_ENTRY = st.floats(-1e6, 1e6)  # a pose's entries (wire/ranges.py MAX_ENTRY)


def _transform(draw: st.DrawFn, group: str = "se3") -> list[float]:
    """A matrix of ``group`` (wire/ranges.py: in range), row-major: exp of a twist drawn in [-2, 2]."""
    G = get_group(group)
    return [float(x) for x in G.exp(np.asarray(_floats(draw, G.dim, st.floats(-2.0, 2.0)))).ravel()]


def _image(draw: st.DrawFn, w: int, h: int) -> dict[str, Any]:
    px = np.frombuffer(draw(st.binary(min_size=h * w * 3, max_size=h * w * 3)), np.uint8).reshape(h, w, 3)
    if draw(st.booleans()):
        return {"enc": "raw", "dtype": "|u1", "shape": [h, w, 3], "data": px.tobytes()}
    q = draw(st.integers(1, 100))
    ok, buf = cv2.imencode(".jpg", px, [cv2.IMWRITE_JPEG_QUALITY, q])
    assert ok, "cv2.imencode failed on a tiny image"
    return {"enc": "jpeg", "quality": q, "shape": [h, w, 3], "data": buf.tobytes()}


def _depth(draw: st.DrawFn, w: int, h: int) -> dict[str, Any]:
    raw = draw(st.binary(min_size=2 * h * w, max_size=2 * h * w))
    enc = draw(st.sampled_from(["raw", "zstd"]))
    if enc == "zstd":
        raw = zstandard.ZstdCompressor(level=1, write_content_size=True).compress(raw)
    return {"enc": enc, "dtype": "<u2", "shape": [h, w], "scale": draw(st.floats(1.0, 1e6)), "data": raw}


def _f4(draw: st.DrawFn, shape: tuple[int, ...]) -> dict[str, Any]:
    vals = _floats(draw, math.prod(shape), _F32)
    return {"dtype": "<f4", "shape": list(shape), "data": np.asarray(vals, "<f4").reshape(shape).tobytes()}


def _size(draw: st.DrawFn) -> tuple[int, int]:
    return draw(st.integers(1, MAX_SIDE)), draw(st.integers(1, MAX_SIDE))


def _opt(draw: st.DrawFn, strategy: st.SearchStrategy) -> Any:
    return draw(st.one_of(st.none(), strategy))


# --- one builder per message type (fields without the envelope) ---------------------------------

def _frame(draw: st.DrawFn) -> dict[str, Any]:
    w, h = _size(draw)
    capture = st.dictionaries(st.text(max_size=12), st.one_of(_INT, st.floats(), st.text(max_size=12)), max_size=4)
    return {"t_ns": draw(_TIME), "intrinsics": _intrinsics(draw, w, h), "color": _image(draw, w, h),
            "depth": _depth(draw, w, h), "pose": _opt(draw, st.lists(_ENTRY, min_size=16, max_size=16)),
            "origin": _opt(draw, st.text(max_size=20)), "pub_ns": _opt(draw, _TIME), "capture": _opt(draw, capture)}


def _flow(draw: st.DrawFn) -> dict[str, Any]:
    n = draw(st.integers(0, 6))
    f: dict[str, Any] = {"seq_next": draw(st.integers(0, 2**64 - 1))}
    for name, cols in (("points", 3), ("displacements", 3), ("weights", None), ("pixels", 2), ("pixels_next", 2)):
        f[name] = _f4(draw, (n,) if cols is None else (n, cols))
    f["intrinsics"] = _intrinsics(draw, *_size(draw))
    f["intrinsics_next"] = _intrinsics(draw, *_size(draw))
    f["counts"] = draw(st.dictionaries(st.text(max_size=10), _INT, max_size=4))
    f["problem"] = draw(st.text(max_size=20))
    return f


def _i2(draw: st.DrawFn, shape: tuple[int, ...]) -> np.ndarray:
    vals = draw(st.lists(st.integers(-32767, 32767), min_size=math.prod(shape), max_size=math.prod(shape)))
    return np.asarray(vals, "<i2").reshape(shape)


def _flow_compact(draw: st.DrawFn) -> dict[str, Any]:
    """A version-2 flow (wire/flowpack.py): grid samples, float32 depths, int16 fixed-point flow."""
    cols, rows = draw(st.integers(0, 12)), draw(st.integers(0, 6))
    bits = np.asarray(draw(st.lists(st.booleans(), min_size=cols * rows, max_size=cols * rows)), np.uint8)
    n = int(bits.sum())
    f: dict[str, Any] = {"seq_next": draw(st.integers(0, 2**64 - 1)), "n": n,
                         "grid": {"x0": draw(st.integers(0, 64)), "y0": draw(st.integers(0, 64)),
                                  "step": draw(st.integers(1, 8)), "cols": cols, "rows": rows,
                                  "mask": np.packbits(bits, bitorder="little").tobytes()}}
    depth = np.asarray(draw(st.lists(st.floats(0.125, 10.0, width=32), min_size=n, max_size=n)), "<f4")
    f["depth"] = flowpack.pack_array(depth, "<f4")
    f["offset"] = flowpack.pack_array(_i2(draw, (n, 2)), "<i2")
    f["depth_change"] = flowpack.pack_array(_i2(draw, (n,)), "<i2")
    f["offset_exp"], f["depth_change_exp"] = draw(st.integers(4, 16)), draw(st.integers(12, 24))
    f["weights"] = _opt(draw, st.just(flowpack.pack_array(np.ones(n), "<f4")))
    f["intrinsics"] = _intrinsics(draw, *_size(draw))
    f["intrinsics_next"] = _intrinsics(draw, *_size(draw))
    f["counts"] = draw(st.dictionaries(st.text(max_size=10), _INT, max_size=4))
    f["problem"] = draw(st.text(max_size=20))
    return f


def _motion(draw: st.DrawFn) -> dict[str, Any]:
    group = draw(st.sampled_from(sorted(GROUP_DIMS)))
    dim = GROUP_DIMS[group]
    return {"seq_next": draw(st.integers(0, 2**63)), "group": group,
            "estimator": draw(st.sampled_from(["exact", "induced", ""])), "matrix": _transform(draw, group),
            "twist": _floats(draw, dim), "zeta_bar": _opt(draw, st.lists(_FINITE, min_size=dim, max_size=dim)),
            "valid": draw(st.booleans()), "reason": draw(st.text(max_size=20)),
            "n_points": draw(st.integers(0, 2**63)), "inlier_ratio": draw(st.floats(0, 1)), "rms_px": draw(st.floats())}


def _correction(draw: st.DrawFn) -> dict[str, Any]:
    size = draw(st.integers(1, 100))
    batch = [draw(st.integers(0, 2**40)), draw(st.integers(0, size - 1)), size]
    return {"matrix": _transform(draw), "segment": draw(_INT), "keyframe": draw(st.booleans()),
            "valid": draw(st.booleans()), "reason": draw(st.text(max_size=20)),
            "zoom": _opt(draw, st.floats(0.01, 100.0)), "batch": _opt(draw, st.just(batch))}


def _stabilized(draw: st.DrawFn) -> dict[str, Any]:
    return {"t_ns": draw(_TIME), "image": _image(draw, *_size(draw)), "zoom": draw(st.floats(0.01, 100.0)),
            "flags": draw(st.lists(st.text(max_size=12), max_size=3)), "src_pub_ns": _opt(draw, _TIME),
            "ready_pub_ns": _opt(draw, _TIME)}


def _stats(draw: st.DrawFn) -> dict[str, Any]:
    value = st.one_of(st.none(), st.booleans(), _INT, st.floats(), st.text(max_size=12))
    return {"service": draw(st.text(max_size=12)), "values": draw(st.dictionaries(st.text(max_size=10), value,
                                                                                   max_size=5))}


def _end(draw: st.DrawFn) -> dict[str, Any]:
    return {"last_seq": draw(st.integers(-1, 2**63)), "reason": draw(st.text(max_size=20))}


BUILDERS = {"frame": _frame, "flow": _flow, "motion": _motion, "correction": _correction,
            "stabilized": _stabilized, "stats": _stats, "end": _end}


@st.composite
def valid_maps(draw: st.DrawFn) -> dict[str, Any]:
    """A msgpack map of a valid message of any type (envelope first, as the encoder packs it)."""
    mtype = draw(st.sampled_from(sorted(BUILDERS)))
    compact = mtype == "flow" and draw(st.booleans())  # version 2's compact layout, else version 1's arrays
    env = {"v": 2 if compact else 1, "type": mtype, "stream": draw(_STREAM), "seq": draw(st.integers(0, 2**64 - 1))}
    return env | (_flow_compact(draw) if compact else BUILDERS[mtype](draw))


# --- corruption --------------------------------------------------------------------------------

def _slots(obj: Any, depth: int = 0) -> list[tuple[Any, Any]]:
    """(container, key or index) of every value in ``obj`` down to depth 4."""
    out: list[tuple[Any, Any]] = []
    items = obj.items() if isinstance(obj, dict) else enumerate(obj) if isinstance(obj, list) else ()
    for k, v in items:
        out.append((obj, k))
        if depth < 4 and isinstance(v, (dict, list)) and len(v) <= 32:
            out.extend(_slots(v, depth + 1))
    return out


def _retyped(v: Any) -> Any:
    """The same content as another msgpack type."""
    if isinstance(v, bool):
        return int(v)
    if isinstance(v, int):
        return float(v) if abs(v) < 2**1023 else str(v)
    if isinstance(v, float):
        return int(v) if math.isfinite(v) and abs(v) < 2**63 else str(v)
    if isinstance(v, str):
        return v.encode()
    if isinstance(v, bytes):
        return v.decode("latin-1")
    if isinstance(v, list):
        return {str(i): x for i, x in enumerate(v)}
    if isinstance(v, dict):
        return list(v.values())
    return 0


def _resized(draw: st.DrawFn, v: Any) -> Any:
    """A bin, str or list made shorter or longer (wrong length for its dtype x shape, row count, ...)."""
    if isinstance(v, (bytes, str, list)):
        if draw(st.booleans()) and len(v):
            return v[:draw(st.integers(0, len(v) - 1))]
        pad = draw(st.integers(1, 64))
        return v + (b"\x7f" * pad if isinstance(v, bytes) else "x" * pad if isinstance(v, str) else [0.0] * pad)
    return draw(VALUES)


def _corrupt_once(draw: st.DrawFn, msg: dict[str, Any]) -> None:
    slots = _slots(msg)
    arrays = [c for c, _ in slots if isinstance(c, dict) and ("dtype" in c or "shape" in c)]
    action = draw(st.sampled_from(["delete", "value", "retype", "resize", "number", "dtype", "shape"]))
    if action in ("dtype", "shape") and arrays:
        a = draw(st.sampled_from(arrays))
        if action == "dtype":
            a["dtype"] = draw(st.sampled_from(_DTYPES))
        else:
            dims = st.one_of(st.integers(-3, 70_000), st.sampled_from([2**31 - 1, 2**31, 2**40, 2**63 - 1]))
            a["shape"] = draw(st.lists(dims, max_size=4))
        return
    container, k = draw(st.sampled_from(slots))
    if action == "delete":
        del container[k]
    elif action == "retype":
        container[k] = _retyped(container[k])
    elif action == "resize":
        container[k] = _resized(draw, container[k])
    elif action == "number":
        container[k] = draw(st.one_of(st.sampled_from(_BOUNDARY), _INT, st.floats()))
    else:
        container[k] = draw(VALUES)


@functools.cache
def _seed_data() -> tuple[tuple[bytes, ...], tuple[dict[str, Any], ...]]:
    """The valid seed messages and their maps (module-level, so strategy reprs stay short)."""
    base = tuple(seeds())
    return base, tuple(msgpack.unpackb(b, raw=False) for b in base)


def _template(draw: st.DrawFn) -> dict[str, Any]:
    return copy.deepcopy(draw(st.sampled_from(_seed_data()[1])))


@st.composite
def field_messages(draw: st.DrawFn) -> tuple[str, bytes]:
    """("fields:<type>", bytes) of a message map with 0-3 corruptions (0: a valid message)."""
    msg = draw(valid_maps()) if draw(st.booleans()) else _template(draw)
    name = f"fields:{msg['type']}"
    for _ in range(draw(st.integers(0, 3))):
        if msg:
            _corrupt_once(draw, msg)
    if draw(st.integers(0, 9)) == 0:
        msg[draw(st.text(max_size=8))] = draw(VALUES)  # an unknown key: decoders must ignore it
    return name, msgpack.packb(msg, use_bin_type=True)


@st.composite
def byte_mutations(draw: st.DrawFn) -> tuple[str, bytes]:
    """("bytes", a valid seed message with 1-4 byte-level edits)."""
    base = _seed_data()[0]
    data = bytearray(draw(st.sampled_from(base)))
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["flip", "set", "insert", "delete", "truncate", "splice", "repeat"]))
        i = draw(st.integers(0, len(data)))
        j = min(len(data), i + draw(st.integers(1, 32)))
        if op == "flip" and i < len(data):
            data[i] ^= 1 << draw(st.integers(0, 7))
        elif op == "set" and i < len(data):
            data[i] = draw(st.sampled_from([0x00, 0xFF, 0x7F, 0x80, 0xC0, 0xC1, 0xCF, 0xD3, 0xDD, 0xDF]) | st.integers(0, 255))
        elif op == "insert":
            data[i:i] = draw(st.binary(min_size=1, max_size=16))
        elif op == "delete":
            del data[i:j]
        elif op == "truncate":
            del data[i:]
        elif op == "splice":
            other = draw(st.sampled_from(base))
            k = draw(st.integers(0, len(other) - 1))
            data[i:j] = other[k:k + (j - i) + 1]
        elif op == "repeat":
            data[j:j] = data[i:j] * draw(st.integers(1, 4))
    return "bytes", bytes(data)


def inputs() -> st.SearchStrategy[tuple[str, bytes]]:
    """(family name, input bytes) from all three families."""
    families = {"fields": field_messages(), "bytes": byte_mutations(),
                "random": st.binary(max_size=512).map(lambda b: ("random", b))}
    return st.sampled_from(FAMILY_WEIGHTS).flatmap(families.__getitem__)


def _run_batch(rep: FuzzReport, strategy: st.SearchStrategy, want: int, batch_seed: int, hang_ms: float) -> None:
    """One Hypothesis run of at most ``want`` examples; every body call checks one input."""
    quota = [want]

    @hypothesis_seed(batch_seed)
    @settings(max_examples=want, database=None, deadline=None, phases=[Phase.generate], derandomize=False,
              suppress_health_check=list(HealthCheck), print_blob=False)
    @given(strategy)
    def body(item: tuple[str, bytes]) -> None:
        if quota[0] > 0:  # Hypothesis never calls it more often; the guard keeps the count exact anyway
            quota[0] -= 1
            check(rep, item[0], item[1], hang_ms)

    body()


def run(n: int = 100_000, seed: int = 0, hang_ms: float = 1000.0, batch: int = BATCH) -> FuzzReport:
    """Exactly ``n`` Hypothesis-generated inputs through ``wire.decode``; deterministic for ``seed``."""
    rep = FuzzReport(engine="hypothesis")
    strategy = inputs()
    t_start = time.perf_counter()
    b = 0
    while rep.inputs < n:
        before = rep.inputs
        _run_batch(rep, strategy, min(batch, n - rep.inputs), seed * 1_000_003 + b, hang_ms)
        if rep.inputs == before:
            raise RuntimeError(f"Hypothesis generated no input in batch {b} (seed {seed})")
        b += 1
    rep.seconds = time.perf_counter() - t_start
    return rep


def main(argv: list[str] | None = None) -> int:
    """``python -m tests.tools.fuzz --engine hypothesis`` with ``argv`` (--n, --seed)."""
    from .fuzz import main as fuzz_main

    return fuzz_main(["--engine", "hypothesis", *(sys.argv[1:] if argv is None else argv)],
                     prog="python -m tests.tools.fuzz_hypothesis")


if __name__ == "__main__":
    raise SystemExit(main())

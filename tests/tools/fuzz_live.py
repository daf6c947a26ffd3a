"""``python -m tests.tools.fuzz --target live``: fuzzed and forged messages into a running pipeline.

Runs ``quick-stream up`` on a synthetic stream (realtime pace, as a live camera) and watches it from a
monitor session of its own. Once the stabilized output flows, a session of its own (another
publisher, as an attacker's would be) puts ``n`` messages on each of ``keys`` (default the frame key):
valid messages of the key's types, of the stream's frame size, mutated by :data:`.fuzz.MUTATORS`
(round robin, deterministic for ``seed``), with ``forged_ends`` valid ``end`` markers among them whose
``last_seq`` is the newest seq of that key the monitor has seen (a forger who watches the stream); the
motion key's first message is a motion whose matrix entries are all 1e308 (finite: issue 30 row 5).
Then the stream goes on for ``after`` frames and the capture is stopped (SIGTERM: its own end).

Reports what the pipeline did with the real frames (the capture's, told from the injected ones by
their bytes): sent, passed through flow (a seq or seq_next of some flow), stabilized, flagged, also
split into those sent before, during and after the injection (by the newest real frame seen when it
began and ended); every service's ``internal_errors`` and the recorder's ``view_errors``; the end
markers each stage published (one per stage when a forged end ends nothing); each service's counters
(drops, messages refused on arrival, ends ignored, decode and internal errors; the recorder's failed
Foxglove views) and restarts. Exit 0 when no real frame was lost, each stage ended once and no service
had an internal error; 1 otherwise.
"""
from __future__ import annotations

import hashlib
import os
import random
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from quick_stream.core.motion import MotionEstimate
from quick_stream.core.path.planner import Correction
from quick_stream.io.sources import open_source
from quick_stream.stream import keys
from quick_stream.stream.wire import EndOfStream, StabilizedImage, WireError, encode, encode_frame, encode_stabilized
from quick_stream.stream.wire.codec import unpack

from .faults import STREAM, _config, _status, _wait_status, _wait_until
from .fuzz import MUTATORS

COUNTERS = ("dropped", "dropped_foreign", "invalid", "ignored_ends", "decode_errors", "internal_errors", "view_errors",
            "refused_frames", "refused_flows", "jump_flows", "jump_corrections", "abandoned_releases", "orphans",
            "missing", "shed")
KEYS = ("frame", "flow", "motion", "correction", "stabilized", "stats")


def _digest(data: bytes) -> bytes:
    return hashlib.blake2b(data, digest_size=16).digest()


@dataclass
class Monitor:
    """Every message of the stream: (stage, type, seq, seq_next, flagged, digest)."""

    seen: list[tuple[str, str, int, int | None, bool, bytes]] = field(default_factory=list)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def on_message(self, sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        stage = str(sample.key_expr).rsplit("/", 1)[-1]
        try:
            r = unpack(data)
            row = (stage, r.type, r.seq, r.d.get("seq_next"), bool(r.d.get("flags")), _digest(data))
        except WireError:
            row = (stage, "undecodable", -1, None, False, _digest(data))
        with self._lock:
            self.seen.append(row)

    def newest(self, stage: str, injected: set[bytes] | frozenset[bytes] = frozenset()) -> int:
        """The newest seq of ``stage``'s own messages seen, those ``injected`` left out."""
        with self._lock:
            return max((s for st, t, s, *_, d in self.seen if st == stage and t == stage and d not in injected),
                       default=0)

    def count(self, stage: str, mtype: str) -> int:
        with self._lock:
            return sum(st == stage and t == mtype for st, t, *_ in self.seen)


def seeds(key: str, size: str) -> list[bytes]:
    """Valid messages of ``key``'s types (frames of the stream's size), to mutate."""
    w, h = (int(x) for x in size.split("x"))
    f = next(iter(open_source(f"synthetic:frames=1,width={w},height={h}"))).with_(seq=7)
    end = encode(EndOfStream(7, "fuzz"), STREAM)
    if key == "frame":
        return [encode_frame(f, STREAM, depth="zstd", pub_ns=time.time_ns()),
                encode_frame(f, STREAM, color="raw", depth="zstd"), end]
    if key == "motion":
        return [encode(MotionEstimate(7, 8, "se3", "exact", np.eye(4), np.zeros(6), True, "", 9, 0.9, 0.3), STREAM)]
    if key == "correction":
        return [encode(Correction(7, np.eye(4), 2, False, True, "", 1.1, np.eye(4), 0), STREAM, tag=(3, 0, 2)), end]
    if key == "stabilized":
        return [encode_stabilized(StabilizedImage(7, 5, f.color, 1.05), STREAM, src_pub_ns=1), end]
    from .fuzz import seeds as tiny  # flow (compact and version 1), stats: the wire fuzzer's own

    want = {"flow": ("flow",), "stats": ("stats",)}[key]
    return [m for m in tiny() if unpack(m).type in want] + ([end] if key == "flow" else [])


def forged_end(seq: int) -> bytes:
    return encode(EndOfStream(seq, "forged"), STREAM)


def huge_motion(seq: int) -> bytes:
    """A motion of pair (seq, seq + 1) whose matrix entries are 1e308: finite, so the format's old
    checks let it through (it stopped the recorder's Foxglove pose channels for the rest of a run)."""
    import msgpack

    d = unpack(encode(MotionEstimate(seq, seq + 1, "se3", "exact", np.eye(4), np.zeros(6), True, "", 9, 0.9, 0.3),
                      STREAM)).d
    return msgpack.packb({**d, "matrix": [1e308] * 16}, use_bin_type=True)


def run(out: Path, n: int = 2000, seed: int = 0, fps: float = 30.0, size: str = "320x240", after: int = 150,
        forged_ends: int = 10, keys_: tuple[str, ...] = ("frame",), timeout_s: float = 300.0) -> dict:
    from quick_stream.stream.launcher import free_port

    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    status = out / "logs" / "status.json"
    w, h = size.split("x")
    cmd = [sys.executable, "-m", "quick_stream", "up", "--quiet", "--out", str(out), "--port", str(port),
           "--fps", str(fps), "--source", f"synthetic:frames=100000,width={w},height={h}"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    mon = Monitor()
    rng = random.Random(seed)
    injected: set[bytes] = set()
    sessions: list[Any] = []
    text = ""
    try:
        _wait_status(status, lambda s: all(v["running"] for v in s["services"].values()), 60, proc)
        session = zenoh.open(_config(endpoint, None, "monitor", mode="peer"))
        sessions.append(session)
        sub = session.declare_subscriber(keys.stream_keys(STREAM), mon.on_message)
        _wait_status(status, lambda s: s["services"]["capture"]["stats"].get("sent", 0) >= 60, 60, proc)
        _wait_until(lambda: mon.count("stabilized", "stabilized") > 0, timeout_s)
        attacker = zenoh.open(_config(endpoint, None, "fuzzer"))
        sessions.append(attacker)
        pubs = {k: attacker.declare_publisher(keys.key(STREAM, k), reliability=zenoh.Reliability.RELIABLE,
                                              congestion_control=zenoh.CongestionControl.BLOCK) for k in keys_}
        for pub in pubs.values():
            _wait_until(lambda pub=pub: pub.matching_status.matching, timeout_s)
        names = list(MUTATORS)
        t0 = time.monotonic()
        span = [mon.newest("frame")]  # the newest real frame when the injection began, and when it ended
        for k in keys_:
            base = seeds(k, size)
            every = max(n // max(forged_ends, 1), 1)
            for i in range(n):
                if k == "motion" and i == 0:
                    data = huge_motion(mon.newest(k, injected))  # the pair last integrated: later poses build on it
                elif forged_ends and i % every == every // 2 and k != "stats":
                    data = forged_end(mon.newest(k, injected))
                else:
                    data = MUTATORS[names[i % len(names)]](rng, rng.choice(base))
                injected.add(_digest(data))
                pubs[k].put(data)
        inject_s = time.monotonic() - t0
        span.append(mon.newest("frame", injected))
        sent_then = (_status(status) or {})["services"]["capture"]["stats"].get("sent", 0)
        st = _wait_status(status, lambda s: s["services"]["capture"]["stats"].get("sent", 0) >= sent_then + after,
                          timeout_s, proc)
        os.kill(st["services"]["capture"]["pid"], signal.SIGTERM)
        text, _ = proc.communicate(timeout=timeout_s)
        time.sleep(0.2)
        sub.undeclare()
    finally:
        if proc.poll() is None:
            proc.terminate()
            try:
                text, _ = proc.communicate(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                text, _ = proc.communicate()
        for s in sessions:
            s.close()
    (out / "up.log").write_text(text or "")
    r = report(mon, injected, _status(status) or {}, proc.returncode, n, keys_, forged_ends, inject_s, tuple(span))
    from quick_stream.io.recording import read_messages

    topics = [t for f in sorted(out.glob("recording*.mcap")) for t, _, _ in read_messages(f)]
    r["foxglove"] = {t.rsplit("/", 1)[-1]: topics.count(t) for t in (f"/{STREAM}/camera_pose",
                                                                     f"/{STREAM}/stabilized_pose", f"/{STREAM}/tf")}
    return r


def report(mon: Monitor, injected: set[bytes], st: dict, code: int | None, n: int, keys_: tuple[str, ...],
           forged_ends: int, inject_s: float, span: tuple[int, int] = (-1, -1)) -> dict:
    """What became of the real frames (all, and ``before``/``during``/``after`` the injection: up to the
    newest real frame seen when it began, ``span[0]``, and after the newest seen when it ended, ``span[1]``),
    the end markers, and each service's counters."""
    real = [r for r in mon.seen if r[5] not in injected]
    sent = {s for stage, t, s, *_ in real if stage == "frame" and t == "frame"}
    flowed = {x for stage, t, s, nxt, *_ in real if stage == "flow" and t == "flow" for x in (s, nxt)
              if isinstance(x, int)}
    stab = {s for stage, t, s, *_ in real if stage == "stabilized" and t == "stabilized"}
    flagged = {s for stage, t, s, _, fl, _ in real if stage == "stabilized" and t == "stabilized" and fl}
    services = st.get("services", {})
    counters = {}
    for name, v in services.items():
        stats = v.get("stats", {})
        c = {k: stats[k] for k in stats if any(k == x or k.endswith("_" + x) for x in COUNTERS)
             and not k.startswith("pub_") and stats[k]}
        counters[name] = c
    return {"keys": list(keys_), "injected": n * len(keys_), "forged_ends": forged_ends * len(keys_),
            "inject_s": round(inject_s, 2), "frames_sent": len(sent),
            "not_through_flow": len(sent - flowed), "stabilized": len(stab & sent), "lost": len(sent - stab),
            "flagged": len(flagged & sent),
            "phases": {name: {"sent": len(part), "stabilized": len(part & stab), "flagged": len(part & flagged)}
                       for name, part in (("before", {s for s in sent if s <= span[0]}),
                                          ("during", {s for s in sent if span[0] < s <= span[1]}),
                                          ("after", {s for s in sent if s > span[1]}))},
            "ends": {k: mon_count for k in ("frame", "flow", "correction", "stabilized")
                     if (mon_count := sum(1 for stage, t, *_ in real if stage == k and t == "end"))},
            "internal_errors": {name: v.get("stats", {}).get("internal_errors", 0) for name, v in services.items()},
            "view_errors": services.get("recorder", {}).get("stats", {}).get("view_errors"),
            "counters": counters, "restarts": {k: v["restarts"] for k, v in services.items() if v.get("restarts")},
            "up_exit": code}


def format_report(r: dict) -> str:
    return (f"live fuzz: {r['injected']} messages on {', '.join(r['keys'])} in {r['inject_s']} s "
            f"({r['forged_ends']} forged ends); real frames sent {r['frames_sent']}, not through flow "
            f"{r['not_through_flow']}, stabilized {r['stabilized']}, lost {r['lost']}, flagged {r['flagged']}; "
            f"end markers per stage {r['ends']}; recorded Foxglove poses {r.get('foxglove')}; restarts "
            f"{r['restarts']}; up exit {r['up_exit']}\n"
            + "".join(f"  {name:<6} real frames sent {p['sent']}, stabilized {p['stabilized']}, flagged {p['flagged']}\n"
                      for name, p in r.get("phases", {}).items())
            + f"  internal_errors {r.get('internal_errors')}; recorder view_errors {r.get('view_errors')}\n"
            + "\n".join(f"  {name:<9} {c}" for name, c in r["counters"].items()))


def ok(r: dict) -> bool:
    internal = sum(v for c in r["counters"].values() for k, v in c.items() if k == "internal_errors")
    return r["lost"] == 0 and all(v == 1 for v in r["ends"].values()) and internal == 0 and not r["restarts"]

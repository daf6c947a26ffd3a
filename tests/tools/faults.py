"""``python -m tests.tools.faults``: SIGKILL processes of a running ``quick-stream up`` and measure recovery.

Each case runs ``up`` on a synthetic stream and watches it from a monitor session of its
own (a peer, so it keeps seeing the services when the router dies): every message of the
stream with its arrival time (the ground truth of what was published), and the services'
liveliness tokens (when a process went away and when its successor was ready). Once
``kill_after`` frames went out, the victims get SIGKILL (all at once: ``router+flow``), and
again ``repeat - 1`` times, each ``interval_s`` after the previous successor was ready. The
stream is as long as the case needs: once every successor is back and publishing, stabilized
frames flow again and at least ``frames`` frames went out, the driver stops the capture
(SIGTERM: it sends its end marker), so a slow restart on a loaded machine never outlasts it.

Two cases kill nothing but publish bad messages on the frame key at that moment, from a
session of their own: ``poison`` (a valid envelope of type ``stabilized`` numbered 10^12 with
no body, and a frame of format version 2) and ``future-seq`` (a valid frame numbered 10^12).
The stream must go on: nothing lost, nothing flagged, the output not held up.

``tls``: the same cases with the router on deploy/zenoh/router-tls.json5 (mutual TLS and
access control) and every process a TLS client with its own certificate from
deploy/tls/make-certs.sh: the services, ``up``'s status board and the monitor (``quick-monitor``:
it may watch, not publish); the bad messages come from the capture's certificate (the only one
the access control lets publish frames) and the same messages from the monitor's are refused.

Per kill it reports the restart (kill -> the successor's liveliness token) and the resume
(kill -> the first message the successor published: frames for capture, flows, motions,
stabilized frames for render, the first message in the recorder's new file; for the router,
which publishes nothing, the longest pause of the stabilized output after the kill). Per case:
frames sent, stabilized, flagged and lost (sent, never stabilized), render's counters, every
process's restarts and exit, and the recordings: readable as written or after
``quick-stream recover``, and every message the monitor saw that no recording holds: all of
them, and those seen more than ``accept_s`` (1 s) before a kill of the recorder. A restarted
recorder logs the hole its predecessor left ("recorder restart: cam0/frame seq 85-145 ..."): every
message the monitor saw is either recorded (a copy of its stage's seq) or inside such a logged hole;
the rest are counted ``not_recorded_outside_hole`` (docs/reliability.md, "Faults").
``--runs N`` repeats each case N times and sums those counts.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import msgpack
import numpy as np
import zenoh

from quick_stream.io.recording import RecordingError, read_messages, recover
from quick_stream.io.sources import open_source
from quick_stream.stream import argtypes as at, keys
from quick_stream.stream.wire import WireError, encode_frame
from quick_stream.stream.wire.codec import peek, unpack

OUTPUT = {"capture": "frame", "flow": "flow", "motion": "motion", "render": "stabilized"}
STREAM_CAP = 100_000  # the synthetic source's length: the driver ends the stream (run_case)
KILLS = ("flow", "motion", "render", "capture", "recorder", "router", "flow*3", "render*3", "router+flow")
INJECTIONS = ("poison", "future-seq")  # bad messages on the frame key mid-stream, nothing killed
CASES = KILLS + INJECTIONS
STREAM = "cam0"
FAR = 10**12  # the seq of the injected messages
RELEASE_FRAMES = 15  # the motion stage releases corrections every 15 frames (docs/architecture.md, Latency)
DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
ROUTER_TLS = DEPLOY / "zenoh" / "router-tls.json5"
MAKE_CERTS = DEPLOY / "tls" / "make-certs.sh"


@dataclass
class Seen:
    """One message the monitor received."""

    t: float  # time.time() on arrival
    stage: str
    type: str
    seq: int
    digest: bytes
    flagged: bool = False
    restart: bool = False  # a correction whose path restarted there (docs/method.md 4.4)


@dataclass
class StreamMonitor:
    """Every message of one stream and the liveliness events of its services, with arrival times."""

    stream: str
    seen: list[Seen] = field(default_factory=list)
    tokens: list[tuple[float, str, bool]] = field(default_factory=list)  # (time, service, up)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def on_message(self, sample: zenoh.Sample) -> None:
        now = time.time()
        data = sample.payload.to_bytes()
        stage = str(sample.key_expr).rsplit("/", 1)[-1]
        try:
            r = unpack(data)
            mtype, seq, flagged = r.type, r.seq, bool(r.d.get("flags"))
            restart = mtype == "correction" and r.d.get("motion") == "restart"
        except WireError:
            mtype, seq, flagged, restart = "undecodable", -1, False, False
        with self._lock:
            self.seen.append(Seen(now, stage, mtype, seq, _digest(data), flagged, restart))

    def on_token(self, sample: zenoh.Sample) -> None:
        try:
            _, service = keys.parse_health(str(sample.key_expr))
        except ValueError:
            return
        with self._lock:
            self.tokens.append((time.time(), service, sample.kind == zenoh.SampleKind.PUT))

    def ready_after(self, service: str, t: float) -> float | None:
        """When ``service``'s token next came up after ``t``."""
        with self._lock:
            return next((tt for tt, s, up in self.tokens if s == service and up and tt > t), None)

    def digests(self) -> set[bytes]:
        with self._lock:
            return {m.digest for m in self.seen}

    def first(self, stage: str, after: float) -> float | None:
        with self._lock:
            return next((m.t for m in self.seen if m.stage == stage and m.type == stage and m.t > after), None)


def make_certs(folder: Path) -> Path:
    """Certificates for stream cam0 (deploy/tls/make-certs.sh), once per run: ``folder``."""
    if not MAKE_CERTS.is_file():
        raise FileNotFoundError(f"{MAKE_CERTS}: tests.tools.faults --tls runs from the source tree (deploy/)")
    if folder.exists():
        shutil.rmtree(folder)
    subprocess.run(["bash", str(MAKE_CERTS), "--streams", STREAM, str(folder)], check=True, capture_output=True)
    return folder


def _config(endpoint: str, tls: Path | None, party: str, mode: str = "client") -> zenoh.Config:
    """A session of the driver's: ``party``'s certificate under TLS (monitor, or a service of cam0)."""
    from quick_stream.stream.transport import session_config

    if tls is None:
        return session_config(endpoint, mode)
    folder = tls / party if party in ("monitor", "router") else tls / STREAM / party
    return session_config(endpoint, "client", str(folder), party)  # peers would bypass the access control


def bad_messages(case: str, size: str) -> list[bytes]:
    """The messages ``case`` publishes on the frame key: each one a service must refuse."""
    if case == "poison":  # a valid envelope and nothing else; a frame of an unknown format version
        w, h = (int(x) for x in size.split("x"))
        frame = unpack(encode_frame(next(iter(open_source(f"synthetic:frames=1,width={w},height={h}"))), STREAM)).d
        return [msgpack.packb({"v": 1, "type": "stabilized", "stream": STREAM, "seq": FAR}),
                msgpack.packb({**frame, "v": 2, "seq": FAR + 1}, use_bin_type=True)]
    if case == "future-seq":  # one valid frame numbered far ahead
        w, h = (int(x) for x in size.split("x"))
        frame = next(iter(open_source(f"synthetic:frames=1,width={w},height={h}")))
        return [encode_frame(frame.with_(seq=FAR), STREAM)]
    raise ValueError(f"not an injection case: {case!r}")


class Injector:
    """A session that publishes on the frame key as ``party``, open until :meth:`close` (a message
    put right before a session closes may never leave it)."""

    def __init__(self, endpoint: str, tls: Path | None, party: str) -> None:
        self.session = zenoh.open(_config(endpoint, tls, party))
        self.pub = self.session.declare_publisher(keys.key(STREAM, "frame"), reliability=zenoh.Reliability.RELIABLE,
                                                  congestion_control=zenoh.CongestionControl.BLOCK)

    def put(self, messages: list[bytes], timeout: float) -> None:
        # a client's publisher sends only once it knows a subscriber: wait for that, not a clock
        _wait_until(lambda: self.pub.matching_status.matching, timeout)
        for m in messages:
            self.pub.put(m)

    def close(self) -> None:
        self.pub.undeclare()
        self.session.close()


def _status(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _wait_status(path: Path, ready, timeout: float, proc: subprocess.Popen | None = None) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        st = _status(path)
        if st and ready(st):
            return st
        if proc is not None and proc.poll() is not None:
            raise RuntimeError(f"`up` ended before the case could run (exit {proc.returncode}); see {path.parent}")
        time.sleep(0.05)
    raise TimeoutError(f"{path}: condition not reached in {timeout:g} s")


def parse_case(case: str) -> tuple[list[str], int]:
    """``flow`` -> (["flow"], 1); ``render*3`` -> (["render"], 3); ``router+flow`` -> (["router", "flow"], 1);
    an injection case (``poison``, ``future-seq``) kills nothing: ([], 1)."""
    if case in INJECTIONS:
        return [], 1
    names, _, rep = case.partition("*")
    return names.split("+"), int(rep or 1)


def run_case(out: Path, case: str, frames: int = 240, fps: float = 30.0, size: str = "320x240",
             kill_after: int = 60, interval_s: float = 2.0, accept_s: float = 1.0, timeout_s: float = 180,
             pace: str = "realtime", tls: Path | None = None) -> dict:
    """Run one fault case (see the module doc); returns its report. ``pace="fast"``: the capture sends as
    fast as the pipeline takes frames (its output credit), so a machine too loaded for ``fps`` drops
    nothing and what is measured is recovery alone (the tests); realtime is a live camera (the tool run by hand).
    ``tls``: the folder deploy/tls/make-certs.sh wrote (:func:`make_certs`): router on
    deploy/zenoh/router-tls.json5, every process a TLS client with its own certificate."""
    from quick_stream.stream.launcher import free_port

    victims, repeat = parse_case(case)
    w, h = size.split("x")
    port = free_port()
    endpoint = f"{'tls' if tls else 'tcp'}/127.0.0.1:{port}"
    if out.exists():
        shutil.rmtree(out)  # the case's own folder: recordings of an earlier run would be counted
    out.mkdir(parents=True)
    status = out / "logs" / "status.json"
    cmd = [sys.executable, "-m", "quick_stream", "up", "--quiet", "--out", str(out), "--port", str(port),
           "--fps", str(fps), "--pace", pace, "--source", f"synthetic:frames={STREAM_CAP},width={w},height={h}"]
    if tls:
        cmd += ["--tls-dir", str(tls), "--router-config", str(ROUTER_TLS)]
    bad = bad_messages(case, size) if case in INJECTIONS else []
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    mon = StreamMonitor(STREAM)
    session = None
    injectors: list[Injector] = []
    events: list[tuple[float, str]] = []  # (time, "kill" | "inject")
    kills: list[float] = []
    refused: list[bytes] = []  # the same messages from an identity the access control refuses
    try:
        _wait_status(status, lambda s: all(v["running"] for v in s["services"].values()), 60, proc)
        # the monitor: a peer on plain TCP (it keeps seeing the services when the router dies); under TLS a
        # client like everyone (peers would bypass the access control)
        session = zenoh.open(_config(endpoint, tls, "monitor", mode="peer"))
        subs = [session.declare_subscriber(keys.stream_keys(STREAM), mon.on_message),
                session.liveliness().declare_subscriber(f"{keys.PREFIX}/{STREAM}/health/*", mon.on_token, history=True)]
        if bad:
            injectors.append(Injector(endpoint, tls, "capture"))  # the only certificate allowed to publish frames
            if tls:
                injectors.append(Injector(endpoint, tls, "monitor"))
                refused = [msgpack.packb({"v": 1, "type": "stabilized", "stream": STREAM, "seq": FAR + 2 + i})
                           for i in range(len(bad))]
        for i in range(repeat):
            if i == 0:
                _wait_status(status, lambda s: s["services"]["capture"]["stats"].get("sent", 0) >= kill_after, 60, proc)
                # and the stabilized output has begun: every stage has published (a render killed before its
                # first output has no cursor to take over from: its successor starts afresh, without history)
                _wait_until(lambda: mon.first("stabilized", 0.0) is not None, timeout_s)
                st = _status(status)
            else:  # the next kill once every successor has been up for interval_s
                for v in victims:
                    if v != "router":
                        _wait_until(lambda v=v: mon.ready_after(v, kills[-1]) is not None, 20)
                time.sleep(interval_s)
                st = _status(status)
            if bad:
                if refused:  # first, so that it would have arrived before the allowed ones, were it let through
                    injectors[1].put(refused, timeout_s)
                events.append((time.time(), "inject"))
                injectors[0].put(bad, timeout_s)
                continue
            pids = [st["services"][v]["pid"] for v in victims]
            kills.append(time.time())
            events.append((kills[-1], "kill"))
            for pid in pids:
                os.kill(pid, signal.SIGKILL)
            if i + 1 < repeat:
                _wait_status(status, lambda s, i=i: all(s["services"][v]["restarts"] >= i + 1 for v in victims), 60)
        # The stream ends when the driver says so, not at a fixed frame count (a loaded machine
        # restarts slowly): once every successor is up and publishing (or the bad messages reached the
        # monitor), the stabilized output flows again after that and at least ``frames`` frames went
        # out, the capture is stopped (SIGTERM: it sends its end marker) and `up` finishes the stream.
        back = events[-1][0]
        for v in victims:
            if v not in ("router",):
                _wait_until(lambda v=v: mon.ready_after(v, kills[-1]) is not None, timeout_s)
                back = max(back, mon.ready_after(v, kills[-1]))
            if v in OUTPUT:
                _wait_until(lambda v=v, back=back: mon.first(OUTPUT[v], back) is not None, timeout_s)
        if bad:
            digests = {_digest(m) for m in bad}
            _wait_until(lambda: digests <= mon.digests(), timeout_s)
        _wait_until(lambda: mon.first("stabilized", back) is not None, timeout_s)
        st = _wait_status(status, lambda s: s["services"]["capture"]["stats"].get("sent", 0) > frames, timeout_s, proc)
        os.kill(st["services"]["capture"]["pid"], signal.SIGTERM)
        text, _ = proc.communicate(timeout=timeout_s)
        time.sleep(0.2)
        for s in subs:
            s.undeclare()
    finally:
        if proc.poll() is None:  # the case failed: `up` stops its children (they are in sessions of their own,
            proc.terminate()     # so a SIGKILL to `up` alone would leave them running)
            try:
                text, _ = proc.communicate(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.communicate()
        for inj in injectors:
            inj.close()
        if session is not None:
            session.close()
    (out / "up.log").write_text(text)
    return _report(out, case, victims, events, mon, _status(status) or {}, proc.returncode, text, accept_s,
                   bad, refused, tls is not None, fps)


def _digest(data: bytes) -> bytes:
    return hashlib.blake2b(data, digest_size=16).digest()


def _wait_until(cond, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise TimeoutError("condition not reached")
        time.sleep(0.05)


def _recordings(out: Path, skip: set[bytes] = frozenset()) -> tuple[set[bytes], set[tuple[str, str, int]], list[dict]]:
    """Digests and (stage, type, seq) of every message in the run's recordings (repairing
    footer-less ones) and per-file notes; the messages whose digest is in ``skip`` (the bad ones a
    case injected) give their digest only."""
    digests: set[bytes] = set()
    ids: set[tuple[str, str, int]] = set()
    files = []
    def order(p: Path) -> int:  # recording.mcap, recording-1.mcap, recording-2.mcap, ...
        return int(p.stem.rpartition("-")[2]) if "-" in p.stem else 0

    for path in sorted((p for p in out.glob("recording*.mcap") if not p.stem.endswith(".recovered")), key=order):
        note = {"file": path.name, "repaired": False}
        try:
            msgs = list(read_messages(path))
        except RecordingError:
            fixed = path.with_name(path.stem + ".recovered.mcap")
            rep = recover(path, fixed)
            note.update(repaired=True, recovered_messages=rep.messages)
            msgs = list(read_messages(fixed))
        note["messages"] = len(msgs)
        note["first_log_time"] = min((t for _, t, _ in msgs), default=0) / 1e9
        span: dict[str, list[int]] = {}  # stage -> [first, last] seq this file recorded
        mine: set[tuple[str, bytes]] = set()
        note["stored_twice"] = 0  # wire messages (not stats) this file holds more than once on their key, byte for byte
        for topic, _, d in msgs:
            if topic.startswith("quick/"):
                digests.add(digest := _digest(d))
                note["stored_twice"] += (topic, digest) in mine and not topic.endswith("/stats")
                mine.add((topic, digest))
                if digest not in skip and (env := peek(d)) is not None:  # the envelope is enough: (type, seq)
                    stage = topic.rsplit("/", 1)[-1]
                    ids.add((stage, *env))
                    if env[0] not in ("stats", "end"):
                        lo, hi = span.setdefault(stage, [env[1], env[1]])
                        span[stage] = [min(lo, env[1]), max(hi, env[1])]
        note["seq_span"] = span
        files.append(note)
    return digests, ids, files


HOLE_LINE = re.compile(r"recorder restart: ([^/\s]+)/(\w+) seq (\d+)-(\d+)")
GAP_LINE = re.compile(r"WARNING: ([^/\s]+)/(\w+): seq (\d+)-(\d+) never arrived")


def logged_holes(log_text: str, line: re.Pattern = HOLE_LINE) -> list[tuple[str, int, int]]:
    """(stage, first, last) of every hole a restarted recorder logged (its predecessor's account);
    ``line=GAP_LINE``: of every gap a recorder logged as never arrived (at most one line per stage
    and second: its stats count them all)."""
    return [(m[2], int(m[3]), int(m[4])) for m in line.finditer(log_text)]


def _inside(stage: str, seq: int, ranges: list[tuple[str, int, int]]) -> bool:
    return any(s == stage and a <= seq <= b for s, a, b in ranges)


def _longest_gap(times: list[float]) -> float | None:
    return round(float(max(np.diff(times))), 3) if len(times) > 1 else None


def _report(out: Path, case: str, victims: list[str], events: list[tuple[float, str]], mon: StreamMonitor,
            st: dict, code: int | None, text: str, accept_s: float, bad: list[bytes] = (),
            refused: list[bytes] = (), tls: bool = False, fps: float = 30.0) -> dict:
    injected = {_digest(m) for m in bad}
    refused_d = {_digest(m) for m in refused}
    seen = [m for m in mon.seen if m.digest not in injected | refused_d]
    digests, ids, files = _recordings(out, injected | refused_d)
    kills = [t for t, kind in events if kind == "kill"]
    # what was sent and stabilized: seen by the monitor or recorded (the monitor is a subscriber
    # like any other and may itself miss a message; the recording is the record)
    sent = sorted({m.seq for m in seen if m.type == "frame"} | {q for _, t, q in ids if t == "frame"})
    stab = [m for m in seen if m.type == "stabilized" and m.stage == "stabilized"]
    out_seqs = {m.seq for m in stab} | {q for s, t, q in ids if t == "stabilized" and s == "stabilized"}
    monitor_ids = {(m.stage, m.type, m.seq) for m in seen}
    monitor_missed = sorted(i for i in ids - monitor_ids if i[1] != "stats")
    per_event = []
    for k, kind in events:
        row: dict = {"event": kind}
        for v in victims:
            ready = mon.ready_after(v, k)
            row[f"{v}_restart_s"] = None if ready is None else round(ready - k, 3)
            if v in OUTPUT and ready is not None:
                first = mon.first(OUTPUT[v], ready)
                row[f"{v}_resume_s"] = None if first is None else round(first - k, 3)
        if "capture" in victims:  # where the successor's numbering starts: after its predecessor's, or from 0
            row["capture_last_seq_before"] = max((m.seq for m in seen if m.type == "frame" and m.t < k), default=None)
            ready = mon.ready_after("capture", k)
            row["capture_first_seq_after"] = next((m.seq for m in seen if m.type == "frame" and ready is not None
                                                   and m.t > ready), None)
        row["stabilized_pause_s"] = _longest_gap([m.t for m in stab if m.t > k - 0.5])
        if kind == "inject":  # the stream's own rhythm before: the output comes in bursts, one per release
            before = _longest_gap([m.t for m in stab if k - 10 < m.t <= k])
            row["stabilized_gap_before_s"] = before
            # paused: a gap after the bad messages longer than any in the 10 s before by more than the
            # planner's release period (15 frames: 0.5 s at 30 fps), i.e. at least one release held up
            row["output_paused"] = (None if before is None or row["stabilized_pause_s"] is None
                                    else row["stabilized_pause_s"] > before + RELEASE_FRAMES / fps)
        per_event.append(row)
    if "recorder" in victims:  # the restarted recorder's first message: when recording resumed
        for k, row, note in zip(kills, per_event, files[1:]):
            row["recorder_resume_s"] = round(note["first_log_time"] - k, 3)
    missing = [m for m in seen if m.digest not in digests and m.type != "stats"]
    # of those, the ones of which the recording holds no other copy (same stage, type and seq: a
    # message whose publisher died while sending it can reach some peers and not others, and its
    # successor publishes that seq again, with other bytes)
    no_copy = [m for m in missing if (m.stage, m.type, m.seq) not in ids]
    log_path = out / "logs" / "recorder.log"
    rec_log = log_path.read_text(errors="replace") if log_path.is_file() else ""
    holes, gaps = logged_holes(rec_log), logged_holes(rec_log, GAP_LINE)
    # of those, the ones outside every hole a restarted recorder logged and every gap a recorder logged
    # as never arrived: in no file and in no account
    unaccounted = [m for m in no_copy if not _inside(m.stage, m.seq, holes + gaps)]
    published = {(m.stage, m.type, m.seq) for m in seen if m.type != "stats"}
    rec_kills = [k for k in kills if "recorder" in victims]
    early = [m for m in missing if any(m.t < k - accept_s for k in rec_kills)]
    # and the ones inside the seq range a recording holds of their stage: published while a
    # recorder was recording, not lost to a recorder's downtime (order only, no clock)
    late = [m for m in missing if any(f["seq_span"].get(m.stage, [0, -1])[0] < m.seq < f["seq_span"][m.stage][1]
                                      for f in files if m.stage in f["seq_span"])]
    # how long before a recorder kill the oldest message it lost had arrived (the loss window)
    window = max((k - m.t for k in rec_kills for m in missing if k - 5.0 < m.t < k), default=0.0)
    services = st.get("services", {})
    render = services.get("render", {}).get("stats", {})
    report = {"case": case, "tls": tls, "kills": len(kills), "per_event": per_event,
              "restarts": {n: s["restarts"] for n, s in services.items()},
              "up_exit": code, "clean_stop": code == 0 and "exit codes" not in text,
              "frames_sent": len(sent), "stabilized": len(stab), "stabilized_unique": len(out_seqs),
              "flagged": sum(m.flagged for m in stab), "lost": len(set(sent) - out_seqs),
              # stabilized, yet sent as far as neither the monitor nor the recording knows: a frame a killed
              # capture was sending can reach flow and render and not them
              "stabilized_not_seen_sent": sorted(out_seqs - set(sent)),
              "path_restarts": len({m.seq for m in seen if m.restart}),
              "monitor_missed": len(monitor_missed), "monitor_missed_examples": monitor_missed[:5],
              "render": {k: render.get(k) for k in ("missing", "dropped", "orphans", "refused_frames")},
              # frames a live capture skipped (the pipeline behind: never published, a seq gap flow bridges)
              "shed": services.get("capture", {}).get("stats", {}).get("shed"),
              "recorder_unreceived": {k: v for k, v in services.get("recorder", {}).get("stats", {}).items()
                                      if k.startswith("unreceived_")},
              "recorder_restart_hole": services.get("recorder", {}).get("stats", {}).get("restart_hole"),
              # a restarted publisher's replay (the same bytes again): stored once, not a renumbering
              "recorded_twice": sum(f["stored_twice"] for f in files),
              "recorder_replays": services.get("recorder", {}).get("stats", {}).get("replays"),
              "recorder_renumberings": services.get("recorder", {}).get("stats", {}).get("renumberings"),
              "recordings": files, "not_recorded": len(missing),
              "not_recorded_by_stage": {s: sum(m.stage == s for m in missing) for s in sorted({m.stage for m in missing})},
              "not_recorded_no_copy": len(no_copy),
              "not_recorded_examples": [{"stage": m.stage, "type": m.type, "seq": m.seq,
                                         "s_from_kill": round(min((m.t - k for k in kills), key=abs, default=0.0), 3),
                                         "copy_recorded": (m.stage, m.type, m.seq) in ids} for m in missing[:5]],
              "lost_accepted_before_kill": len(early), "lost_while_recording": len(late),
              "lost_while_recording_examples": [
                  {"stage": m.stage, "type": m.type, "seq": m.seq, "in_logged_gap": _inside(m.stage, m.seq, gaps),
                   "copy_recorded": (m.stage, m.type, m.seq) in ids,
                   "s_from_kill": round(min((m.t - k for k in kills), key=abs, default=0.0), 3),
                   "spans": [f["seq_span"].get(m.stage) for f in files]} for m in late[:5]],
              # every message published (the monitor saw it) is recorded or in a hole a successor logged
              "published": len(published), "recorded_of_published": len(published & ids),
              "recorder_holes": holes, "in_logged_hole": sum(_inside(st, q, holes) for st, _, q in published - ids),
              "in_logged_gap": sum(_inside(st, q, gaps) and not _inside(st, q, holes) for st, _, q in published - ids),
              "not_recorded_outside_hole": len(unaccounted),
              # received by the killed recorder, or on their way to it (published before its kill)
              "outside_hole_before_kill": sum(any(m.t < k for k in rec_kills) for m in unaccounted),
              "outside_hole_examples": [{"stage": m.stage, "type": m.type, "seq": m.seq,
                                         "s_from_kill": round(min((m.t - k for k in kills), key=abs, default=0.0), 3)}
                                        for m in unaccounted[:5]],
              "loss_window_s": round(window, 3)}
    if bad:
        seen_d = mon.digests()
        counters = {n: {k: v for k, v in services.get(n, {}).get("stats", {}).items()
                        if k in ("decode_errors", "refused_frames", "seq_jumps", "inbox0_invalid", "inbox1_invalid")}
                    for n in ("flow", "render")}
        report["injected"] = {"messages": len(bad), "seen": len(injected & seen_d), "recorded": len(injected & digests),
                              "counters": counters}
        if tls:  # the same from the monitor's certificate: refused by the router, so nobody has them
            report["refused_reached"] = len(refused_d & (seen_d | digests))
    return report


def format_report(r: dict) -> str:
    def row(e: dict) -> str:
        return ", ".join(f"{k} {v}" for k, v in e.items() if v is not None and k != "event")

    events = "; ".join(f"{e['event']}: {row(e)}" for e in r["per_event"])
    rec = ", ".join(f"{f['file']} {f['messages']} msgs{' (recovered)' if f['repaired'] else ''}" for f in r["recordings"])
    lines = [f"{r['case']:<12} kills {r['kills']}  [{events}]",
             f"{'':<12} frames sent {r['frames_sent']}, stabilized {r['stabilized_unique']} (flagged {r['flagged']}), "
             f"lost {r['lost']} (messages recorded that the monitor missed: {r['monitor_missed']} "
             f"{r['monitor_missed_examples']}); render {r['render']}; capture shed {r['shed']}; never reached the recorder "
             f"{r['recorder_unreceived']}; restarts "
             f"{ {k: v for k, v in r['restarts'].items() if v} }; clean stop {r['clean_stop']}",
             f"{'':<12} recordings: {rec}; messages not recorded {r['not_recorded']} {r['not_recorded_by_stage']} "
             f"(no copy of that stage's seq recorded: {r['not_recorded_no_copy']}), "
             f"of them seen > 1 s before a recorder kill: {r['lost_accepted_before_kill']} (oldest lost: seen "
             f"{r['loss_window_s']} s before the kill)",
             f"{'':<12} recorder: byte-identical messages stored twice in a file {r['recorded_twice']}, replays "
             f"dropped {r['recorder_replays']}, renumberings {r['recorder_renumberings']}",
             f"{'':<12} published {r['published']}: recorded {r['recorded_of_published']}, in a hole a restarted "
             f"recorder logged {r['in_logged_hole']}, in a gap logged as never arrived {r['in_logged_gap']}, in "
             f"neither {r['not_recorded_outside_hole']} (published before a recorder kill: "
             f"{r['outside_hole_before_kill']}) {r['outside_hole_examples']}"]
    if "injected" in r:
        i = r["injected"]
        lines.append(f"{'':<12} injected {i['messages']} bad messages{' (capture certificate)' if r['tls'] else ''}: "
                     f"seen {i['seen']}, "
                     f"recorded {i['recorded']}; refused by {i['counters']}"
                     + (f"; the same from the monitor's certificate reached {r['refused_reached']}" if r["tls"] else ""))
    return "\n".join(lines)


def summarize_runs(reports: list[dict]) -> str:
    """One line for the repeated runs of a case: messages published, recorded, in a logged hole, in neither."""
    n = len(reports)
    tot = {k: sum(r[k] for r in reports) for k in ("published", "recorded_of_published", "in_logged_hole",
                                                   "in_logged_gap", "not_recorded_outside_hole",
                                                   "outside_hole_before_kill")}
    bad = sum(r["not_recorded_outside_hole"] > 0 for r in reports)
    return (f"{reports[0]['case']} x {n} runs: published {tot['published']}, recorded {tot['recorded_of_published']}, "
            f"in a logged recorder-restart hole {tot['in_logged_hole']}, in a gap logged as never arrived "
            f"{tot['in_logged_gap']}, in neither {tot['not_recorded_outside_hole']} (of them published before a "
            f"recorder kill: {tot['outside_hole_before_kill']}; runs with any: {bad} of {n})")


def run_cases(cases: list[str], out: str, json_path: str | None, tls: bool = False, runs: int = 1, **kw) -> int:
    """Every case in turn (``runs`` times each), each report printed as it ends (and all of them as JSON
    in ``json_path``); with ``runs`` > 1 a summary line per case."""
    reports = []
    certs = make_certs(Path(out) / "certs") if tls else None  # once per run, in the run's folder
    how = (f"mutual TLS and access control ({ROUTER_TLS.relative_to(DEPLOY.parent)}), every process a TLS client "
           f"with its own certificate ({certs})" if tls else "plain TCP, the services are peers")
    print(f"faults: {how}", flush=True)
    for case in cases:
        mine = []
        for i in range(runs):
            folder = case.replace("*", "x").replace("+", "-") + (f"-run{i + 1}" if runs > 1 else "")
            r = run_case(Path(out) / folder, case, tls=certs, **kw)
            mine.append(r)
            print(format_report(r), flush=True)
        reports += mine
        if runs > 1:
            print(summarize_runs(mine), flush=True)
    if json_path:
        Path(json_path).write_text(json.dumps(reports, indent=1))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m tests.tools.faults", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", default="all", help="comma-separated: a service (flow), repeated (render*3), "
                   "together (router+flow), bad messages on the frame key (poison, future-seq); default all "
                   "(every service, flow*3, render*3, router+flow, poison, future-seq)")
    p.add_argument("--frames", type=int, default=240, help="frames each case sends at least; the stream ends once "
                   "every successor is back (default 240)")
    p.add_argument("--fps", type=float, default=30.0)
    p.add_argument("--size", type=at.frame_size, default="320x240", help="frame size WxH (default 320x240)")
    p.add_argument("--kill-after", type=int, default=60, help="frames sent before the first kill (default 60)")
    p.add_argument("--out", default=None, help="folder for each case's recordings and logs (default "
                   "out/bench-faults, with --tls out/bench-faults-tls)")
    p.add_argument("--tls", action="store_true", help="the router on deploy/zenoh/router-tls.json5 (mutual TLS, "
                   "access control), every process a TLS client with its own certificate (made in OUT/certs)")
    p.add_argument("--runs", type=at.positive_int, default=1, help="run each case this many times; prints a "
                   "summary per case (messages published, recorded, in a logged recorder-restart hole, in neither)")
    p.add_argument("--json", default=None, metavar="FILE", help="also write the reports as JSON here")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    cases = list(CASES) if args.cases == "all" else args.cases.split(",")
    out = args.out or ("out/bench-faults-tls" if args.tls else "out/bench-faults")
    return run_cases(cases, out, args.json, tls=args.tls, runs=args.runs, frames=args.frames, fps=args.fps,
                     size=args.size, kill_after=args.kill_after)


if __name__ == "__main__":
    sys.exit(main())

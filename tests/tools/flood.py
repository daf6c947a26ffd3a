"""``python -m tests.tools.flood``: a foreign publisher floods the frame key; the pipeline's own capacity beside it.

Runs router, flow, motion and render (``--record``: and the recorder) on loopback and, in one run:

1. **capacity**: our capture replays ``--capacity-frames`` pre-encoded synthetic frames at the
   pipeline's own pace (``--pace fast``: its output credit; a replay costs the capture almost nothing,
   like a camera driver); the stabilized frames a second, after the first ``--warm-s`` seconds;
2. **flood**: a separate process with a zenoh session of its own and a plain publisher, not our
   capture (``python -m tests.tools.flood publish ENDPOINT``), publishes ``--size`` synthetic frames
   (encoded with ``quick_stream.stream.wire``, as docs/wire-format.md documents for third parties)
   at ``--fps`` for ``--seconds`` on the frame key, then the ``end`` marker; the same rate measured;
3. **capacity** again (the machine's load drifts: the capacity is the mean of both).

Per phase, from a monitor session of its own (flow, correction and stabilized keys, stats): frames
stabilized and flagged, the stabilized rate, and the account of wasted work: frames flow or motion
processed (a flow reached them, a correction was made) that never came out (``processed_not_output``:
dropped by render, or missing), and frames that came out although flow never took them
(``output_not_taken``: render decoded and rendered a frame flow had shed, as a flagged orphan); with
every service's counters over the phase (render's dropped/missing/orphans, flow's inbox drops and
sheds). The decision: the flood's stabilized rate against the capacity (``ratio``), and both
accounts 0.

    python -m tests.tools.flood --out /tmp/flood --json flood.json
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import msgpack
import zenoh

from quick_stream.stream import keys
from quick_stream.stream.launcher import ServiceSpec, Supervisor, free_port, open_when_up, router_spec
from quick_stream.stream.wire import EndOfStream, WireError, encode_end, encode_frame
from quick_stream.stream.wire.codec import unpack

STREAM = "cam0"
LOOP = 480  # distinct frames the foreign publisher pre-encodes and plays back and forth (4 s at 120 fps)


# --- the foreign publisher ------------------------------------------------------------------------

def _wait_for(session: zenoh.Session, services: list[str], stream: str, timeout_s: float) -> None:
    """Until the liveliness tokens of ``services`` are up (a service declares its token once its
    subscribers exist, so the router routes our frames to them)."""
    deadline = time.monotonic() + timeout_s
    while True:
        up = {keys.parse_health(str(r.ok.key_expr))[1] for r in session.liveliness().get(
            f"{keys.PREFIX}/{stream}/health/*", timeout=1.0) if r.ok is not None}
        if set(services) <= up:
            return
        if time.monotonic() > deadline:
            raise TimeoutError(f"{', '.join(sorted(set(services) - up))} not up after {timeout_s:g} s")
        time.sleep(0.1)


def publish(endpoint: str, fps: float, seconds: float, size: str, stream: str = STREAM, loop: int = LOOP,
            wait_for: list[str] = (), block: bool = False) -> dict:
    """Publish ``size`` synthetic frames at ``fps`` for ``seconds`` on ``stream``'s frame key from a
    session of our own (a plain publisher with zenoh's defaults: what a third party writes from
    docs/wire-format.md), then the ``end`` marker. The frames are pre-encoded (``loop`` of them,
    played forwards then backwards, so the camera never jumps) and re-stamped: seq, capture time
    and publication time follow the published rate. ``wait_for``: services whose liveliness tokens
    must be up first (else: a subscriber of the frame key, and a second for the others). ``block``:
    the publisher waits for a congested link instead of dropping for it (zenoh's default), so every
    receiver gets every frame (an exact account). Returns what was sent and when."""
    from quick_stream.io.sources import open_source
    from quick_stream.stream.transport import session_config

    w, h = (int(x) for x in size.split("x"))
    src = open_source(f"synthetic:frames={loop},width={w},height={h},fps={fps:g}")
    bodies = [unpack(encode_frame(f, stream, depth="zstd", depth_scale=src.depth_scale)).d for f in src]
    order = list(range(loop)) + list(range(loop - 2, 0, -1))
    session = zenoh.open(session_config(endpoint, "client"))
    pub = session.declare_publisher(keys.key(stream, "frame"),
                                    **({"congestion_control": zenoh.CongestionControl.BLOCK} if block else {}))
    deadline = time.monotonic() + 60
    while not pub.matching_status.matching:  # a client's publisher sends once a subscriber is known
        if time.monotonic() > deadline:
            raise TimeoutError("no subscriber of the frame key after 60 s")
        time.sleep(0.05)
    if wait_for:
        _wait_for(session, list(wait_for), stream, 60)
    else:
        time.sleep(1.0)  # every receiver's subscription, not only the first one's, has reached the router
    n, late = int(round(fps * seconds)), 0
    t0 = time.monotonic()
    started_ns = time.time_ns()
    for i in range(n):
        due = t0 + i / fps
        if (wait := due - time.monotonic()) > 0:
            time.sleep(wait)
        else:
            late += wait < -1.0 / fps
        body = dict(bodies[order[i % len(order)]], seq=i, t_ns=int(round(i * 1e9 / fps)), pub_ns=time.time_ns())
        pub.put(msgpack.packb(body, use_bin_type=True))
    elapsed = time.monotonic() - t0
    pub.put(encode_end(EndOfStream(n - 1, "flood over"), stream))
    time.sleep(1.0)  # a message put right before a session closes may never leave it
    pub.undeclare()
    session.close()
    return {"sent": n, "seconds": round(elapsed, 2), "fps": round(n / elapsed, 2), "late": late,
            "started_ns": started_ns}


# --- the monitor ----------------------------------------------------------------------------------

@dataclass
class Phase:
    """What the monitor saw of one stream."""

    name: str
    flows: set[tuple[int, int]] = field(default_factory=set)
    corrections: set[int] = field(default_factory=set)
    out: dict[int, float] = field(default_factory=dict)  # stabilized seq -> arrival (monotonic)
    flagged: set[int] = field(default_factory=set)
    ended: bool = False
    stats_before: dict = field(default_factory=dict)
    stats_after: dict = field(default_factory=dict)

    def rate(self, t_from: float, t_to: float, corrected: bool = False) -> float:
        """Stabilized frames a second that arrived between ``t_from`` and ``t_to`` (``corrected``: the
        flagged ones left out)."""
        n = sum(t_from <= t <= t_to and not (corrected and s in self.flagged) for s, t in self.out.items())
        return n / (t_to - t_from) if t_to > t_from else 0.0


class Monitor:
    """Flows, corrections, stabilized frames and stats of the stream, into the current :class:`Phase`."""

    def __init__(self, session: zenoh.Session) -> None:
        self.phase: Phase | None = None
        self.stats: dict[str, dict] = {}
        self._lock = threading.Lock()
        self._subs = [session.declare_subscriber(keys.key(STREAM, st), self.on_sample)
                      for st in ("flow", "correction", "stabilized", "stats")]

    def on_sample(self, sample: zenoh.Sample) -> None:
        try:
            r = unpack(sample.payload.to_bytes())
        except WireError:
            return
        with self._lock:
            if r.type == "stats":
                self.stats[r.d["service"]] = dict(r.d["values"])
                return
            ph = self.phase
            if ph is None:
                return
            if r.type == "flow":
                ph.flows.add((r.seq, r.d["seq_next"]))
            elif r.type == "correction":
                ph.corrections.add(r.seq)
            elif r.type == "stabilized":
                ph.out[r.seq] = time.monotonic()
                if r.d.get("flags"):
                    ph.flagged.add(r.seq)
            elif r.type == "end" and str(sample.key_expr).endswith("/stabilized"):
                ph.ended = True

    def begin(self, name: str) -> Phase:
        with self._lock:
            self.phase = Phase(name, stats_before=json.loads(json.dumps(self.stats)))
            return self.phase

    def finish(self, timeout_s: float) -> Phase:
        """Wait for the phase's stabilized ``end`` and the stats that follow it."""
        ph = self.phase
        _wait(lambda: ph.ended, timeout_s, f"{ph.name}: no end of the stabilized stream")
        time.sleep(2.5)  # every service's next stats (about once a second) count the whole stream
        with self._lock:
            ph.stats_after = json.loads(json.dumps(self.stats))
            self.phase = None
        return ph

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()


def _wait(cond, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise TimeoutError(what)
        time.sleep(0.05)


COUNTERS = {"render": ("dropped", "missing", "orphans", "shed_upstream", "refused_frames", "bad_frames"),
            "flow": ("inbox0_dropped", "shed", "shed_backlog", "refused_frames", "empty_flows", "missing_frames",
                     "breaks"),
            "motion": ("invalid_motions", "gaps", "motions_bridge")}


def account(ph: Phase, t_from: float, t_to: float) -> dict:
    """One phase's numbers (module docstring)."""
    taken = {s for f in ph.flows for s in f}
    deltas = {}
    for svc, names in COUNTERS.items():
        a, b = ph.stats_before.get(svc, {}), ph.stats_after.get(svc, {})
        deltas[svc] = {k: b.get(k, 0) - a.get(k, 0) for k in names if k in b}
    return {"stabilized": len(ph.out), "flagged": len(ph.flagged), "flows": len(ph.flows),
            "corrections": len(ph.corrections), "rate_fps": round(ph.rate(t_from, t_to), 2),
            "corrected_fps": round(ph.rate(t_from, t_to, corrected=True), 2),
            "processed_not_output": len(ph.corrections - ph.out.keys()),
            "output_not_taken": len(ph.out.keys() - taken), "counters": deltas}


# --- the run --------------------------------------------------------------------------------------

def run(out: Path, fps: float, seconds: float, size: str, capacity_frames: int, warm_s: float,
        record: bool, timeout_s: float) -> dict:
    from quick_stream.bench.pipeline import prerecord

    out.mkdir(parents=True, exist_ok=True)
    w, h = size.split("x")
    source = out / f"capacity-{size}-{capacity_frames}.mcap"
    if not source.exists():  # a 30 fps camera's frames, encoded once as our capture sends them
        prerecord(source, f"synthetic:frames={capacity_frames},width={w},height={h},fps=30")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    z = ["-e", endpoint, "--no-multicast-scouting"]
    specs = [router_spec(["-m", "quick_stream", "router", "-l", endpoint, "--no-multicast-scouting"])]
    if record:
        specs.append(ServiceSpec("recorder", ["-m", "quick_stream.services.recorder", *z,
                                              "--output", str(out / "recording.mcap")]))
    specs += [ServiceSpec("flow", ["-m", "quick_stream.services.flow", *z]),
              ServiceSpec("motion", ["-m", "quick_stream.services.motion", *z]),
              ServiceSpec("render", ["-m", "quick_stream.services.render", *z, "--output", str(out / "stabilized.avi")])]
    waits = ",".join(s.name for s in specs[1:])
    for i in (1, 2):
        specs.append(ServiceSpec(f"capture{i}", ["-m", "quick_stream.services.capture", *z, "--source", f"mcap:{source}",
                                                 "--pace", "fast", "--wait-for", waits], may_finish=True, restart=False))
    sup = Supervisor(specs, out / "logs", max_restarts=0)
    report: dict = {"size": size, "fps": fps, "seconds": seconds, "recording": record}
    sup.start("router")
    session = open_when_up(endpoint, 30)
    mon = Monitor(session)
    try:
        for s in specs[1:-2]:
            sup.start(s.name)
        for i, name in ((1, "capacity1"), (None, "flood"), (2, "capacity2")):
            ph = mon.begin(name)
            t0 = time.monotonic()
            cpu0 = _cpu(sup, specs)
            if i is None:
                pub = subprocess.run([sys.executable, "-m", "tests.tools.flood", "publish", endpoint, "--fps", str(fps),
                                      "--seconds", str(seconds), "--size", size, "--wait-for", waits],
                                     capture_output=True, text=True, timeout=seconds + 180)
                if pub.returncode != 0:
                    raise RuntimeError(f"the publisher failed: {pub.stderr[-2000:]}")
                report["publisher"] = sent = json.loads(pub.stdout.strip().splitlines()[-1])
                # the output's window ends with the publisher's last frame (not its process)
                t_end = time.monotonic() - (time.time_ns() - sent["started_ns"]) / 1e9 + sent["seconds"]
            else:
                sup.start(f"capture{i}")
                t_end = None  # the pipeline's own pace holds to the last frame out
            mon.finish(timeout_s)
            first, last = min(ph.out.values(), default=t0), max(ph.out.values(), default=t0)
            report[name] = account(ph, first + warm_s, last if t_end is None else t_end)
            report[name].update(first_out_s=round(first - t0, 1), last_out_s=round(last - t0, 1),
                                window_s=round((last if t_end is None else t_end) - first - warm_s, 1))
            cpu1, span = _cpu(sup, specs), time.monotonic() - t0
            report[name]["cpu_pct"] = {n: round(100 * (cpu1[n] - cpu0[n]) / span, 1) for n in cpu1 if n in cpu0}
            print(f"{name}: {json.dumps(report[name])}", file=sys.stderr, flush=True)
    finally:
        mon.close()
        session.close()
        sup.stop([s.name for s in specs if s.name.startswith("capture")]
                 + [s.name for s in specs[1:] if not s.name.startswith("capture")] + ["router"])
    cap = (report["capacity1"]["rate_fps"] + report["capacity2"]["rate_fps"]) / 2
    fl = report["flood"]
    report["capacity_fps"] = round(cap, 2)
    report["ratio"] = round(fl["rate_fps"] / cap, 3) if cap else None
    report["ratio_corrected"] = round(fl["corrected_fps"] / cap, 3) if cap else None
    report["holds"] = bool(report["ratio_corrected"] and report["ratio_corrected"] >= 0.9 and fl["processed_not_output"] == 0
                           and fl["output_not_taken"] == 0)
    return report


def _cpu(sup: Supervisor, specs: list[ServiceSpec]) -> dict[str, float]:
    """CPU seconds used so far by each running service (not the captures)."""
    from quick_stream.bench.pipeline import proc_sample

    out = {}
    for s in specs:
        pid = sup.pid(s.name) if not s.name.startswith("capture") else None
        if pid and (got := proc_sample(pid)):
            out[s.name] = got[0]
    return out


def format_report(r: dict) -> str:
    fl = r["flood"]
    c = fl["counters"]
    return (f"flood {r['size']} at {r['publisher']['fps']} fps for {r['publisher']['seconds']} s "
            f"({r['publisher']['sent']} frames): stabilized {fl['stabilized']} ({fl['flagged']} flagged), "
            f"{fl['rate_fps']} fps after warm-up ({fl['corrected_fps']} not flagged); capacity {r['capacity1']['rate_fps']} / {r['capacity2']['rate_fps']} fps "
            f"(mean {r['capacity_fps']}): ratio {r['ratio']} ({r['ratio_corrected']} not flagged)\n"
            f"  processed by flow/motion, not output: {fl['processed_not_output']}; output, not taken by flow: "
            f"{fl['output_not_taken']}\n  counters over the flood: {json.dumps(c)}\n"
            f"  CPU % per process: capacity1 {r['capacity1']['cpu_pct']}, flood {fl['cpu_pct']}, "
            f"capacity2 {r['capacity2']['cpu_pct']}\n"
            f"  holds (not flagged >= 0.9 of the capacity, both accounts 0): {r['holds']}")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m tests.tools.flood", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd")
    pp = sub.add_parser("publish", help="the foreign publisher alone (prints what it sent as JSON)")
    pp.add_argument("endpoint")
    pp.add_argument("--loop", type=int, default=LOOP, help=f"distinct frames pre-encoded (default {LOOP})")
    pp.add_argument("--wait-for", default="", metavar="S1,S2", help="services whose liveliness tokens must be up first")
    pp.add_argument("--block", action="store_true", help="wait for a congested link instead of dropping for it")
    for q in (p, pp):
        q.add_argument("--fps", type=float, default=120.0)
        q.add_argument("--seconds", type=float, default=60.0)
        q.add_argument("--size", default="640x480")
    p.add_argument("--capacity-frames", type=int, default=900, help="frames of each capacity phase (default 900)")
    p.add_argument("--warm-s", type=float, default=5.0, help="seconds of each phase's output left out of its rate")
    p.add_argument("--record", action="store_true", help="run the recorder too")
    p.add_argument("--timeout", type=float, default=300.0)
    p.add_argument("--out", default="/tmp/quick-stream-flood")
    p.add_argument("--json", default=None)
    return p


def main(argv: list[str] | None = None) -> int:
    a = build_parser().parse_args(argv)
    if a.cmd == "publish":
        print(json.dumps(publish(a.endpoint, a.fps, a.seconds, a.size, loop=a.loop,
                                 wait_for=[x for x in a.wait_for.split(",") if x], block=a.block)), flush=True)
        return 0
    r = run(Path(a.out), a.fps, a.seconds, a.size, a.capacity_frames, a.warm_s, a.record, a.timeout)
    print(format_report(r))
    if a.json:
        Path(a.json).write_text(json.dumps(r, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""``python -m tests.tools.slow_viewer``: what a slow foreign subscriber costs the pipeline.

Runs router, recorder, flow, motion, render and a live capture (``--pace realtime``, synthetic
frames) on loopback, plus a *viewer*: a separate process, not part of the pipeline, that opens its
own zenoh session to the router (``--viewer peer``: a peer that also listens, as zenoh's examples
and the services do, so gossip gives it direct links to the services; ``client``: through the router
only; ``none``: no viewer) and subscribes to ``--key`` (default every key of the stream) slowly:
``--handler fifo`` reads a bounded ``FifoChannel(4)`` (zenoh's own queueing) and sleeps
``--sleep`` seconds per sample, ``callback`` sleeps inside a callback subscriber.

Reported: the longest put of each publisher of the pipeline (``pub_<stage>_put_ms_max``, worst
stats period) and how many took over 100 ms; the frames flow's inbox dropped and the capture shed;
render's flagged and missing frames; the stabilized frames out of those sent and the longest pause
between two stabilized frames as a subscriber of the output saw it (``output_pause_s``); the
samples the viewer got. ``--services-cfg KEY:VALUE`` passes a ``--cfg`` to every service (and the
router), to try a transport setting.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from quick_stream.io.recording import read_messages
from quick_stream.stream import argtypes as at
from quick_stream.stream.launcher import Supervisor
from quick_stream.stream.wire import WireError, decode

from ..helpers import pipeline_specs
from . import repo_env

VIEWER_FIFO = 4  # samples the viewer's FifoChannel holds before zenoh's receive path waits for it


def viewer_main(argv: list[str]) -> int:
    """The slow viewer process: ``python -m tests.tools.slow_viewer viewer ENDPOINT MODE KEY HANDLER SLEEP``.
    Prints one JSON line (samples received, peers it had direct links to) when it gets SIGTERM."""

    import zenoh

    endpoint, mode, key, handler, sleep_s = argv[0], argv[1], argv[2], argv[3], float(argv[4])
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    if mode == "peer":
        conf.insert_json5("listen/endpoints", json.dumps(["tcp/127.0.0.1:0"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    got = [0]
    peers: set[str] = set()
    session = zenoh.open(conf)

    def slow(_sample: Any) -> None:
        got[0] += 1
        peers.update(str(z) for z in session.info.peers_zid())
        stop.wait(sleep_s)

    if handler == "callback":
        sub = session.declare_subscriber(key, slow)
        stop.wait()
    else:
        sub = session.declare_subscriber(key, zenoh.handlers.FifoChannel(VIEWER_FIFO))
        while not stop.is_set():
            sample = sub.try_recv()
            if sample is None:
                stop.wait(0.01)
            else:
                slow(sample)
    print(json.dumps({"viewer_received": got[0], "viewer_direct_peers": len(peers)}), flush=True)
    sub.undeclare()
    try:
        session.close()
    except zenoh.ZError:
        pass
    return 0


def run(args: argparse.Namespace) -> dict[str, Any]:
    from quick_stream.stream.launcher import free_port, open_when_up

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rec = out / "rec.mcap"
    if rec.exists():
        rec.unlink()
    shutil.rmtree(out / "logs", ignore_errors=True)  # "end of stream" in an earlier run's render.log
    ep = f"tcp/127.0.0.1:{free_port()}"
    cfg = [x for kv in args.services_cfg for x in ("--cfg", kv)]
    flags = ["--stream", args.stream, *cfg, *(["-m", args.services_mode] if args.services_mode else [])]
    w, h = args.size.split("x")
    capture = ["--source", f"synthetic:frames={args.frames},width={w},height={h}", "--fps", str(args.fps)]
    specs = pipeline_specs(out, ep, capture=capture, flags=flags, router=cfg)
    sup = Supervisor(specs, out / "logs", max_restarts=0)
    sup.start("router")
    # the driver's own eye on the output: a client that only notes when each stabilized frame arrives
    session = open_when_up(ep, timeout_s=20.0)
    arrivals: list[float] = []
    key = args.key.replace("{stream}", args.stream)
    viewer = None
    if args.viewer != "none":
        viewer = subprocess.Popen([sys.executable, "-m", "tests.tools.slow_viewer", "viewer", ep, args.viewer, key,
                                   args.handler, str(args.sleep)], stdout=subprocess.PIPE, text=True, env=repo_env())
    if viewer is not None:
        time.sleep(1.0)  # the viewer's session is up before the services start
    watch = session.declare_subscriber(f"quick/@v1/{args.stream}/stabilized", lambda _s: arrivals.append(time.monotonic()))
    for s in specs[1:]:
        sup.start(s.name)
    log = out / "logs" / "render.log"
    t0 = time.monotonic()
    paused = None
    try:
        deadline = time.monotonic() + args.frames / args.fps + 120
        while time.monotonic() < deadline:
            time.sleep(0.1)
            sup.poll()
            if args.pause and paused is None and time.monotonic() - t0 > args.pause_at:
                victim, secs = args.pause.split(":")
                paused = victim
                os.kill(sup.pid(victim), signal.SIGSTOP)  # a healthy service that stops reading for a while
                time.sleep(float(secs))
                os.kill(sup.pid(victim), signal.SIGCONT)
            if log.exists() and "end of stream" in log.read_text():
                break
        else:
            raise SystemExit(f"no end of stream in time: see {out / 'logs'}")
    finally:
        viewer_report: dict[str, Any] = {}
        if viewer is not None:
            viewer.terminate()
            try:
                text, _ = viewer.communicate(timeout=20)
                viewer_report = json.loads(text.strip().splitlines()[-1]) if text.strip() else {}
            except (subprocess.TimeoutExpired, ValueError):
                viewer.kill()
        codes = sup.stop()
        watch.undeclare()
        session.close()
    report = {"viewer": args.viewer, "pause": args.pause, "handler": args.handler, "services_cfg": args.services_cfg,
              "services_mode": args.services_mode or "peer", "exit_codes": codes, **viewer_report}
    report.update(summarize(rec, arrivals))
    return report


def summarize(rec: Path, arrivals: list[float]) -> dict[str, Any]:
    """The pipeline's side of it, from the recording's stats (worst of every period for put times)."""
    worst: dict[str, float] = {}
    last: dict[str, dict] = {}
    stabilized = 0
    for topic, _, data in read_messages(rec):
        if not topic.startswith("quick/"):
            continue
        try:
            m = decode(data)
        except WireError:
            continue
        if m.type == "stats":
            last[m.obj.service] = m.obj.values
            for k, v in m.obj.values.items():
                if k.endswith("_put_ms_max"):
                    name = f"{m.obj.service}.{k[4:-11]}"
                    worst[name] = max(worst.get(name, 0.0), float(v))
        elif m.type == "stabilized":
            stabilized += 1
    f, r, c = last.get("flow", {}), last.get("render", {}), last.get("capture", {})
    slow = {f"{svc}.{k[4:-10]}": v for svc, vals in last.items() for k, v in vals.items()
            if k.endswith("_slow_puts") and v}
    gaps = [b - a for a, b in zip(arrivals, arrivals[1:])]
    return {"sent": c.get("sent"), "shed": c.get("shed"), "flow_inbox_dropped": f.get("inbox0_dropped"),
            "render_flagged": r.get("flagged"), "render_missing": r.get("missing"), "render_orphans": r.get("orphans"),
            "stabilized_recorded": stabilized, "stabilized_seen": len(arrivals),
            "output_pause_s": round(max(gaps), 2) if gaps else None,
            "put_ms_max": {k: round(v) for k, v in sorted(worst.items())}, "slow_puts": slow}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m tests.tools.slow_viewer", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--viewer", choices=("peer", "client", "none"), default="peer",
                   help="the viewer's zenoh mode (peer: listens, so gossip links it to the services directly)")
    p.add_argument("--handler", choices=("fifo", "callback"), default="fifo",
                   help="fifo: a bounded FifoChannel read slowly (default); callback: a callback that sleeps")
    p.add_argument("--key", default="quick/@v1/{stream}/**", help="what the viewer subscribes to")
    p.add_argument("--sleep", type=at.nonneg_float, default=1.0, help="seconds the viewer spends per sample")
    p.add_argument("--frames", type=at.positive_int, default=450, help="frames the capture sends (default 450)")
    p.add_argument("--fps", type=at.positive_float, default=30.0)
    p.add_argument("--size", type=at.frame_size, default="320x240", help="frame size WxH (default 320x240)")
    p.add_argument("--stream", type=at.stream_id, default="cam0")
    p.add_argument("--services-mode", choices=("peer", "client"), default=None,
                   help="the services' zenoh mode (default: peer, as `quick-stream up`)")
    p.add_argument("--services-cfg", action="append", default=[], metavar="KEY:VALUE",
                   help="a zenoh setting for every service and the router (repeatable)")
    p.add_argument("--pause", default=None, metavar="SERVICE:SECONDS",
                   help="also stop a healthy service (SIGSTOP) for SECONDS mid-stream, e.g. motion:2")
    p.add_argument("--pause-at", type=at.nonneg_float, default=8.0, help="seconds after the start (default 8)")
    p.add_argument("--out", type=at.output_dir("--out"), default="out/bench-slow-viewer",
                   help="folder for the recording and logs")
    return p


def main(argv: list[str] | None = None) -> int:
    """The driver (prints its report as one JSON line); ``viewer ...``: the viewer process itself."""
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["viewer"]:
        return viewer_main(argv[1:])
    args = build_parser().parse_args(argv)
    try:
        at.check_outputs(args)
    except ValueError as e:
        print(f"slow_viewer: {e}", file=sys.stderr)
        return 2
    print(json.dumps(run(args)))
    return 0


if __name__ == "__main__":
    sys.exit(main())

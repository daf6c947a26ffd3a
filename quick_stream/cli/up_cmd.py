"""``quick-stream up``: the whole streaming stabilizer on this host, with live status.

Starts a Zenoh router (a Python process, no ``zenohd``) and the services as
separate processes, all on loopback: recorder, flow, motion, render, then
capture (which waits until the others are up). With ``--tls-dir`` the router
requires mutual TLS and enforces its access control, and every service is a TLS
client of it with its own certificate (deploy/tls/make-certs.sh; docs/deployment.md). Shows fps, ms per item, drops and
restarts per service once a second; restarts a service that dies; stops
everything cleanly when the source is exhausted and the last frame is rendered,
after ``--duration`` seconds, or on Ctrl-C. The stabilizer settings (the defaults, a replayed
recording's, ``--settings`` and the flags) go into one file, ``<out>/logs/settings.toml``, which
every service reads (``--settings``). Leaves in ``--out`` the MCAP recording
and the stabilized MP4, never overwriting an earlier run's (``recording-1.mcap``,
``stabilized-1.mp4``, ...), and the services' logs (``<out>/logs``).
"""
from __future__ import annotations

import argparse
import json
import signal
import sys
import time
from pathlib import Path

import zenoh

from ..io.recording import fresh_path
from ..io.sinks import VIDEO_CODECS
from ..stream.argtypes import plain_text
from ..io.sources import SourceError, check_source, source_settings
from ..stream import argtypes as at
from ..stream.launcher import ServiceSpec, StatusBoard, Supervisor, free_port, open_when_up, router_spec
from ..io.settings_file import settings_toml
from ..io.stabilizer_flags import add_stabilizer_args, stabilizer_params

SERVICES = ("recorder", "flow", "motion", "render", "capture")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("up", help="run router + all services locally, with live status",
                       description=plain_text(__doc__), formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--source", default="synthetic", metavar="SPEC",
                   help="synthetic[:k=v,...], tum:PATH, mcap:FILE or depthai[:DEVICE_ID][,k=v,...] "
                   "(default: synthetic)")
    p.add_argument("--frames", type=at.positive_int, default=None,
                   help="stop the source after this many frames (default: all)")
    p.add_argument("--duration", type=at.positive_float, default=None, metavar="S",
                   help="stop everything after this many seconds (default: when the source is done)")
    p.add_argument("--pace", choices=("realtime", "fast"), default="realtime",
                   help="realtime: frames sent at their own timestamps; fast: as fast as the pipeline takes "
                   "them (default: realtime)")
    p.add_argument("--fps", type=at.positive_float, default=None,
                   help="capture rate override, realtime pacing only (default: the source's rate)")
    p.add_argument("--stream", type=at.stream_id, default="cam0",
                   help="stream id, 1-64 of [A-Za-z0-9_-] (default: cam0)")
    p.add_argument("--out", type=at.output_dir("--out"), default="out", metavar="DIR",
                   help="folder for the recording, the stabilized video and logs; an earlier run's files are "
                   "kept, this run's numbered after them (default: out)")
    p.add_argument("--no-record", action="store_true", help="do not run the recorder")
    p.add_argument("--port", type=at.port, default=0, help="router port on 127.0.0.1 (default: a free one)")
    p.add_argument("--color", choices=("jpeg", "raw"), default="jpeg",
                   help="frame colour encoding on the wire (default: jpeg)")
    p.add_argument("--video-codec", choices=VIDEO_CODECS, default="mjpeg",
                   help="the stabilized video's codec: mjpeg stores the JPEGs the render publishes, with no second "
                   "encode; mp4v encodes each frame again (~2.5 ms a 640x480 frame), files a third of the size "
                   "(default mjpeg)")
    p.add_argument("--png", type=at.output_dir("--png", files="*.png"), default=None, metavar="DIR",
                   help="render also writes every frame as PNG here (default: none)")
    p.add_argument("--force", action="store_true",
                   help="overwrite PNG frames already in --png DIR (default: refuse)")
    p.add_argument("--quiet", action="store_true", help="no live status")
    p.add_argument("--tls-dir", default=None, metavar="DIR",
                   help="mutual TLS and access control: the folder deploy/tls/make-certs.sh wrote (router/, "
                   "monitor/: this command's own session, <stream>/<service>/); the services are TLS clients "
                   "of the router (default: no TLS)")
    p.add_argument("--router-config", default=None, metavar="FILE",
                   help="with --tls-dir: the router's configuration; its listen endpoint and certificate paths are "
                   "replaced (default: 'quick-stream acl --streams <stream>', written to <out>/logs/router-tls.json5)")
    add_stabilizer_args(p)


def tls_party(args: argparse.Namespace, name: str) -> tuple[str, str]:
    """(--tls-dir, --tls-name) of party ``name`` (router, monitor, or a service of ``args.stream``) in the
    folder make-certs.sh wrote."""
    d = Path(args.tls_dir)
    return (str(d / name), name) if name in ("router", "monitor") else (str(d / args.stream / name), name)


def check_tls(args: argparse.Namespace) -> None:
    """ValueError naming what is missing when ``--tls-dir`` lacks a certificate ``up`` needs."""
    if args.router_config and not args.tls_dir:
        raise ValueError("--router-config goes with --tls-dir")
    if not args.tls_dir:
        return
    from ..stream.transport import tls_settings

    names = ["router", "monitor", *(s for s in SERVICES if s != "recorder" or not args.no_record)]
    for name in names:
        d, n = tls_party(args, name)
        try:
            tls_settings(d, n, "client")
        except ValueError as e:
            raise ValueError(f"--tls-dir {args.tls_dir}: {e} (deploy/tls/make-certs.sh --streams {args.stream} "
                             f"{args.tls_dir})") from None
    if args.router_config and not Path(args.router_config).is_file():
        raise ValueError(f"--router-config {args.router_config}: no such file")


def service_specs(args: argparse.Namespace, endpoint: str, out: Path) -> list[ServiceSpec]:
    """Router first, then the services in start order, each with the zenoh flags to reach the router
    (with ``--tls-dir``: as TLS clients, each with its own certificate)."""
    tls = bool(getattr(args, "tls_dir", None))

    def z(name: str) -> list[str]:
        flags = ["-e", endpoint, "--no-multicast-scouting", "--stream", args.stream]
        if tls:
            d, n = tls_party(args, name)
            flags = ["-m", "client", *flags, "--tls-dir", d, "--tls-name", n]
        return flags

    st = ["--settings", str(args.settings_file)]
    router = ["-m", "quick_stream", "router", "-l", endpoint, "--no-multicast-scouting"]
    if tls:
        d, n = tls_party(args, "router")
        router += ["-c", str(args.router_config), "--tls-dir", d, "--tls-name", n]
    specs = [router_spec(router)]
    if not args.no_record:
        specs.append(ServiceSpec("recorder", ["-m", "quick_stream.services.recorder", *z("recorder"), *st,
                                              "--output", str(args.recording)]))
    specs += [
        ServiceSpec("flow", ["-m", "quick_stream.services.flow", *z("flow"), *st]),
        ServiceSpec("motion", ["-m", "quick_stream.services.motion", *z("motion"), *st]),
        ServiceSpec("render", ["-m", "quick_stream.services.render", *z("render"), *st,
                               "--output", str(getattr(args, "video", out / "stabilized.mp4")),
                               "--video-codec", args.video_codec]
                    + (["--png", args.png] if args.png else [])),
    ]
    wait = ",".join(s.name for s in specs[1:])
    cap = ["-m", "quick_stream.services.capture", *z("capture"), "--source", args.source, "--pace", args.pace,
           "--color", args.color, "--wait-for", wait]
    if args.frames is not None:
        cap += ["--frames", str(args.frames)]
    if args.fps is not None:
        cap += ["--fps", str(args.fps)]
    specs.append(ServiceSpec("capture", cap, may_finish=True))
    return specs


COLUMNS = (("fps", ("send_fps", "flow_fps", "motion_fps", "render_fps", "log_fps")),
           ("ms p50", ("send_ms_p50", "flow_ms_p50", "motion_ms_p50", "render_ms_p50", "log_ms_p50")),
           ("ms p99", ("send_ms_p99", "flow_ms_p99", "motion_ms_p99", "render_ms_p99", "log_ms_p99")))


def _first(v: dict, names: tuple[str, ...]) -> str:
    for n in names:
        if n in v:
            return f"{v[n]:.1f}" if isinstance(v[n], float) else str(v[n])
    return "-"


def status_lines(board: StatusBoard, sup: Supervisor, stream: str, t0: float) -> list[str]:
    lines = [f"quick-stream up: {time.monotonic() - t0:6.1f} s   stream {stream}",
             f"{'service':<9} {'state':<8} {'fps':>6} {'ms p50':>7} {'ms p99':>7} {'drops':>6} {'restarts':>8}  notes"]
    for name in SERVICES:
        if name not in sup.children:
            continue
        v = board.get(stream, name)
        c = sup.children[name]
        state = "up" if sup.running(name) else ("done" if c.finished else "down")
        drops = sum(int(x) for k, x in v.items() if k.endswith("_dropped") or k == "dropped")
        notes = []
        for k in ("bad_frames", "decode_errors", "refused_frames", "invalid_frames", "missing_frames", "timestamp_jumps",
                  "size_changes", "gaps", "motions_rotation", "motions_bridge", "invalid_motions", "orphans",
                  "missing", "flagged", "internal_errors"):
            if v.get(k):
                notes.append(f"{k} {v[k]}")
        if "lat_proc_ms_p99" in v:
            notes.append(f"latency processing p50/p99 {v.get('lat_proc_ms_p50', 0):.0f}/{v['lat_proc_ms_p99']:.0f} ms")
        lines.append(f"{name:<9} {state:<8} {_first(v, COLUMNS[0][1]):>6} {_first(v, COLUMNS[1][1]):>7} "
                     f"{_first(v, COLUMNS[2][1]):>7} {drops:>6} {c.restarts:>8}  {', '.join(notes)}")
    return lines


def write_status(path: Path, board: StatusBoard, sup: Supervisor, stream: str, reason: str | None) -> None:
    """Machine-readable live status (``<out>/logs/status.json``): pids, states, restarts, latest stats."""
    doc = {"time": time.time(), "stream": stream, "stopped": reason, "events": sup.events,
           "bad_stats_messages": board.errors, "services": {
        n: {"pid": sup.pid(n), "running": sup.running(n), "restarts": c.restarts, "finished": c.finished,
            "stats": board.get(stream, n)} for n, c in sup.children.items()}}
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(doc, indent=1))
    tmp.replace(path)


def run(args: argparse.Namespace) -> int:
    try:
        check_source(args.source)  # before any process starts: a bad spec is not capture's to find
        params = stabilizer_params(args, recorded=source_settings(args.source))
        check_tls(args)
    except SourceError as e:
        print(f"quick-stream up: --source: {e}", file=sys.stderr)
        return 2
    except ValueError as e:
        print(f"quick-stream up: {e}", file=sys.stderr)
        return 2
    stop: list[str] = []

    def on_signal(signum: int, _frame) -> None:
        stop.append("Ctrl-C" if signum == signal.SIGINT else f"signal {signal.Signals(signum).name}")

    # explicit handlers: also when started with SIGINT ignored (a background job) and for SIGTERM
    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    # never overwrite a recording or a video: an earlier run's stays, this one gets recording-1.mcap,
    # stabilized-1.mp4, ...
    args.recording = fresh_path(out / "recording.mcap")
    args.video = fresh_path(out / "stabilized.mp4")
    before = set(out.glob("recording*.mcap"))
    # one settings file for every service (and the recording's settings record)
    (out / "logs").mkdir(exist_ok=True)
    args.settings_file = fresh_path(out / "logs" / "settings.toml")
    args.settings_file.write_text(settings_toml(params, f"settings of {args.recording.name} (quick-stream up)"))
    endpoint = f"{'tls' if args.tls_dir else 'tcp'}/127.0.0.1:{args.port or free_port()}"
    if args.tls_dir and not args.router_config:
        from ..stream.acl import router_config_text

        args.router_config = str(out / "logs" / "router-tls.json5")
        Path(args.router_config).write_text(router_config_text([args.stream]))
    sup = Supervisor(service_specs(args, endpoint, out), out / "logs")
    sup.start("router")
    try:
        session = open_when_up(endpoint, timeout_s=20.0, tls=tls_party(args, "monitor") if args.tls_dir else None)
    except zenoh.ZError as e:
        sup.stop()
        print(f"quick-stream up: router did not come up on {endpoint}: {e} (see {out / 'logs' / 'router.log'})",
              file=sys.stderr)
        return 1
    for name in sup.children:
        if name != "router":
            sup.start(name)
    board = StatusBoard(session)
    t0 = time.monotonic()
    status_path = out / "logs" / "status.json"
    tty = sys.stdout.isatty() and not args.quiet
    shown = 0
    reason = "?"
    failed: list[str] = []
    try:
        while True:
            time.sleep(0.25)
            sup.poll()
            write_status(status_path, board, sup, args.stream, None)
            render = board.get(args.stream, "render")
            if render.get("ended", 0) >= 1 and sup.children["capture"].finished:
                reason = "source exhausted, last frame rendered"
                break
            if stop:
                reason = stop[0]
                break
            if args.duration is not None and time.monotonic() - t0 >= args.duration:
                reason = f"--duration {args.duration:g} s"
                break
            failed = [n for n, c in sup.children.items() if c.finished and c.exits and c.exits[-1][1] != 0]
            if failed:  # not restarted: cannot go on (exit 2: no camera, a bad flag, a full disk) or too many crashes
                reason = f"{failed[0]} failed (see logs/{failed[0]}.log)"
                break
            if not args.quiet and (tty or int((time.monotonic() - t0) * 4) % 20 == 0):
                lines = status_lines(board, sup, args.stream, t0)
                if tty and shown:
                    sys.stdout.write(f"\x1b[{shown}F")
                sys.stdout.write("\n".join(x + "\x1b[K" if tty else x for x in lines) + "\n")
                sys.stdout.flush()
                shown = len(lines)
    finally:
        final = status_lines(board, sup, args.stream, t0)
        order = [n for n in ("capture", "flow", "motion", "render", "recorder", "router") if n in sup.children]
        codes = sup.stop(order)
        write_status(status_path, board, sup, args.stream, reason)
        board.close()
        session.close()
    print(f"stopped: {reason}")
    print("\n".join(final))
    # -SIGTERM: a service stopped before it had installed its handler (while starting: nothing to clean up)
    bad = {n: c for n, c in codes.items() if c not in (0, None, -signal.SIGTERM)}
    if bad:
        print("exit codes: " + ", ".join(f"{n} {c}" for n, c in bad.items()), file=sys.stderr)
    for e in sup.events:
        print(f"event: {e['service']} {e['event']}")
    files = [args.video] + ([] if args.no_record else sorted(set(out.glob("recording*.mcap")) - before))
    print("wrote " + ", ".join(str(f) for f in files if f.exists()) + f" (logs in {out / 'logs'})")
    return 1 if failed else 0

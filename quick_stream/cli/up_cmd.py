"""``quick-stream up``: the whole streaming stabilizer on this host, with live status.

Starts a Zenoh router (a Python process, no ``zenohd``) and the services as
separate processes, all on loopback: recorder, flow, motion, render, then
capture (which waits until the others are up). With ``--tls-dir`` the router
requires mutual TLS and enforces its access control, and every service is a TLS
client of it with its own certificate (deploy/tls/make-certs.sh; docs/deployment.md). Shows fps, ms per item, drops and
restarts per service once a second (on stderr, a terminal's in place; ``--quiet``: none), and at
the end on stdout why it stopped, the services' last status, the account of every frame and the
files written; restarts a service that dies; stops
everything cleanly when the source is exhausted and the last frame is rendered,
after ``--duration`` seconds, or on Ctrl-C (then the capture stops first, and the frames it
sent get ``--stop-wait`` seconds to reach the video and the recording; a second Ctrl-C stops
at once). The stabilizer settings (the defaults, a replayed
recording's, ``--settings`` and the flags) go into one file, ``<out>/logs/settings.toml``, which
every service reads (``--settings``). Leaves in ``--out`` the MCAP recording
and the stabilized video (``stabilized.avi``: Motion JPEG; ``stabilized.mp4`` with ``--video-codec
mp4v``) and the services' logs and ``status.json`` (``<out>/logs``). A folder that holds an earlier
run's files keeps them: this run's files all get the next number free for every one of them
(``stabilized-1.avi``, ``recording-1.mcap`` and fresh logs in ``<out>/logs-1``), nothing is
overwritten or appended to.
"""
from __future__ import annotations

import argparse
import signal
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from ..io.sinks import VIDEO_CODECS
from ..stream.argtypes import plain_text
from ..io.sources import SourceError, check_source, source_settings
from ..stream import argtypes as at, topology
from ..stream.launcher import StatusBoard, Supervisor, free_port, open_when_up
from ..stream.process import close_within
from .up_report import child_failure, frame_account, log_tail, outputs, status_lines, write_status
from .up_run import RunPaths, check_tls, prepare_run, service_specs, tls_party
from ..io.stabilizer_flags import add_stabilizer_args, stabilizer_params

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
    p.add_argument("--stop-grace", type=at.positive_float, default=5.0, metavar="S",
                   help="seconds each process gets to finish after SIGTERM before it is killed (default: 5)")
    p.add_argument("--pace", choices=("realtime", "fast"), default="realtime",
                   help="realtime: frames sent at their own timestamps; fast: as fast as the pipeline takes "
                   "them (default: realtime)")
    p.add_argument("--fps", type=at.positive_float, default=None,
                   help="capture rate override, realtime pacing only (default: the source's rate)")
    p.add_argument("--stream", type=at.stream_id, default="cam0",
                   help="stream id, 1-64 of [A-Za-z0-9_-] (default: cam0)")
    p.add_argument("--out", type=at.output_dir("--out"), default="out", metavar="DIR",
                   help="folder for the recording, the stabilized video and the logs; an earlier run's files are "
                   "kept, this run's all numbered after them (stabilized-1.avi, recording-1.mcap, logs-1/) "
                   "(default: out)")
    p.add_argument("--no-record", action="store_true", help="do not run the recorder")
    p.add_argument("--port", type=at.port, default=0, help="router port on 127.0.0.1 (default: a free one)")
    p.add_argument("--color", choices=("jpeg", "raw"), default="jpeg",
                   help="frame colour encoding on the wire (default: jpeg)")
    p.add_argument("--video-codec", choices=VIDEO_CODECS, default="mjpeg",
                   help="the stabilized video's codec: mjpeg stores the JPEGs the render publishes, with no second "
                   "encode, in <out>/stabilized.avi; mp4v encodes each frame again (~2.5 ms a 640x480 frame), files "
                   "a third of the size, in <out>/stabilized.mp4 (default mjpeg)")
    p.add_argument("--png", type=at.output_dir("--png", files="*.png"), default=None, metavar="DIR",
                   help="render also writes every frame as PNG here (default: none)")
    p.add_argument("--force", action="store_true",
                   help="overwrite PNG frames already in --png DIR (default: refuse)")
    p.add_argument("--stop-wait", type=at.nonneg_float, default=10.0, metavar="S",
                   help="stopped before the stream's end (--duration, Ctrl-C): the capture stops first and ends the "
                   "stream, and the frames it sent get this many seconds to reach the video and the recording "
                   "before the other services stop; a second Ctrl-C stops at once (default 10)")
    p.add_argument("--quiet", action="store_true", help="no live status board (on stderr); the end is still said")
    p.add_argument("--tls-dir", default=None, metavar="DIR",
                   help="mutual TLS and access control: the folder deploy/tls/make-certs.sh wrote (router/, "
                   "monitor/: this command's own session, <stream>/<service>/); the services are TLS clients "
                   "of the router (default: no TLS)")
    p.add_argument("--router-config", default=None, metavar="FILE",
                   help="with --tls-dir: the router's configuration; its listen endpoint and certificate paths are "
                   "replaced (default: 'quick-stream acl --streams <stream>', written to <out>/logs/router-tls.json5)")
    add_stabilizer_args(p)


ENDED = "source exhausted, last frame rendered"


class Abort(Exception):
    """Why ``up`` gives up while starting (a signal, the router exited before it answered)."""


@dataclass
class Outcome:
    """How the run went: why it stopped, what failed (a write of ``up``'s own, a service)."""

    reason: str = "?"
    error: str | None = None  # what failed, in words (None: nothing)
    failed: list[str] = field(default_factory=list)  # services that failed and were not restarted
    drained: bool = False  # stopped before the stream's end, every frame sent reached the render's end
    cut: str | None = None  # why the frames sent did not all get to the outputs (None: they did, or no stop wait)


def say(text: str, err: bool = False) -> None:
    """Print, on stderr when ``err``; a closed stdout (``up | head``) loses the line, not the run."""
    try:
        print(text, file=sys.stderr if err else sys.stdout, flush=True)
    except OSError:
        pass


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
    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        return _run(args, params, stop)
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def cannot_write(e: OSError) -> str:
    return f"cannot write {e.filename or 'a file'}: {e.strerror or e}"


def _run(args: argparse.Namespace, params, stop: list[str]) -> int:
    out = Path(args.out)
    try:
        paths = prepare_run(args, params, out)
    except OSError as e:
        print(f"quick-stream up: {cannot_write(e)}", file=sys.stderr)
        return 2
    before = set(out.glob("recording*.mcap"))
    endpoint = f"{'tls' if args.tls_dir else 'tcp'}/127.0.0.1:{args.port or free_port()}"
    sup = Supervisor(service_specs(args, endpoint, paths), paths.logs)
    status_path = paths.status
    o = Outcome()
    session = board = None
    t0 = time.monotonic()

    def starting() -> None:  # between tries to reach the router
        if stop:
            raise Abort(f"{stop[0]} while the router was starting")
        if (rc := sup.exited("router")) is not None:
            why = log_tail(sup.log_dir / "router.log") or "its log is empty"
            raise Abort(f"router exited {rc} before it answered: {why}")

    try:
        sup.start("router")
        session = open_when_up(endpoint, timeout_s=20.0, tls=tls_party(args, "monitor") if args.tls_dir else None,
                               waiting=starting)
        for name in sup.children:
            if name != "router":
                sup.start(name)
        board = StatusBoard(session)
        _loop(args, sup, board, stop, status_path, t0, o)
        if o.reason != ENDED and not o.error and not o.failed:
            _drain(args, sup, board, stop, status_path, o)
    except Abort as e:
        o.reason = o.error = str(e)
    except zenoh.ZError as e:
        o.reason = o.error = f"router did not come up on {endpoint}: {e} (see {paths.logs / 'router.log'})"
    except OSError as e:  # a write of up's own: the status file, a service's log
        o.reason = o.error = cannot_write(e)
    except Exception as e:  # noqa: BLE001 - a bug of up's own: said, and the run still stopped and closed
        traceback.print_exc()
        o.reason = o.error = f"internal error: {type(e).__name__}: {e}"
    finally:
        # everything stopped, then the board from the services' last stats: the same counts as the
        # final account (a board taken before could miss flow's last stats, and drops with them)
        final: list[str] = []
        order = [n for n in (*topology.SERVICES, "router") if n in sup.children]  # as the data flows
        try:
            codes = sup.stop(order, grace_s=args.stop_grace)
            if board is not None:
                board.drain()  # the services' last stats (the router stops last)
                try:
                    final = status_lines(board, sup, args.stream, t0)
                except Exception:  # noqa: BLE001 - the session is closed whatever happens
                    final = []
        finally:  # the session closed whatever happened, within a bounded time
            closers = [c.close for c in (board, session) if c is not None]
            closing = close_within(closers, timeout_s=5.0) if closers else None
    return _finish(args, paths, sup, board, o, codes, before, final, closing)


def _loop(args: argparse.Namespace, sup: Supervisor, board: StatusBoard, stop: list[str], status_path: Path,
          t0: float, o: Outcome) -> None:
    """Until the stream is done, a signal, ``--duration``, or a failure (``o`` says which); OSError when
    the status file cannot be written."""
    board_out = sys.stderr  # the live status is progress, on stderr; stdout is for the run's result (its end)
    quiet = args.quiet
    tty = board_out.isatty() and not quiet
    shown = 0
    while True:
        time.sleep(0.25)
        for name in sup.poll():
            board.restarted(args.stream, name)
        write_status(status_path, board, sup, args.stream, None)
        render = board.get(args.stream, "render")
        if render.get("ended", 0) >= 1 and sup.children["capture"].finished:
            o.reason = ENDED
            return
        if stop:
            o.reason = stop[0]
            return
        if args.duration is not None and time.monotonic() - t0 >= args.duration:
            o.reason = f"--duration {args.duration:g} s"
            return
        o.failed = [n for n, c in sup.children.items() if c.finished and c.exit_code not in (0, None)]
        if o.failed:  # not restarted: cannot go on (exit 2: no camera, a bad flag, a full disk) or crashes
            o.reason = f"{o.failed[0]} failed (see {status_path.parent.name}/{o.failed[0]}.log)"
            o.error = "; ".join(child_failure(sup, n, Path(args.out)) for n in o.failed)
            return
        if not quiet and (tty or int((time.monotonic() - t0) * 4) % 20 == 0):
            lines = status_lines(board, sup, args.stream, t0)
            try:
                if tty and shown:
                    board_out.write(f"\x1b[{shown}F")
                board_out.write("\n".join(x + "\x1b[K" if tty else x for x in lines) + "\n")
                board_out.flush()
            except OSError:  # stderr closed (a pipe's reader went away): the run goes on, status.json has it
                quiet = True
            shown = len(lines)


def _drain(args: argparse.Namespace, sup: Supervisor, board: StatusBoard, stop: list[str], status_path: Path,
           o: Outcome, clock=time.monotonic, sleep=time.sleep) -> None:
    """Stopped before the stream's end (``--duration``, Ctrl-C, a signal): the capture is stopped first (it
    ends the stream after its last frame), then the frames it sent get ``--stop-wait`` seconds to reach
    the render's end (the video, and the recording, which stops after the render) before the other
    services are stopped. Stopping everything at once left the frames in flight out of the video (90
    sent, 60 in it). A second signal or a service that fails ends the wait; ``o.cut`` says why the
    frames sent did not all get there."""
    signals = len(stop)
    ended = board.get(args.stream, "render").get("ended", 0)
    if "capture" in sup.children and not sup.children["capture"].finished:
        sup.stop(["capture"], grace_s=args.stop_grace)  # SIGTERM: it sends no more frames and ends the stream
    board.drain()
    sent = int(board.totals(args.stream, "capture").get("sent", 0) or 0)
    if sent == 0 or args.stop_wait <= 0 or not sup.running("render"):
        if sent and args.stop_wait <= 0:
            o.cut = "--stop-wait 0: the services stopped with the capture"
        return
    say(f"quick-stream up: stopping ({o.reason}): the capture has ended the stream; the frames it sent get up to "
        f"{args.stop_wait:g} s to reach the outputs (Ctrl-C again: stop now)", err=True)
    deadline = clock() + args.stop_wait
    while True:
        if board.get(args.stream, "render").get("ended", 0) > ended:
            o.drained = True
            return
        if len(stop) > signals:
            o.cut = f"{stop[-1]} while the frames sent were on their way to the outputs"
            return
        if clock() >= deadline:
            o.cut = f"the frames sent were not all through the render within --stop-wait {args.stop_wait:g} s"
            return
        for name in sup.poll():
            board.restarted(args.stream, name)
        failed = [n for n, c in sup.children.items() if n != "capture" and c.finished
                  and c.exit_code not in (0, None)]
        if failed:
            o.failed = failed
            o.error = "; ".join(child_failure(sup, n, Path(args.out)) for n in failed)
            o.cut = f"{failed[0]} failed while the frames sent were on their way to the outputs"
            return
        write_status(status_path, board, sup, args.stream, None)
        sleep(0.1)


def _finish(args: argparse.Namespace, paths: RunPaths, sup: Supervisor, board: StatusBoard | None, o: Outcome,
            codes: dict[str, int | None], before: set[Path], final: list[str], closing: str | None) -> int:
    """After the children stopped and the session closed (``closing``: what went wrong closing it):
    the account, the outputs, status.json and the last lines; the exit code."""
    account = frame_account((lambda n: board.totals(args.stream, n)) if board is not None else (lambda n: {}))
    status_path = paths.status
    files = [(paths.video, account.rendered > 0)]
    files += [(f, False) for f in ([] if args.no_record else sorted(set(paths.recording.parent.glob("recording*.mcap"))
                                                                   - before))]
    whole, broken = outputs(files)
    nothing = account.rendered == 0
    code = 1 if (o.error or o.failed or nothing) else 0
    summary = None  # no account without the services' stats (the run never got that far)
    if board is not None:
        summary = account.line(args.pace, o.reason == ENDED or o.drained) + (
            ": nothing was produced" if nothing else "") + (f" ({o.cut})" if o.cut and account.lost else "")
    end = {"error": o.error, "exit_code": code, "frames": account.as_dict() if board is not None else None,
           "summary": summary,
           "outputs": {"whole": [str(f) for f in whole], "incomplete": {str(f): why for f, why in broken}}}
    try:
        write_status(status_path, board, sup, args.stream, o.reason, end)
    except OSError as e:
        say(f"quick-stream up: {cannot_write(e)} (the run's end is not in it)", err=True)
    if closing is not None:
        say(f"quick-stream up: closing its zenoh session: {closing}; exiting anyway", err=True)
    say(f"stopped: {o.reason}")
    if final:
        say("\n".join(final))
    if o.error:
        say(f"quick-stream up: {o.error}", err=True)
    # -SIGTERM: a service stopped before it had installed its handler (while starting: nothing to clean up)
    bad = {n: c for n, c in codes.items() if c not in (0, None, -signal.SIGTERM)}
    if bad:
        say("exit codes: " + ", ".join(f"{n} {c}" for n, c in bad.items()), err=True)
    for e in sup.events:
        say(f"event: {e['service']} {e['event']}")
    if summary is not None:
        say(summary, err=nothing)
    for f, why in broken:
        say(f"quick-stream up: {f} is incomplete: {why}", err=True)
    say(("wrote " + ", ".join(str(f) for f in whole) if whole else "wrote nothing") + f" (logs in {paths.logs})")
    return code

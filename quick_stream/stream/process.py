"""A service process around its runtime: flags, logging, ``main``, heap and CPU priority.

:func:`service_main` is every service's ``main`` (parse, log, build the zenoh config, check,
run); :func:`service_parser` the parser with the standard zenoh flags, ``--stream``, ``-v`` and
``--max-frame-side``; it has the C heap keep the frame-sized buffers it frees for the next frame
(:mod:`.heap`, whose ``trim_heap`` the runtime calls every ``TRIM_EVERY`` stats to hand freed
pages back to the OS). :func:`lower_priority` lowers the process's CPU priority.
"""
from __future__ import annotations

import argparse
import atexit
import logging
import os
import signal
import threading
import time
from typing import Any, Callable

import zenoh

from .heap import keep_freed_buffers
from .wire.pixels import MAX_IMAGE_PIXELS, MAX_PIXELS_ENV, set_max_image_pixels, set_max_image_side

MAX_SIDE_ENV = "QUICK_STREAM_MAX_FRAME_SIDE"  # the default of every service's --max-frame-side


def add_queue_args(p: argparse.ArgumentParser, *, queue: int | None = None, queue_help: str = "",
                   history: int | None = None, history_help: str = "") -> None:
    """A service's ``--queue`` (what its input inbox holds before the oldest is dropped) and
    ``--history`` (what its output publisher keeps for a successor and for recovery), each only
    when given a default; the helps say what the numbers mean for that service."""
    from . import argtypes as at

    if queue is not None:
        p.add_argument("--queue", type=at.positive_int, default=queue, help=queue_help)
    if history is not None:
        p.add_argument("--history", type=at.int_in(0), default=history, help=history_help)


def service_parser(service: str, description: str | None) -> argparse.ArgumentParser:
    """Argument parser with the standard zenoh flags, ``--stream`` and ``-v``."""
    from .argtypes import plain_text, stream_id
    from .transport import add_zenoh_args

    p = argparse.ArgumentParser(prog=f"quick-stream-{service}", description=plain_text(description),
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--stream", type=stream_id, default="cam0",
                   help="stream (camera) id, 1-64 of [A-Za-z0-9_-]; one per camera (default cam0)")
    p.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    p.add_argument("--max-frame-side", type=int, default=int(os.environ.get(MAX_SIDE_ENV, 4096)), metavar="PX",
                   help=f"largest image width or height accepted, checked from the header before decoding "
                   f"(default 4096, or ${MAX_SIDE_ENV})")
    p.add_argument("--max-frame-pixels", type=int, default=MAX_IMAGE_PIXELS,
                   metavar="N", help=f"most pixels (width x height) an image may have, checked from the header before "
                   f"decoding; bounds what one frame costs in memory (default 1920x1200 = 2304000, or ${MAX_PIXELS_ENV}; "
                   f"it applies to every process that decodes frames, quick-stream stabilize too)")
    add_zenoh_args(p)
    return p


TRIM_EVERY = 10  # stats periods (about 10 s)


def lower_priority(niceness: int) -> None:
    """Raise this process's nice value by ``niceness`` (background work such as recording yields
    the CPU to the live path on a busy machine; its queue absorbs the wait)."""
    if niceness > 0:
        os.nice(niceness)


def setup_logging(service: str, verbose: bool) -> None:
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO,
                        format=f"%(asctime)s {service} %(levelname)s: %(message)s")


def _ignore_term_while_exiting() -> None:
    """At interpreter exit, after the service's work and clean-up are done: ignore SIGTERM.
    CPython puts the default (fatal) handler back while it finalises, so a supervisor's SIGTERM
    arriving in those last moments (zenoh's objects are dropped there, slowly on a busy machine)
    turned a clean exit into -15; an ignored signal is left alone
    (tests/integration/test_faults.py::test_sigterm_while_a_finished_service_exits_keeps_the_clean_exit)."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)


CLOSE_TIMED_OUT = "did not finish within"  # what close_within says when a closer hung


def close_within(closers: list[Callable[[], None]], timeout_s: float) -> str | None:
    """Run ``closers`` in order (e.g. a subscription's undeclare, then its session's close) in a daemon
    thread, waiting at most ``timeout_s``: a close that hangs (a router that stopped answering) does
    not hang the caller. None when all ran, else what went wrong (the first error, or the timeout)."""
    errors: list[str] = []

    def close_all() -> None:
        for close in closers:
            try:
                close()
            except Exception as e:  # noqa: BLE001 - a close that fails leaves nothing more to do
                errors.append(f"{type(e).__name__}: {e}")

    t = threading.Thread(target=close_all, name="close", daemon=True)
    t.start()
    t.join(timeout_s)
    if t.is_alive():
        return f"{CLOSE_TIMED_OUT} {timeout_s:g} s"
    return errors[0] if errors else None


SESSION_CLOSE_S = 5.0  # the longest a service waits for its zenoh session to close
_unclosed: list[str] = []  # sessions whose close did not finish: the process then exits without finalising


def closed_late(problem: str) -> None:
    """A session's close did not finish (its router went away: a SIGKILLed ``up`` takes its router with
    it): :func:`service_main` then ends the process at once, its outputs finished, instead of letting
    the interpreter's finalisation wait on zenoh again (a recorder ran on for over a minute)."""
    _unclosed.append(problem)


PROFILE_ENV = "QUICK_STREAM_PROFILE"  # a folder: each service profiles its main thread into it (bench pipeline --profile)


def _profiled(service: str, run: Callable[[argparse.Namespace, zenoh.Config], int]
              ) -> Callable[[argparse.Namespace, zenoh.Config], int]:
    """``run`` itself, or, when ``QUICK_STREAM_PROFILE`` names a folder, ``run`` under :mod:`cProfile`
    writing ``<folder>/<service>-<pid>.prof`` when it returns (read by ``bench pipeline --profile``)."""
    folder = os.environ.get(PROFILE_ENV)
    if not folder:
        return run

    def profiled(args: argparse.Namespace, conf: zenoh.Config) -> int:
        import cProfile

        prof = cProfile.Profile(time.thread_time)  # the main thread's CPU time: a wait costs nothing
        prof.enable()
        try:
            return run(args, conf)
        finally:
            prof.disable()
            prof.dump_stats(os.path.join(folder, f"{service}-{os.getpid()}.prof"))
    return profiled


def service_main(service: str, parser: argparse.ArgumentParser, run: Callable[[argparse.Namespace, zenoh.Config], int],
                 argv: list[str] | None, check: Callable[[argparse.Namespace], Any] | None = None,
                 early: Callable[[argparse.Namespace], int | None] | None = None) -> int:
    """A service's ``main``: parse, log, one OpenCV thread, build the zenoh config (and ``check`` the
    service's own settings and that its output paths can be written), then ``run(args, conf)``; a bad
    flag or config exits 2 with its message, before any session is opened. A session zenoh refuses
    to open (e.g. a listen endpoint already in use) is logged with zenoh's reason, exit 2.
    ``early`` may answer without a session (e.g. ``--list-devices``) by returning an exit code."""
    import cv2

    from .argtypes import check_outputs
    from .transport import config_from_args, zenoh_message

    args = parser.parse_args(argv)
    setup_logging(service, args.verbose)
    keep_freed_buffers()
    atexit.unregister(_ignore_term_while_exiting)  # once, however often main() runs in one process
    atexit.register(_ignore_term_while_exiting)
    if early is not None and (code := early(args)) is not None:
        return code
    cv2.setNumThreads(1)
    try:
        if hasattr(args, "max_frame_side"):
            set_max_image_side(args.max_frame_side)
        if hasattr(args, "max_frame_pixels"):
            set_max_image_pixels(args.max_frame_pixels)
        conf = config_from_args(args)
        check_outputs(args)
        if check is not None:
            check(args)
    except ValueError as e:
        logging.getLogger(service).error("%s", e)
        return 2
    try:
        code = _profiled(service, run)(args, conf)
    except zenoh.ZError as e:
        logging.getLogger(service).error("zenoh: %s (check -e/-l/-c/--cfg and the QUICK_STREAM_ZENOH_* variables)",
                                         zenoh_message(e))
        return 2
    if _unclosed:  # its outputs are finished; the interpreter's finalisation would wait on zenoh again
        logging.getLogger(service).warning("exiting without waiting for zenoh: its session's close %s", _unclosed[0])
        logging.shutdown()
        os._exit(code)
    return code

"""``quick-stream router``: a Zenoh router in a Python process (no ``zenohd`` needed).

The hub the services connect to (``-e tcp/HOST:7447``). Listens on
``tcp/0.0.0.0:7447`` unless ``-l`` (or the ``-c`` file) says otherwise; the other standard
zenoh flags (``-e`` to other routers, ``-c``, ``--cfg``, ``--no-multicast-scouting``, TLS)
apply. Always a router: ``-m`` takes ``router`` only (a ``mode`` set by the ``-c`` file or
QUICK_STREAM_ZENOH_MODE is overridden). Runs until SIGTERM/SIGINT.
"""
from __future__ import annotations

import argparse
import os
import signal
import sys
import threading

import zenoh

from ..stream.argtypes import plain_text
from ..stream.transport import add_zenoh_args, config_from_args, zenoh_message

DEFAULT_LISTEN = "tcp/0.0.0.0:7447"


CLOSE_TIMEOUT_S = 10.0  # a stopping router exits after this even if its session is still closing


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("router", help="run a Zenoh router (the services' hub)", description=plain_text(__doc__),
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    add_zenoh_args(p)
    for action in p._actions:  # the standard zenoh flags, as a router takes them
        if action.dest == "mode":  # always a router: -m takes only that (peer/client would be refused by name)
            action.choices, action.default = ("router",), "router"
            action.help = "session mode: always router for this command (default: router)"
        elif action.dest == "listen":
            action.help = (f"endpoint to listen on; repeatable (default: {DEFAULT_LISTEN}, unless the -c file "
                           "sets listen endpoints)")


def router_config(args: argparse.Namespace) -> zenoh.Config:
    """The router's config: the flags, in router mode (``-m`` takes nothing else), listening on 7447 by default."""
    args.mode = "router"
    if not args.listen and not args.config:
        args.listen = [DEFAULT_LISTEN]
    return config_from_args(args)


def _stop_when_orphaned(stop: threading.Event, period_s: float = 0.5) -> None:
    """Stop once this process is re-parented (its launcher, ``up``, died). The launcher's
    parent-death signal stops the services; a SIGKILLed ``up`` once left the router running
    without a trace of that signal (a fresh clone, quiet machine), so the router also watches."""
    parent = os.getppid()
    while not stop.wait(period_s):
        if os.getppid() != parent:
            print("quick-stream router: its launcher is gone; stopping", file=sys.stderr, flush=True)
            stop.set()


def run(args: argparse.Namespace) -> int:
    try:
        conf = router_config(args)
    except ValueError as e:
        print(f"quick-stream router: {e}", file=sys.stderr)
        return 2
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as e:  # e.g. the listen address is in use
        print(f"quick-stream router: cannot start: {zenoh_message(e)}", file=sys.stderr)
        return 2
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    threading.Thread(target=_stop_when_orphaned, args=(stop,), daemon=True).start()
    try:
        print(f"quick-stream router: up, zid {session.zid()}, listening on {', '.join(args.listen or ['(config)'])}",
              file=sys.stderr, flush=True)
        stop.wait()
    finally:
        print("quick-stream router: stopping", file=sys.stderr, flush=True)
        # bounded: closing a router whose clients are going away at the same moment (a SIGKILLed `up`
        # takes every child down at once) once left it running for over a minute on a loaded machine
        closer = threading.Thread(target=session.close, daemon=True)
        closer.start()
        closer.join(CLOSE_TIMEOUT_S)
        if closer.is_alive():
            print(f"quick-stream router: the session did not close in {CLOSE_TIMEOUT_S:g} s; exiting",
                  file=sys.stderr, flush=True)
            os._exit(0)
    return 0

"""Starting, watching and restarting the service processes of one host (``quick-stream up``).

* :class:`Supervisor` runs each service as a child process (``python -m
  quick_stream.services.<name>``; never a fork of a process holding a zenoh
  session: zenoh's runtime does not survive a fork), writes its output to ``<log_dir>/<name>.log``, restarts
  it when it dies (any exit but a clean one of a service allowed to finish),
  and stops everything in order: SIGTERM, then SIGKILL after a grace period. Each child runs in
  its own session (a Ctrl-C at the terminal reaches the supervisor only, which stops the children
  in order) and dies with the supervisor: it gets SIGTERM when the supervisor dies, however it
  dies (:data:`PARENT_DEATH`; a SIGKILLed ``up`` leaves no service running).
* :class:`StatusBoard` listens to every service's ``stats`` messages and keeps
  the latest per service, for the live status and the final summary.
* :func:`free_port`, :func:`open_when_up`: a loopback port for a router, and a
  client session to it once it answers (``up``, the benchmarks, the tests).
"""
from __future__ import annotations

import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from . import keys
from .cursor import RESTARTED_ENV
from .wire import WireError, check

log = logging.getLogger(__name__)

# Run by each child before it execs its service (``python -I -S -c PARENT_DEATH SUPERVISOR_PID SIGNAL ARGV...``):
# Linux's parent-death signal (prctl PR_SET_PDEATHSIG = 1, kept across exec) sends it SIGNAL when the
# supervisor dies: SIGTERM, so a service stops cleanly as on Ctrl-C, or SIGKILL for a child with nothing
# to flush (:func:`router_spec`). If the supervisor died before that call (the child
# was re-parented), there is nothing to run for. Not in Popen's preexec_fn: the supervisor has zenoh's
# threads, and Python code between fork and exec may then deadlock. Linux sends the signal when the
# *thread* that started the child ends: start and restart children from a thread that lives as long
# as the supervisor (``up``: its main thread). Elsewhere (no prctl) the child runs without it.
PARENT_DEATH = """\
import ctypes, os, signal, sys
supervisor = int(sys.argv[1])
try:
    ctypes.CDLL(None, use_errno=True).prctl(1, int(sys.argv[2]))
except (OSError, AttributeError):
    pass
if os.getppid() != supervisor:
    try:
        os.kill(supervisor, 0)
    except ProcessLookupError:
        sys.exit(0)
os.execv(sys.argv[3], sys.argv[3:])
"""


@dataclass
class ServiceSpec:
    """One child process: ``argv`` after ``python``; ``may_finish``: exit code 0 means done, not crashed."""

    name: str
    argv: list[str]
    may_finish: bool = False
    restart: bool = True
    prefix: list[str] = field(default_factory=list)  # e.g. ["ip", "netns", "exec", "cam"] (must exec)
    on_parent_death: int = signal.SIGTERM  # what the child gets when the supervisor dies (PARENT_DEATH)


def router_spec(argv: list[str], **kw: Any) -> ServiceSpec:
    """The router's :class:`ServiceSpec`: killed outright when the supervisor dies. It holds nothing to
    flush, and once, after a SIGKILLed ``up``, it went on running for over a minute without handling
    its SIGTERM or noticing it was orphaned (1 fresh-clone CI run in 4; not reproduced in 21 tries)."""
    return ServiceSpec("router", argv, on_parent_death=signal.SIGKILL, **kw)


@dataclass
class Child:
    spec: ServiceSpec
    proc: subprocess.Popen | None = None
    started: float = 0.0
    restarts: int = 0
    finished: bool = False
    exits: list[tuple[float, int]] = field(default_factory=list)  # (time, returncode) of each death


class Supervisor:
    """Runs and restarts a set of service processes."""

    def __init__(self, specs: list[ServiceSpec], log_dir: str | Path, restart_delay_s: float = 0.1,
                 max_restarts: int = 20, env: dict[str, str] | None = None) -> None:
        self.children = {s.name: Child(s) for s in specs}
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.restart_delay_s = restart_delay_s
        self.max_restarts = max_restarts
        self.env = {**os.environ, **(env or {})}
        self.events: list[dict[str, Any]] = []
        self._lock = threading.Lock()

    def _spawn(self, c: Child) -> None:
        logf = open(self.log_dir / f"{c.spec.name}.log", "ab")
        # a restarted service is told so (it waits longer for the others before deciding that no
        # stream is under way: killed with the router, they may take seconds to reconnect)
        env = {**self.env, RESTARTED_ENV: str(c.restarts)} if c.restarts else self.env
        argv = [sys.executable, "-I", "-S", "-c", PARENT_DEATH, str(os.getpid()), str(int(c.spec.on_parent_death)),
                sys.executable, *c.spec.argv]
        c.proc = subprocess.Popen([*c.spec.prefix, *argv], stdout=logf, stderr=subprocess.STDOUT,
                                  stdin=subprocess.DEVNULL, env=env, start_new_session=True)
        logf.close()
        c.started = time.monotonic()

    def start(self, name: str | None = None) -> None:
        """Start one service (or all, in the order given)."""
        for c in ([self.children[name]] if name else self.children.values()):
            self._spawn(c)

    def poll(self) -> list[str]:
        """Restart crashed services; returns the names restarted now."""
        out = []
        with self._lock:
            for c in self.children.values():
                if c.proc is None or c.finished:
                    continue
                rc = c.proc.poll()
                if rc is None:
                    continue
                c.exits.append((time.monotonic(), rc))
                if rc == 0 and c.spec.may_finish:
                    c.finished = True
                    self.events.append({"t": time.time(), "service": c.spec.name, "event": "finished"})
                    continue
                if rc == 2:  # cannot go on (a bad flag, no camera, a full disk): a restart cannot mend it
                    c.finished = True
                    self.events.append({"t": time.time(), "service": c.spec.name,
                                        "event": "exited 2 (cannot go on, see its log), not restarted"})
                    log.error("%s exited with 2 (cannot go on, see its log); not restarting", c.spec.name)
                    continue
                if not c.spec.restart or c.restarts >= self.max_restarts:
                    c.finished = True
                    self.events.append({"t": time.time(), "service": c.spec.name, "event": f"died ({rc}), not restarted"})
                    log.error("%s exited with %s; not restarting", c.spec.name, rc)
                    continue
                time.sleep(self.restart_delay_s)
                c.restarts += 1
                self._spawn(c)
                self.events.append({"t": time.time(), "service": c.spec.name, "event": f"died ({rc}), restarted"})
                log.warning("%s exited with %s; restarted (%d)", c.spec.name, rc, c.restarts)
                out.append(c.spec.name)
        return out

    def pid(self, name: str) -> int | None:
        p = self.children[name].proc
        return None if p is None else p.pid

    def running(self, name: str) -> bool:
        c = self.children[name]
        return c.proc is not None and c.proc.poll() is None

    def stop(self, order: list[str] | None = None, grace_s: float = 5.0) -> dict[str, int | None]:
        """SIGTERM the services in ``order`` (default: reverse start order), each waited for up to
        ``grace_s`` before SIGKILL; returns their exit codes."""
        names = order or list(reversed(self.children))
        codes: dict[str, int | None] = {}
        with self._lock:
            for n in names:
                self.children[n].finished = True
            for n in names:
                p = self.children[n].proc
                if p is None:
                    continue
                if p.poll() is None:
                    p.send_signal(signal.SIGTERM)
                    try:
                        p.wait(grace_s)
                    except subprocess.TimeoutExpired:
                        log.error("%s did not stop within %.0f s of SIGTERM; killing it", n, grace_s)
                        p.kill()
                        p.wait()
                codes[n] = p.returncode
        return codes


class StatusBoard:
    """Latest ``stats`` of every service of every stream, from a zenoh subscription."""

    def __init__(self, session: zenoh.Session) -> None:
        self.latest: dict[tuple[str, str], dict[str, Any]] = {}
        self.updated: dict[tuple[str, str], float] = {}
        self.errors = 0
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(keys.all_streams("stats"), self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            stream, stage = keys.parse(key)
            m = check(sample.payload.to_bytes(), stream, stage)  # a stats message of the key's stream
        except (ValueError, WireError) as e:  # WireError is a ValueError too
            self.errors += 1
            if self.errors <= 10 or self.errors % 1000 == 0:  # one line per bad message, not a flood
                log.warning("bad message on %s (%d so far): %s", key, self.errors, e)
            return
        with self._lock:
            self.latest[(m.stream, m.obj.service)] = dict(m.obj.values)
            self.updated[(m.stream, m.obj.service)] = time.monotonic()

    def get(self, stream: str, service: str) -> dict[str, Any]:
        with self._lock:
            return dict(self.latest.get((stream, service), {}))

    def snapshot(self) -> dict[tuple[str, str], dict[str, Any]]:
        with self._lock:
            return {k: dict(v) for k, v in self.latest.items()}

    def close(self) -> None:
        self._sub.undeclare()


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now (for a router started next)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def open_when_up(endpoint: str, timeout_s: float, tls: tuple[str, str] | None = None) -> zenoh.Session:
    """A client session to the router at ``endpoint``, retried until it answers or ``timeout_s``;
    ``tls``: (folder, name) of its certificate."""
    from .transport import session_config

    conf = session_config(endpoint, "client", *(tls or (None, None)))
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return zenoh.open(conf)
        except zenoh.ZError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)

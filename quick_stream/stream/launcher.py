"""Starting, watching and restarting the service processes of one host (``quick-stream up``).

* :class:`Supervisor` runs each service as a child process (``python -m
  quick_stream.services.<name>``; never a fork of a process holding a zenoh
  session: zenoh's runtime does not survive a fork), writes its output to ``<log_dir>/<name>.log``, restarts
  it when it dies (any exit but a clean one of a service allowed to finish; not an exit 2, "cannot go
  on", nor a crash loop: ``crash_loop`` error exits in a row, each within ``min_uptime_s`` of its
  start), and stops everything in order: SIGTERM, then SIGKILL after a grace period. Each child runs in
  its own session (a Ctrl-C at the terminal reaches the supervisor only, which stops the children
  in order) and dies with the supervisor: it gets SIGTERM when the supervisor dies, however it
  dies (:data:`PARENT_DEATH`; a SIGKILLed ``up`` leaves no service running).
* :class:`StatusBoard` reads every service's ``stats`` messages (pulled from a ring buffer by the
  caller's thread: zenoh starts no thread of ours, so an open session never holds up the
  interpreter's exit) and keeps the latest per service, and the counts of a restarted service's
  predecessors, for the live status and the final summary.
* :func:`free_port`, :func:`open_when_up`: a loopback port for a router, a client session to it once
  it answers (``up``, the benchmarks, the tests; giving up at once when the caller says so: the router
  died, a signal came); its close cannot hang the caller (:func:`~quick_stream.stream.process.close_within`).
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
from typing import Any, Callable

import zenoh

from . import keys
from .cursor import RESTARTED_ENV
from .inbox import publisher_of
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
    flush, and a router left orphaned by a SIGKILLed ``up`` has been seen to run on for over a minute
    without handling its SIGTERM (tests/integration/test_parent_death.py)."""
    return ServiceSpec("router", argv, on_parent_death=signal.SIGKILL, **kw)


@dataclass
class Child:
    spec: ServiceSpec
    proc: subprocess.Popen | None = None
    started: float = 0.0
    restarts: int = 0
    finished: bool = False
    exits: list[tuple[float, int]] = field(default_factory=list)  # (time, returncode) of each death
    quick_exits: int = 0  # error exits in a row, each soon after its start (a crash loop)
    reaped: bool = False  # the current process's exit is in ``exits``

    @property
    def exit_code(self) -> int | None:
        """The last exit code (None: never exited)."""
        return self.exits[-1][1] if self.exits else None


class Supervisor:
    """Runs and restarts a set of service processes."""

    def __init__(self, specs: list[ServiceSpec], log_dir: str | Path, restart_delay_s: float = 0.1,
                 max_restarts: int = 20, env: dict[str, str] | None = None, min_uptime_s: float = 10.0,
                 crash_loop: int = 3) -> None:
        """``min_uptime_s``, ``crash_loop``: a service that exits with an error (a code > 0, not a signal:
        a killed service is restarted) ``crash_loop`` times in a row, each time within ``min_uptime_s``
        of its start, is not restarted again (it cannot start: a restart will not mend it)."""
        self.children = {s.name: Child(s) for s in specs}
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.restart_delay_s = restart_delay_s
        self.max_restarts = max_restarts
        self.min_uptime_s, self.crash_loop = min_uptime_s, crash_loop
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
        c.reaped = False

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
                now = time.monotonic()
                if not c.reaped:  # (unless :meth:`exited` recorded it)
                    c.exits.append((now, rc))
                    c.reaped = True
                c.quick_exits = c.quick_exits + 1 if rc > 0 and now - c.started < self.min_uptime_s else 0
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
                if c.quick_exits >= self.crash_loop:
                    c.finished = True
                    why = (f"exited {rc} {c.quick_exits} times in a row, each within {self.min_uptime_s:g} s of its "
                           "start: not restarted (see its log)")
                    self.events.append({"t": time.time(), "service": c.spec.name, "event": why})
                    log.error("%s %s", c.spec.name, why)
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

    def exited(self, name: str) -> int | None:
        """The exit code of ``name``'s current process if it has exited (recorded), else None; no restart."""
        c = self.children[name]
        rc = None if c.proc is None else c.proc.poll()
        if rc is not None and not c.reaped:
            c.exits.append((time.monotonic(), rc))
            c.reaped = True
        return rc

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
                if not self.children[n].reaped:
                    self.children[n].exits.append((time.monotonic(), p.returncode))
                    self.children[n].reaped = True
        return codes


class StatusBoard:
    """Latest ``stats`` of every service of every stream, from a zenoh subscription read by
    :meth:`drain` (called by :meth:`get`, :meth:`totals` and :meth:`snapshot`): samples wait in a
    ring of ``capacity`` (the oldest dropped), no thread of zenoh's runs our code.

    A service's counters start again from 0 when it is restarted (its stats numbering starts again
    too): :meth:`totals` adds the last values its predecessors published, so a restart hides no
    count (the predecessor's last second, after its last stats message, is not known).

    A service's stats are taken from one publisher (the zenoh session that sent them,
    :func:`~quick_stream.stream.inbox.publisher_of`): another publisher's stats under its name are
    ignored (counted in :attr:`foreign`) unless that one has been quiet for ``quiet_s`` or the service
    was restarted (:meth:`restarted`, its supervisor's word). A stats message forged with a lower seq passed for a restart and
    added the service's counts to its totals again (the live fuzz: flow's refused frames counted twice
    in the final summary, docs/reliability.md)."""

    def __init__(self, session: zenoh.Session, capacity: int = 4096, quiet_s: float = 3.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.quiet_s, self.clock = quiet_s, clock
        self.foreign = 0  # stats under a service's name from a publisher other than the service's
        self._source: dict[tuple[str, str], str | None] = {}
        self._restarted: set[tuple[str, str]] = set()  # services restarted: their next publisher is taken
        self.latest: dict[tuple[str, str], dict[str, Any]] = {}
        self.updated: dict[tuple[str, str], float] = {}
        self.carried: dict[tuple[str, str], dict[str, int]] = {}  # predecessors' counts (int values summed)
        self._errors = 0
        self._seq: dict[tuple[str, str], int] = {}
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(keys.all_streams("stats"), zenoh.handlers.RingChannel(capacity))

    def drain(self) -> None:
        """Take in every stats message that has arrived."""
        while True:
            try:
                sample = self._sub.try_recv()
            except zenoh.ZError:  # closed
                return
            if sample is None:
                return
            self._on_sample(sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            stream, stage = keys.parse(key)
            m = check(sample.payload.to_bytes(), stream, stage)  # a stats message of the key's stream
        except (ValueError, WireError) as e:  # WireError is a ValueError too
            self._errors += 1
            if self._errors <= 10 or self._errors % 1000 == 0:  # one line per bad message, not a flood
                log.warning("bad message on %s (%d so far): %s", key, self._errors, e)
            return
        k = (m.stream, m.obj.service)
        source, now = publisher_of(sample), self.clock()
        with self._lock:
            if (k in self.latest and k not in self._restarted and source != self._source.get(k)
                    and now - self.updated[k] < self.quiet_s):
                self.foreign += 1  # the service is alive and publishing: not its stats
                if self.foreign <= 10 or self.foreign % 1000 == 0:
                    log.warning("stats of %s/%s from %s, not from the service's publisher %s: ignored (%d so far)",
                                *k, source, self._source.get(k), self.foreign)
                return
            self._source[k] = source
            self._restarted.discard(k)
            if k in self.latest and m.seq <= self._seq.get(k, -1):  # numbered from 0 again: a restarted service
                carried = self.carried.setdefault(k, {})
                for name, v in self.latest[k].items():
                    if isinstance(v, int) and not isinstance(v, bool):
                        carried[name] = carried.get(name, 0) + v
            self._seq[k] = m.seq
            self.latest[k] = dict(m.obj.values)
            self.updated[k] = now

    def restarted(self, stream: str, service: str) -> None:
        """``service`` was restarted (by its supervisor): the next stats under its name come from its new
        process's publisher, taken at once (not only after ``quiet_s``: a recorder restarted 2 s after its
        kill near a stream's end had its stats, and the hole it logged, ignored)."""
        self.drain()  # what the predecessor sent before is its own
        with self._lock:
            self._restarted.add((stream, service))

    @property
    def errors(self) -> int:
        """Stats messages that were not (undecodable, of another stream than their key's, not stats)."""
        self.drain()
        return self._errors

    def get(self, stream: str, service: str) -> dict[str, Any]:
        """The latest stats of ``service`` (its current process's)."""
        self.drain()
        with self._lock:
            return dict(self.latest.get((stream, service), {}))

    def totals(self, stream: str, service: str) -> dict[str, Any]:
        """The latest stats of ``service`` with its predecessors' counts added (every int value: meaningful
        for counters, such as ``sent`` or ``missing_frames``, not for gauges, such as ``buffered``)."""
        self.drain()
        with self._lock:
            out = dict(self.latest.get((stream, service), {}))
            for name, v in self.carried.get((stream, service), {}).items():
                out[name] = out.get(name, 0) + v if isinstance(out.get(name, 0), int) else out[name]
            return out

    def snapshot(self) -> dict[tuple[str, str], dict[str, Any]]:
        self.drain()
        with self._lock:
            return {k: dict(v) for k, v in self.latest.items()}

    def close(self) -> None:
        self._sub.undeclare()


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now (for a router started next)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def open_when_up(endpoint: str, timeout_s: float, tls: tuple[str, str] | None = None,
                 waiting: Callable[[], None] | None = None) -> zenoh.Session:
    """A client session to the router at ``endpoint``, retried until it answers or ``timeout_s``
    (zenoh.ZError); ``tls``: (folder, name) of its certificate. ``waiting`` is called before each
    try and may raise to give up (the router died, a signal came): each try waits at most a few
    seconds for the router (1 s, then 2 s, then 4 s), not the client's usual 30 s."""
    from .transport import session_config

    deadline = time.monotonic() + timeout_s
    attempt_s = 1.0
    while True:
        if waiting is not None:
            waiting()
        conf = session_config(endpoint, "client", *(tls or (None, None)))
        left = max(deadline - time.monotonic(), 0.1)
        conf.insert_json5("connect/timeout_ms", str(int(min(attempt_s, left) * 1000)))
        try:
            return zenoh.open(conf)
        except zenoh.ZError:
            if time.monotonic() > deadline:
                raise
            attempt_s = min(attempt_s * 2, 4.0)
            time.sleep(0.2)



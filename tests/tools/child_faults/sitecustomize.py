"""Test tool: one process of ``quick-stream up`` misbehaves on purpose (tests/integration/test_up_failures.py).

Put this folder on ``PYTHONPATH`` and name the fault in ``QUICK_STREAM_TEST_FAULT=<process>:<fault>``;
every Python process started with that environment imports this module at start-up (``site``), and
the one whose command line is ``-m quick_stream router`` (``router``) or ``-m
quick_stream.services.<process>`` acts on it (``up``'s children: the launcher's parent-death wrapper
runs with ``-I -S`` and ignores it, the service it execs does not):

* ``hang``: ignores SIGTERM and never gets going (a process stuck before it answers anyone);
* ``exit1``: exits 1 at once (a service that cannot start, a crash loop);
* ``lose=A-B`` (flow): the frames numbered A to B never reach its stage, as if lost on the way;
* ``slow=MS`` (flow): every frame takes MS milliseconds longer (a pipeline behind the capture).
"""
from __future__ import annotations

import os


def _target() -> str | None:
    try:
        argv = open("/proc/self/cmdline", "rb").read().decode(errors="replace").split("\0")
    except OSError:
        return None
    if "-m" not in argv or argv.index("-m") + 1 >= len(argv):
        return None
    module, rest = argv[argv.index("-m") + 1], argv[argv.index("-m") + 2:]
    if module == "quick_stream" and rest[:1] == ["router"]:
        return "router"
    prefix = "quick_stream.services."
    return module[len(prefix):] if module.startswith(prefix) else None


def _lose(first: int, last: int) -> None:
    from quick_stream.core import flow_stage

    push = flow_stage.FlowDriver.push

    def lossy(self, frame, *args, **kw):
        if first <= frame.seq <= last:
            return []
        return push(self, frame, *args, **kw)

    flow_stage.FlowDriver.push = lossy


def _slow(ms: float) -> None:
    import time

    from quick_stream.core import flow_stage

    push = flow_stage.FlowDriver.push

    def slow(self, frame, *args, **kw):
        time.sleep(ms / 1000)
        return push(self, frame, *args, **kw)

    flow_stage.FlowDriver.push = slow


def _apply(spec: str) -> None:
    name, _, fault = spec.partition(":")
    if _target() != name:
        return
    if fault == "hang":
        import signal
        import time

        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        while True:
            time.sleep(1)
    elif fault == "exit1":
        os._exit(1)
    elif fault.startswith("lose="):
        a, _, b = fault[len("lose="):].partition("-")
        _lose(int(a), int(b))
    elif fault.startswith("slow="):
        _slow(float(fault[len("slow="):]))


if os.environ.get("QUICK_STREAM_TEST_FAULT"):
    _apply(os.environ["QUICK_STREAM_TEST_FAULT"])

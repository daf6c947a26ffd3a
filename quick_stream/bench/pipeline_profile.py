"""``bench pipeline --profile``: where each process's CPU goes, per stabilized frame.

Two views of the same run:

* **threads** (:func:`thread_cpu`): each process's CPU split by thread from ``/proc/<pid>/task``:
  the main thread (where a service decodes, computes and publishes), its other Python threads (a
  render's video writer, a recorder's flusher, and the threads zenoh calls subscribers back on, where
  each arriving message is checked: :mod:`quick_stream.stream.arrivals`) and zenoh's own runtime
  (``rx-*``, ``tx-*``, ``net-*``, ...), as shares of the process's CPU over the run;
* **functions** (:func:`summarise`): each service's main thread under :mod:`cProfile` (the service
  does that itself when ``QUICK_STREAM_PROFILE`` names a folder:
  :func:`quick_stream.stream.process.service_main`), its functions by own time in ms per stabilized
  frame, on that thread's CPU clock (``time.thread_time``: a call that blocks, a publisher's put
  waiting for Python's lock or the network, costs only the CPU it uses), the calls a service waits
  in left out. The profiler's own cost slows the services by about half, Python-heavy code more
  than OpenCV's: read the table for where the time goes, the rate and CPU columns of a run
  without it for how much.
"""
from __future__ import annotations

import os
import pstats
from pathlib import Path

from ..stream.process import PROFILE_ENV

__all__ = ["PROFILE_ENV", "format_profile", "stat_cpu", "summarise", "thread_cpu", "thread_shares"]

CLK = os.sysconf("SC_CLK_TCK")
# names of the calls a service makes to wait for work (its own time is idle, not work)
WAITS = ("acquire", "sleep", "select", "poll", "wait", "epoll")


def stat_cpu(stat: str) -> float:
    """CPU seconds (user + system) of a ``/proc/<pid>/stat`` or ``/proc/<pid>/task/<tid>/stat`` text."""
    f = stat[stat.rindex(")") + 2:].split()
    return (int(f[11]) + int(f[12])) / CLK


def thread_cpu(pid: int) -> dict[str, float]:
    """CPU seconds a live process's threads have used, by group: ``main`` (the thread whose id is the
    process's), ``python`` (its other threads that kept the process's name: Python's own threads, the
    ones zenoh calls subscribers back on among them) and ``zenoh`` (the threads that named themselves:
    zenoh's runtime, ``rx-0``, ``tx-0``, ``net-0``, ...); {} if it is gone."""
    out = {"main": 0.0, "python": 0.0, "zenoh": 0.0}
    try:
        tasks = sorted(Path(f"/proc/{pid}/task").iterdir(), key=lambda t: t.name != str(pid))  # main first
    except OSError:
        return {}
    name = None
    for t in tasks:
        try:
            stat = (t / "stat").read_text()
        except OSError:
            continue  # a thread that ended meanwhile
        comm = stat[stat.index("(") + 1:stat.rindex(")")]
        cpu = stat_cpu(stat)
        if t.name == str(pid):
            name, group = comm, "main"
        else:
            group = "python" if comm == name else "zenoh"
        out[group] += cpu
    return out


def thread_shares(cpu: dict[str, float]) -> dict[str, float]:
    """:func:`thread_cpu`'s seconds as percentages of their sum."""
    total = sum(cpu.values())
    return {k: round(100.0 * v / total, 1) for k, v in cpu.items()} if total > 0 else {}


def summarise(folder: Path, frames: int, top: int = 12) -> dict[str, list[dict]]:
    """Per service (the ``<service>-<pid>.prof`` files in ``folder``): its ``top`` functions by own
    time, waits left out, as ms and calls per stabilized frame (``frames``, the run's total)."""
    out: dict[str, list[dict]] = {}
    for prof in sorted(folder.glob("*.prof")):
        service = prof.stem.rsplit("-", 1)[0]
        try:
            st = pstats.Stats(str(prof))
        except (OSError, EOFError, TypeError, ValueError):
            continue  # a service killed while writing it
        rows = []
        for (file, line, name), (_cc, calls, own, cum, _callers) in st.stats.items():  # type: ignore[attr-defined]
            if _bare(name) in WAITS:
                continue
            where = name if file == "~" else f"{Path(file).name}:{line}({name})"
            rows.append({"function": where, "own_ms": 1e3 * own / max(frames, 1),
                         "cum_ms": 1e3 * cum / max(frames, 1), "calls": calls / max(frames, 1)})
        rows.sort(key=lambda r: -r["own_ms"])
        out[service] = [{k: round(v, 3) if isinstance(v, float) else v for k, v in r.items()} for r in rows[:top]]
    return out


def _bare(name: str) -> str:
    """A profiled function's own name: ``acquire`` of ``<method 'acquire' of '_thread.lock' objects>``,
    ``sleep`` of ``<built-in method time.sleep>``."""
    if name.startswith("<method '"):
        return name.split("'")[1]
    if name.startswith("<built-in method "):
        return name[len("<built-in method "):-1].rsplit(".", 1)[-1]
    return name


def format_profile(threads: dict[str, dict[str, float]], functions: dict[str, list[dict]]) -> str:
    """The two views as text lines."""
    lines = []
    if threads:
        lines.append("  CPU by thread (% of the process's): " + "; ".join(
            f"{name} " + ", ".join(f"{k} {v:.0f}" for k, v in s.items()) for name, s in threads.items() if s))
    for service, rows in functions.items():
        lines.append(f"  {service}: own time in ms per stabilized frame (cProfile, main thread, waits left out)")
        for r in rows:
            lines.append(f"    {r['own_ms']:7.3f} ms  {r['calls']:6.2f} calls  {r['function']}")
    return "\n".join(lines)

"""What ``quick-stream up`` shows and leaves: the status board, ``<out>/logs/status.json``, the
account of every frame the source offered, and which of its outputs are whole.

The *drops* column counts, per service, the frames lost there or on the way to it, from the
services' own stats (a restarted service's predecessors included, :meth:`StatusBoard.totals`):

* capture: frames shed (offered faster than the pipeline takes them) or that the source could not
  deliver or encode (``shed``, ``bad_frames``);
* flow: frames it shed itself (``shed``: a publisher faster than the pipeline takes them; those its full
  queue dropped among them) and frames missing from the numbering it received (``missing_frames``: lost
  in transit) besides those the capture shed or could not deliver;
* render: frames rendered uncorrected (``flagged``) or not rendered at all: dropped from what it holds,
  refused, unreadable or dropped from its queues;
* motion, recorder: what their queues dropped (the recorder: Foxglove views thinned) and, the
  recorder, what it could not write (``unrecorded``).

A queue's drops are the stream's own messages only: a flood from another publisher is shed first
(``inbox<i>_dropped_foreign``) and drops none of the stream's frames.

A frame lost on the way to flow but rendered uncorrected shows at both (flow: lost; render:
uncorrected). The final account (:class:`FrameAccount`) splits the frames the source offered
once each: stabilized, shed at the capture, shed at flow, lost in transit, rendered uncorrected,
dropped at render.
"""
from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable

from ..io.file_checks import incomplete
from ..stream import topology
from ..stream.launcher import StatusBoard, Supervisor

SERVICES = topology.START_ORDER  # the receivers up before the frames come
COLUMNS = (("fps", ("send_fps", "flow_fps", "motion_fps", "render_fps", "log_fps")),
           ("ms p50", ("send_ms_p50", "flow_ms_p50", "motion_ms_p50", "render_ms_p50", "log_ms_p50")),
           ("ms p99", ("send_ms_p99", "flow_ms_p99", "motion_ms_p99", "render_ms_p99", "log_ms_p99")))
NOTES = ("bad_frames", "shed", "decode_errors", "refused_frames", "invalid_frames", "missing_frames", "timestamp_jumps",
         "size_changes", "gaps", "motions_rotation", "motions_bridge", "invalid_motions", "orphans", "missing",
         "flagged", "dropped", "unrecorded", "error", "internal_errors")
Totals = Callable[[str], dict[str, Any]]  # a service's stats, its predecessors' counts included


def _n(v: dict[str, Any], key: str) -> int:
    x = v.get(key, 0)
    return int(x) if isinstance(x, (int, float)) and not isinstance(x, bool) else 0


def _queues(v: dict[str, Any]) -> int:
    """Messages of the stream's own publishers its queues dropped (another publisher's, shed first when a
    queue is full, ``inbox<i>_dropped_foreign``, are no frame of the stream)."""
    return sum(_n(v, k) - _n(v, f"{k}_foreign") for k in v if k.startswith("inbox") and k.endswith("_dropped"))


def frame_drops(service: str, totals: Totals) -> int:
    """The frames lost at ``service`` or on the way to it (module docstring)."""
    v = totals(service)
    if service == "capture":
        return _n(v, "shed") + _n(v, "bad_frames")
    if service == "flow":  # its own shedding (a frame its full queue drops is one of them), then the rest
        cap = totals("capture")
        return _n(v, "shed") + max(_n(v, "missing_frames") - _n(cap, "shed") - _n(cap, "bad_frames"),
                                   _queues(v) - _n(v, "shed_backlog"), 0)
    if service == "render":
        return (_n(v, "flagged") + _n(v, "dropped") + _n(v, "refused_frames") + _n(v, "bad_frames")
                + _queues(v))
    return _queues(v) + _n(v, "dropped") + _n(v, "unrecorded")


@dataclass
class FrameAccount:
    """Every frame the source offered, once: ``offered`` = ``stabilized`` + ``shed`` + ``bad_source`` +
    ``shed_flow`` + ``lost`` + ``uncorrected`` + ``dropped_render``. ``missing_at_flow``: of the frames sent, those flow
    never had (lost in transit or dropped from its queue; rendered uncorrected or lost, or corrected
    by a path that restarts across them). ``render_known``: render published its stats."""

    offered: int
    sent: int
    shed: int
    bad_source: int
    rendered: int
    uncorrected: int
    dropped_render: int
    lost: int
    missing_at_flow: int
    render_known: bool
    shed_flow: int = 0  # of the frames sent, those the flow service shed (a publisher faster than the pipeline)

    @property
    def stabilized(self) -> int:
        return self.rendered - self.uncorrected

    def line(self, pace: str, whole_stream: bool = True) -> str:
        """``stabilized N of M frames: K shed at the capture (because ...), J lost in transit, ...``;
        ``whole_stream``: False when the run was stopped before the stream's end (frames in flight
        then are among those not rendered)."""
        if not self.render_known:
            head = f"stabilized frames not known (render published no stats) of {self.offered} frames:"
        else:
            head = f"stabilized {self.stabilized} of {self.offered} frames:"
        why = ""
        if self.shed:
            why = (" (because the pipeline took frames more slowly than the capture offered them at real-time "
                   "pace: `--pace fast` waits for the pipeline instead)" if pace == "realtime"
                   else " (because the pipeline fell behind)")
        lost = (f"{self.lost} lost in transit" if whole_stream
                else f"{self.lost} not rendered (in flight when the run stopped, or lost in transit)")
        parts = [f"{self.shed} shed at the capture{why}", lost, f"{self.uncorrected} rendered uncorrected (flagged)",
                 f"{self.dropped_render} dropped at render"]
        if self.shed_flow:
            parts.insert(1, f"{self.shed_flow} shed at flow (frames came faster than the pipeline takes them)")
        if self.bad_source:
            parts.append(f"{self.bad_source} the source could not deliver")
        text = f"{head} {', '.join(parts)}"
        if self.missing_at_flow:
            text += (f"; flow missed {self.missing_at_flow} of the frames sent (lost in transit or dropped from its "
                     "queue: the path restarts across them)")
        return text

    def as_dict(self) -> dict[str, Any]:
        return {**asdict(self), "stabilized": self.stabilized}


def frame_account(totals: Totals) -> FrameAccount:
    """The account of the run from the services' stats (:class:`FrameAccount`)."""
    cap, flow, render = totals("capture"), totals("flow"), totals("render")
    sent, shed, bad = _n(cap, "sent"), _n(cap, "shed"), _n(cap, "bad_frames")
    rendered, flagged = _n(render, "render_total"), _n(render, "flagged")
    unrendered = max(sent - rendered, 0)
    dropped = min(_n(render, "dropped") + _n(render, "refused_frames") + _n(render, "bad_frames") + _queues(render),
                  unrendered)
    shed_flow = min(_n(flow, "shed"), unrendered - dropped)
    return FrameAccount(offered=sent + shed + bad, sent=sent, shed=shed, bad_source=bad, rendered=rendered,
                        uncorrected=min(flagged, rendered), dropped_render=dropped, lost=unrendered - dropped - shed_flow,
                        missing_at_flow=max(_n(flow, "missing_frames") - shed - bad, 0), render_known=bool(render),
                        shed_flow=shed_flow)


def state(sup: Supervisor, name: str) -> str:
    """up, down (restarting), done (exited cleanly, or stopped by ``up``) or ``exit N``."""
    c = sup.children[name]
    if sup.running(name):
        return "up"
    if not c.finished:
        return "down"
    rc = c.exit_code
    return "done" if rc in (0, None, -15) else f"exit {rc}"


def _first(v: dict, names: tuple[str, ...]) -> str:
    for n in names:
        if n in v:
            return f"{v[n]:.1f}" if isinstance(v[n], float) else str(v[n])
    return "-"


def status_lines(board: StatusBoard, sup: Supervisor, stream: str, t0: float) -> list[str]:
    """The status board: one line per service."""
    lines = [f"quick-stream up: {time.monotonic() - t0:6.1f} s   stream {stream}",
             f"{'service':<9} {'state':<8} {'fps':>6} {'ms p50':>7} {'ms p99':>7} {'drops':>6} {'restarts':>8}  notes"]
    totals = lambda n: board.totals(stream, n)  # noqa: E731
    for name in SERVICES:
        if name not in sup.children:
            continue
        v, t = board.get(stream, name), totals(name)
        notes = [f"{k} {t[k]}" for k in NOTES if t.get(k)]
        if "lat_proc_ms_p99" in v:
            notes.append(f"latency processing p50/p99 {v.get('lat_proc_ms_p50', 0):.0f}/{v['lat_proc_ms_p99']:.0f} ms")
        lines.append(f"{name:<9} {state(sup, name):<8} {_first(v, COLUMNS[0][1]):>6} {_first(v, COLUMNS[1][1]):>7} "
                     f"{_first(v, COLUMNS[2][1]):>7} {frame_drops(name, totals):>6} {sup.children[name].restarts:>8}  "
                     f"{', '.join(notes)}")
    return lines


def write_status(path: Path, board: StatusBoard | None, sup: Supervisor, stream: str, reason: str | None,
                 end: dict[str, Any] | None = None) -> None:
    """Machine-readable status (``<out>/logs/status.json``): pids, states, restarts, exit codes, latest
    stats and drops (none without a ``board``: the run never got that far); ``reason``: why the run
    stopped (None: running); ``end``: what the run ended with (``error``, ``exit_code``, ``frames``:
    the :class:`FrameAccount`, ``summary``, ``outputs``). Raises OSError naming ``path`` when it cannot
    be written (the part written is removed); with ``end``, a full disk first gets a shortened status
    written over the old one in place (truncating it frees what the short one needs)."""
    totals = (lambda n: board.totals(stream, n)) if board is not None else (lambda n: {})
    latest = (lambda n: board.get(stream, n)) if board is not None else (lambda n: {})
    doc = {"time": time.time(), "stream": stream, "stopped": reason, **(end or {}), "events": sup.events,
           "bad_stats_messages": board.errors if board is not None else 0, "services": {
               n: {"pid": sup.pid(n), "running": sup.running(n), "state": state(sup, n), "restarts": c.restarts,
                   "finished": c.finished, "exit_codes": [rc for _, rc in c.exits],
                   "drops": frame_drops(n, totals) if n != "router" else 0, "stats": latest(n)}
               for n, c in sup.children.items()}}
    tmp = path.with_suffix(".tmp")
    try:
        tmp.write_text(json.dumps(doc, indent=1))
        tmp.replace(path)
    except OSError as e:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass
        if end is not None:
            short = {k: doc[k] for k in ("time", "stream", "stopped")} | {
                k: end.get(k) for k in ("error", "exit_code", "summary")} | {
                "note": f"shortened, written in place: the whole status could not be written ({e.strerror or e})"}
            try:
                with path.open("r+" if path.exists() else "w") as f:
                    f.truncate(0)
                    f.write(json.dumps(short, indent=1))
                return
            except OSError:
                pass
        raise OSError(e.errno, e.strerror or str(e), str(path)) from None


def outputs(files: list[tuple[Path, bool]]) -> tuple[list[Path], list[tuple[Path, str]]]:
    """``files`` (each with whether it must be there) split into those whole on disk and the others
    with why (:func:`incomplete`); a file never made that need not be is left out of both."""
    whole, broken = [], []
    for f, required in files:
        if not required and not f.exists():
            continue
        problem = incomplete(f)
        if problem is None:
            whole.append(f)
        else:
            broken.append((f, problem))
    return whole, broken


def log_tail(path: Path, lines: int = 2) -> str:
    """The last ``lines`` non-empty lines of a log, joined (empty when there is none or it cannot be read)."""
    try:
        with path.open("rb") as f:
            f.seek(max(f.seek(0, 2) - 4096, 0))
            text = f.read().decode("utf-8", "replace")
    except OSError:
        return ""
    return " | ".join([x.strip() for x in text.splitlines() if x.strip()][-lines:])


def child_failure(sup: Supervisor, name: str, out: Path) -> str:
    """In words, how child ``name`` failed: its exit code (or event) and the end of its log."""
    c = sup.children[name]
    rc = c.exit_code
    event = next((e["event"] for e in reversed(sup.events) if e["service"] == name), None)
    what = event if event else f"exited {rc}"
    tail = log_tail(sup.log_dir / f"{name}.log")
    if tail:
        return f"{name} {what}: {tail}"
    try:
        import shutil

        full = shutil.disk_usage(out).free == 0
    except OSError:
        full = False
    return f"{name} {what}; its log ({sup.log_dir / (name + '.log')}) is empty" + (
        f" ({out} has no space left)" if full else "")

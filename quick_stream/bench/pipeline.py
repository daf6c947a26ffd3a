"""``quick-stream bench pipeline``: the streaming service under load, measured from outside.

Runs the router and every service as separate processes (the ``up`` layout, recording
on) with the capture at a fixed rate (``--fps``) or as fast as it can (``--fast``),
and measures from a monitor session:

* **latency** of each stabilized frame from its stamps (docs/wire-format.md):
  total = received - source published; *segment wait* = when the frame that closed
  its release was published (the planner's look-ahead included: the correction's
  ``closed_by``) - source published; *processing* = total - wait
  (scene flow of the closing pair, motion, path, transport, warp, render, encode,
  and the wait for the frames before it in the same segment, rendered in order);
  *processing, first of batch* = the same for the first frame of each released
  segment (nothing ahead of it), and, with recording on, that frame's wait split into the
  stages it crosses (:mod:`.release_steps`, from the recorder's arrival times); *beyond
  longest wait* = total - the longest segment wait seen: what a player showing every frame
  at one fixed delay needs on top of the one-segment latency (later frames of a batch have a
  frame period of slack each);
* **throughput and drops**: frames sent, stabilized, flagged (orphans: frames some
  stage dropped), per-service inbox drops, render's dropped/missing counters and the frames a
  live capture shed (offered faster than the pipeline takes them);
* **CPU and memory per process** from ``/proc``: mean CPU % over the run, RSS once warm (the
  minute after the first) and over the last minute, the growth between them, the peak (VmHWM)
  and the series from start-up;
* **CPU per stabilized frame**: each process's CPU time per frame stabilized (all streams), their
  sum, and what the machine's cores give per frame at the rate reached (:func:`cpu_per_frame`):
  a rate whose sum is near that budget is limited by the CPU, not by a stage waiting on another.

Prints a table and writes JSON (``--json FILE``, ``-``: standard output); progress on stderr
once a second. Numbers are for the machine it runs on. The run's recordings and videos (about 1 GB
for the 120 s default at 640x480) are scratch: deleted once measured unless ``--keep``, the logs
kept; the last line says where they were and how much (:func:`scratch_files`).
"""
from __future__ import annotations

import json
import os
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import zenoh

from ..io.recording import RecordingError, fresh_path
from ..stream import keys, topology
from ..stream.launcher import StatusBoard, Supervisor, router_spec
from ..stream.stream_specs import stream_specs
from ..stream.wire import WireError
from ..stream.wire.codec import unpack
from .pipeline_profile import PROFILE_ENV, stat_cpu, summarise, thread_cpu, thread_shares
from .pipeline_report import DEFAULT_PRESET, format_presets, format_report
from .release_steps import release_steps


def proc_sample(pid: int) -> tuple[float, int, int] | None:
    """(CPU seconds used, RSS bytes, peak RSS bytes) of a process, None if it is gone."""
    try:
        cpu = stat_cpu(Path(f"/proc/{pid}/stat").read_text())
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    vals = {ln.split(":")[0]: int(ln.split()[1]) * 1024 for ln in status.splitlines()
            if ln.startswith(("VmRSS", "VmHWM"))}
    return cpu, vals.get("VmRSS", 0), vals.get("VmHWM", 0)


@dataclass
class Monitor:
    """Receives stabilized frames (envelope and stamps only) and records their latency."""

    total_ms: list[float] = field(default_factory=list)
    t_recv: list[float] = field(default_factory=list)  # monotonic receive time of each latency sample
    wait_ms: list[float] = field(default_factory=list)
    proc_ms: list[float] = field(default_factory=list)
    first_ms: list[float] = field(default_factory=list)  # processing of each batch's first frame
    seqs: list[int] = field(default_factory=list)
    flagged: int = 0
    ended: bool = False
    t_first: float | None = None
    t_last: float | None = None
    _last_ready: int | None = None
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def on_sample(self, sample: zenoh.Sample) -> None:
        now = time.time_ns()
        try:
            r = unpack(sample.payload.to_bytes())
        except WireError:
            return
        with self._lock:
            if r.type == "end":
                self.ended = True
                return
            if r.type != "stabilized":
                return
            src, ready = r.d.get("src_pub_ns"), r.d.get("ready_pub_ns")
            self.seqs.append(r.seq)
            self.flagged += bool(r.d.get("flags"))
            t = time.monotonic()
            self.t_first = self.t_first or t
            self.t_last = t
            if src and ready:
                self.t_recv.append(t)
                self.total_ms.append((now - src) / 1e6)
                self.wait_ms.append((ready - src) / 1e6)
                self.proc_ms.append((now - ready) / 1e6)
                if ready != self._last_ready:
                    self.first_ms.append((now - ready) / 1e6)
                    self._last_ready = ready


def _pct(a: list[float]) -> dict[str, float]:
    if not a:
        return {}
    x = np.asarray(a)
    return {"p50": float(np.percentile(x, 50)), "p90": float(np.percentile(x, 90)),
            "p99": float(np.percentile(x, 99)), "max": float(x.max()), "n": int(x.size)}


def prerecord(path: Path, spec: str) -> str:
    """Encode a source's frames once into an MCAP (as capture would send them); returns its spec.

    Replaying it (``capture --source mcap:FILE`` sends the recorded bytes) costs the capture
    almost nothing, like a camera driver handing over frames, so the numbers show the
    pipeline without the synthetic renderer's CPU."""
    from ..io.recording import Recorder
    from ..io.sources import open_source
    from ..stream.wire import encode_frame

    src = open_source(spec)
    with Recorder(path) as rec:
        for f in src:
            rec.write(keys.key("cam0", "frame"), encode_frame(f, "cam0", depth="zstd", depth_scale=src.depth_scale),
                      log_time_ns=f.timestamp_ns)
    return f"mcap:{path}"


def run_pipeline(out: Path, fps: float | None, seconds: float, width: int = 640, height: int = 480,
                 record: bool = True, warmup_s: float = 5.0, replay: bool = False, streams: int = 1,
                 progress: Callable[[str], None] | None = None, profile: bool = False,
                 latency: str | None = None) -> dict:
    """One measured run; ``fps`` None = capture as fast as possible; ``replay``: the capture sends a
    pre-encoded recording instead of rendering synthetic frames live; ``streams``: that many cameras
    side by side (``cam0``, ``cam1``, ...; each its own capture, flow, motion and render, synthetic
    seeds 1, 2, ...; one recorder of all). ``progress`` is told once a second how far it is.
    ``profile``: each process's CPU by thread, and each service's main thread under cProfile
    (:mod:`.pipeline_profile`; ``out/profile``). ``latency``: the motion service's ``--latency`` preset
    (None: its default). Returns the report dict."""
    from ..stream.launcher import free_port, open_when_up

    out.mkdir(parents=True, exist_ok=True)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    z = ["-e", endpoint, "--no-multicast-scouting"]
    frames = int((fps or 120) * (seconds + warmup_s)) + 1
    cams = [f"cam{i}" for i in range(streams)]
    specs = [router_spec(["-m", "quick_stream", "router", "-l", endpoint, "--no-multicast-scouting"])]
    recording = fresh_path(out / "recording.mcap")  # measured below: this run's, not a kept earlier one
    for i, cam in enumerate(cams):
        # a camera at the rate offered (its frames' capture times follow it), 30 fps for 'fast'
        src = f"synthetic:frames={frames},width={width},height={height},seed={i + 1},fps={fps or 30:g}"
        if replay:
            src = prerecord(out / f"source-{cam}.mcap", src)
        cap = ["--source", src, *(["--pace", "fast"] if fps is None else ["--pace", "realtime", "--fps", str(fps)])]
        own = {"recorder": ["--output", str(recording)] + (["--all-streams"] if streams > 1 else []),
               "render": ["--output", str(out / f"stabilized-{cam}.avi")], "capture": cap,
               "motion": ["--latency", latency] if latency else []}
        # one recorder, of cam0 (its liveliness token is under its own stream even when it records all):
        # cam0's capture waits for it too
        run = [s for s in topology.SERVICES if s != topology.RECORDER or (record and cam == "cam0")]
        specs += stream_specs(lambda _s, cam=cam: [*z, "--stream", cam], own, run=run,
                              name=lambda s, cam=cam: s if s == topology.RECORDER else _name(s, cam, streams))
    prof_dir = out / "profile"
    if profile:
        prof_dir.mkdir(exist_ok=True)
        for old in prof_dir.glob("*.prof"):
            old.unlink()
    sup = Supervisor(specs, out / "logs", env={PROFILE_ENV: str(prof_dir)} if profile else None)
    threads: dict[str, dict[str, float]] = {}
    sup.start("router")
    session = open_when_up(endpoint, 20)
    mons = {cam: Monitor() for cam in cams}
    subs = [session.declare_subscriber(keys.key(cam, "stabilized"), mons[cam].on_sample) for cam in cams]
    board = StatusBoard(session)
    samples: dict[str, list[tuple[float, float, int, int]]] = {}
    queues: dict[str, list[float]] = {}  # "<stream>.<service>.<queue>" -> its length, once a second
    try:
        for s in specs[1:]:
            sup.start(s.name)
        t_start = None
        deadline = time.monotonic() + seconds + warmup_s + 120
        while time.monotonic() < deadline:
            time.sleep(1.0)
            sup.poll()
            now = time.monotonic()
            if t_start is None and any(m.seqs for m in mons.values()):
                t_start = now
            for name in sup.children:
                pid = sup.pid(name)
                got = proc_sample(pid) if pid else None
                if got:
                    samples.setdefault(name, []).append((now, *got))
                    if profile:
                        threads[name] = thread_cpu(pid) or threads.get(name, {})
            if t_start is not None and now - t_start > warmup_s:
                for (st, svc), vals in board.snapshot().items():
                    for k, v in vals.items():
                        if k in QUEUES or k.endswith("_queued"):
                            queues.setdefault(f"{st}.{svc}.{k}", []).append(float(v))
            if progress:
                phase = ("starting" if t_start is None else "warming up" if now - t_start <= warmup_s
                         else f"measuring {min(now - t_start - warmup_s, seconds):.0f}/{seconds:g} s")
                progress(f"{fps or 'fast'} fps: {phase}, stabilized "
                         + ", ".join(f"{cam} {len(m.seqs)}" for cam, m in mons.items()))
            if all(m.ended for m in mons.values()) or (t_start and now - t_start > seconds + warmup_s + 30):
                break
        stats = board.snapshot()
    finally:
        for sub in subs:
            sub.undeclare()
        board.close()
        session.close()
        sup.stop([s.name for s in specs if s.name.startswith("capture")]
                 + [s.name for s in specs[1:] if not s.name.startswith("capture")] + ["router"])
    procs = _processes(samples)
    # max over each half of the measured window: a queue that grows shows a larger second half
    qs = {k: {"max_first_half": max(v[:max(1, len(v) // 2)]), "max_second_half": max(v[len(v) // 2:]),
              "mean": round(sum(v) / len(v), 1)} for k, v in sorted(queues.items())}
    per = {cam: _report(fps, seconds, warmup_s, width, height, mons[cam], stats, record, cam) for cam in cams}
    if record:  # the recorder has stopped: its file is whole
        for cam in cams:
            seqs = mons[cam].seqs
            skip = _warmup_frames(fps, warmup_s, len(seqs))
            try:
                per[cam]["release_steps_ms"] = release_steps(recording, cam,
                                                             seqs[skip] if skip < len(seqs) else 0)
            except (RecordingError, WireError) as e:
                per[cam]["release_steps_ms"] = {"error": str(e)}
    capture = "replay of a pre-encoded recording" if replay else "synthetic, rendered live"
    rate = sum(x["stabilized_fps"] for x in per.values())
    common = {"processes": procs, "queues": qs, "capture": capture, "latency_preset": latency or DEFAULT_PRESET,
              "cpu_per_frame": cpu_per_frame(procs, rate, len(os.sched_getaffinity(0)))}
    if profile:
        common["profile"] = {"threads": {k: thread_shares(v) for k, v in threads.items()},
                             "functions": summarise(prof_dir, sum(len(m.seqs) for m in mons.values()))}
    if streams == 1:
        return {**per["cam0"], **common}
    return {"streams": per, **common, "size": f"{width}x{height}", "fps_target": fps or "fast",
            "seconds": seconds, "recording": record}


def cpu_per_frame(procs: dict, rate: float, cores: int) -> dict:
    """Each process's CPU ms per stabilized frame at ``rate`` frames/s (all streams together), their
    sum (``total_ms``) and the CPU ms ``cores`` cores give per frame at that rate (``budget_ms``);
    empty when nothing was stabilized."""
    if not rate > 0:
        return {}
    ms = {name: round(p["cpu_pct"] * 10.0 / rate, 2) for name, p in procs.items()}  # (pct / 100) s/s * 1000 / rate
    return {"ms": ms, "total_ms": round(sum(ms.values()), 2), "cores": cores, "budget_ms": round(cores * 1000.0 / rate, 2),
            "rate_fps": round(rate, 2)}


QUEUES = ("buffered", "pending_releases")  # besides every inbox's "inbox<i>_queued": render's held frames


def _name(service: str, cam: str, streams: int) -> str:
    return service if streams == 1 else f"{service}-{cam}"


def _processes(samples: dict[str, list[tuple[float, float, int, int]]], warm_s: float = 60.0) -> dict:
    """Per process: mean CPU %, RSS once warm and at the end, its growth, the peak and the series.

    Growth is over the run after start-up: "warm" is the mean RSS over the minute after the first
    ``warm_s`` seconds (caches and buffers filled), "end" the mean over the last minute (runs
    shorter than 3 minutes: the second and the last fifth of the samples)."""
    procs = {}
    for name, rows in samples.items():
        a = np.array(rows, dtype=float)
        if len(a) < 5:
            continue
        t = a[:, 0] - a[0, 0]
        cpu = 100.0 * (a[-1, 1] - a[0, 1]) / max(t[-1], 1e-9)
        if t[-1] >= 3 * warm_s:
            warm, end = (t >= warm_s) & (t < 2 * warm_s), t >= t[-1] - warm_s
        else:
            k = len(a) // 5
            warm, end = np.zeros(len(a), bool), np.zeros(len(a), bool)
            warm[k:2 * k], end[-k:] = True, True
        r_warm, r_end = a[warm, 2].mean() / 2**20, a[end, 2].mean() / 2**20
        every = max(1, len(a) // 10)
        procs[name] = {"cpu_pct": round(cpu, 1), "rss_mb_warm": round(r_warm, 1), "rss_mb_end": round(r_end, 1),
                       "rss_growth_pct": round(100.0 * (r_end / r_warm - 1.0), 1),
                       "peak_rss_mb": round(a[:, 3].max() / 2**20, 1),
                       "rss_mb_series": [round(x / 2**20, 1) for x in a[::every, 2]]}
    return procs


def _warmup_frames(fps: float | None, warmup_s: float, n: int) -> int:
    """How many of the ``n`` stabilized frames the report leaves out as warm-up."""
    return int(round((fps or 0) * warmup_s)) if fps else min(n // 5, 150)


def _report(fps, seconds, warmup_s, width, height, mon: Monitor, stats, record, stream: str = "cam0") -> dict:
    n = len(mon.seqs)
    skip = _warmup_frames(fps, warmup_s, n)
    w_max = max(mon.wait_ms[skip:], default=0.0)
    lat = {"total_ms": _pct(mon.total_ms[skip:]), "segment_wait_ms": _pct(mon.wait_ms[skip:]),
           "beyond_longest_wait_ms": _pct([t - w_max for t in mon.total_ms[skip:]]),
           "processing_ms": _pct(mon.proc_ms[skip:]),
           "processing_first_of_batch_ms": _pct(mon.first_ms[max(1, skip // 30):])}
    cap = stats.get((stream, "capture"), {})
    sent = int(cap.get("sent", 0))
    drops = {f"{svc}.{k}": v for (st, svc), vals in stats.items() for k, v in vals.items()
             if st == stream and (k.endswith("_dropped") or k in ("dropped", "missing", "orphans", "shed")) and v}
    span = (mon.t_last - mon.t_first) if mon.t_first and mon.t_last and n > 1 else 0.0
    windows = []
    if mon.t_recv:
        t0 = mon.t_recv[0]
        tt, tot = np.asarray(mon.t_recv[skip:]) - t0, np.asarray(mon.total_ms[skip:])
        for w0 in np.arange(tt.min() if tt.size else 0, tt.max() if tt.size else 0, 60.0):
            sel = (tt >= w0) & (tt < w0 + 60.0)
            if sel.sum() > 30:
                windows.append({"from_s": round(float(w0), 1), "total_p99_ms": round(float(np.percentile(tot[sel], 99)), 1),
                                "n": int(sel.sum())})
    return {"fps_target": fps or "fast", "latency_p99_per_minute": windows, "seconds": seconds, "size": f"{width}x{height}", "recording": record,
            "frames_sent": sent, "frames_stabilized": n, "frames_flagged": mon.flagged,
            "unique_out_of_order": int(np.sum(np.diff(mon.seqs) <= 0)) if n > 1 else 0,
            "stabilized_fps": round((n - 1) / span, 2) if span else 0.0,
            "send_fps": cap.get("send_fps"), "behind_ms": cap.get("behind_ms"),
            "drops": drops, "latency": lat}


def _files(folder: Path) -> dict[Path, int]:
    """Every file under ``folder`` and its size."""
    out = {}
    for p in folder.rglob("*") if folder.is_dir() else ():
        try:
            if p.is_file():
                out[p] = p.stat().st_size
        except OSError:
            pass
    return out


def scratch_files(folder: Path, before: dict[Path, int]) -> dict[Path, int]:
    """The files a run wrote in ``folder`` (not there, or another size, ``before``), its logs and
    profiles left out: recordings, videos, pre-encoded sources."""
    return {p: n for p, n in _files(folder).items()
            if before.get(p) != n and not {"logs", "profile"} & set(p.relative_to(folder).parts)}


def _size(n: int) -> str:
    return f"{n / 1e9:.2f} GB" if n >= 1e8 else f"{n / 1e6:.1f} MB"


def main(fps_list: list[float | None], seconds: float, out: str, json_path: str | None,
         record: bool = True, replay: bool = False, streams: int = 1, size: str = "640x480",
         progress: Callable[[str], None] | None = None, keep: bool = False, profile: bool = False,
         presets: list[str] | None = None) -> int:
    """Run each rate (with each ``--latency`` preset of ``presets``, None: the default only) and print
    its report; with several presets, then a table of each one's delay as the viewer sees it
    (:func:`format_presets`). ``json_path``: also the reports as JSON there (``-``: on standard
    output, the reports then going to stderr). Each run's recordings and videos are deleted once
    measured (scratch: ~1 GB a 120 s run) unless ``keep``; either way the last line says where they
    were and how much."""
    reports = []
    w, h = (int(x) for x in size.split("x"))
    text = sys.stderr if json_path == "-" else sys.stdout
    for fps in fps_list:
        for preset in presets or [None]:
            folder = Path(out) / (f"fps-{fps or 'fast'}" + (f"-latency-{preset}" if preset else ""))
            before = _files(folder)
            try:
                r = run_pipeline(folder, fps, seconds, width=w, height=h, record=record, replay=replay,
                                 streams=streams, progress=progress, profile=profile, latency=preset)
            finally:
                scratch = scratch_files(folder, before)
                total = sum(scratch.values())
                if not keep:
                    for p in scratch:
                        p.unlink(missing_ok=True)
                what = ", ".join(sorted({p.suffix.lstrip('.') for p in scratch})) or "nothing"
                note = (f"wrote {_size(total)} in {folder} ({what}; kept: delete {folder} when done)" if keep else
                        f"deleted {_size(total)} of scratch files ({what}) from {folder} (--keep keeps them)")
            reports.append(r)
            print(format_report(r), file=text, flush=True)
            print(f"{note}; logs in {folder / 'logs'}" + (f", profiles in {folder / 'profile'}" if profile else ""),
                  file=text, flush=True)
    if presets and len(presets) > 1:
        print(format_presets(reports), file=text, flush=True)
    if json_path == "-":
        print(json.dumps(reports, indent=1), flush=True)
    elif json_path:
        Path(json_path).parent.mkdir(parents=True, exist_ok=True)
        Path(json_path).write_text(json.dumps(reports, indent=1))
    return 0

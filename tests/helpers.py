"""Shared by the multi-process tests: the single-process reference output, and driving `quick-stream up`."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from quick_stream.cli import build_parser
from quick_stream.core.stabilizer import Stabilizer
from quick_stream.io.recording import read_messages
from quick_stream.io.sources import open_source
from quick_stream.stream import topology
from quick_stream.stream.launcher import ServiceSpec, Supervisor, free_port, open_when_up
from quick_stream.stream.stream_specs import stream_specs
from quick_stream.io.stabilizer_flags import stabilizer_params
from quick_stream.stream.wire import WireError, decode

UP = [sys.executable, "-m", "quick_stream", "up", "--quiet"]


def stabilize(frames, params=None) -> tuple[Stabilizer, list]:
    """Every frame through one in-process Stabilizer: (the stabilizer, its stabilized frames)."""
    st = Stabilizer(params)
    out = []
    for f in frames:
        out += st.push(f)
    out += st.finish()
    return st, out


def flows_of(frames: list) -> list:
    """The flows a flow stage makes of ``frames``, the frames it refuses skipped."""
    from quick_stream.core.continuity import FrameRefused
    from quick_stream.core.flow_stage import FlowStage

    st, out = FlowStage(), []
    for f in frames:
        try:
            out += st.push(f)
        except FrameRefused:
            pass
    return out + st.finish()


def offline_images(spec: str, *settings: str) -> dict[int, np.ndarray]:
    """Stabilized images by seq from the in-process stabilizer with ``stabilize``'s settings (the
    defaults, or the ``settings`` flags: what ``up`` passes on) and one OpenCV thread, as the services
    and ``stabilize`` run it."""
    cv2.setNumThreads(1)
    stab = Stabilizer(stabilizer_params(build_parser().parse_args(["stabilize", *settings])))
    out = {}
    for f in open_source(spec):
        for sf in stab.push(f):
            out[sf.seq] = sf.image
    for sf in stab.finish():
        out[sf.seq] = sf.image
    return out


def wait_for_status(status: Path, ready: Callable[[dict], bool], timeout: float = 60) -> dict:
    """Poll ``up``'s status.json until ``ready(status)``; AssertionError after ``timeout``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        time.sleep(0.2)
        try:
            st = json.loads(status.read_text())
        except (OSError, ValueError):
            continue
        if ready(st):
            return st
    raise AssertionError(f"{status}: condition not reached in {timeout:g} s")


def sent(st: dict) -> int:
    return st["services"]["capture"]["stats"].get("sent", 0)


def up_and_kill(out: Path, source: str, victim: str, min_sent: int = 60, timeout: float = 120) -> tuple[int, dict, str]:
    """Run ``up`` on ``source``, SIGKILL ``victim`` once ``min_sent`` frames went out, wait for the end.
    Returns (kill time ns, final status, up's output); ``up`` must exit 0. Paced by the pipeline
    (``--pace fast``), not a 30 fps camera: on a loaded machine the stream slows down instead of
    overrunning the stages, so what is tested is the recovery (live capacity: the benchmarks)."""
    p = subprocess.Popen([*UP, "--pace", "fast", "--out", str(out), "--source", source], stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT, text=True)
    try:
        st = wait_for_status(out / "logs" / "status.json",
                             lambda s: s["services"][victim]["running"] and sent(s) >= min_sent)
        os.kill(st["services"][victim]["pid"], signal.SIGKILL)
        killed_at = time.time_ns()
        text, _ = p.communicate(timeout=timeout)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 0, text
    return killed_at, json.loads((out / "logs" / "status.json").read_text()), text


RENDER = "quick_stream.services.render"


def stage_specs(z: list[str], stream: str | None = None, render: list[str] = (),
                render_module: str = RENDER) -> list[ServiceSpec]:
    """flow, motion and render with the zenoh flags ``z`` (``stream``: of that stream, each named
    ``<stage>-<stream>``); ``render``: the render's own arguments, ``render_module`` its module (a
    test tool such as ``tests.tools.slow_render``)."""
    s, suffix = (["--stream", stream], f"-{stream}") if stream else ([], "")
    return stream_specs(lambda _: [*z, *s], {"render": render}, run=topology.STAGES,
                        modules={"render": render_module}, name=lambda n: f"{n}{suffix}")


def capture_spec(z: list[str], capture: list[str], wait_for: list[str], name: str = "capture") -> ServiceSpec:
    """A capture with the zenoh flags ``z`` and its own arguments ``capture`` that starts sending
    once the services ``wait_for`` are up; it may finish (its source ends)."""
    return ServiceSpec(name, ["-m", "quick_stream.services.capture", *z, *capture, "--wait-for", ",".join(wait_for)],
                       may_finish=True)


def pipeline_specs(tmp: Path, ep: str, render: list[str] = (), record: bool = True, capture: list[str] | None = None,
                   flags: list[str] = (), router: list[str] = (), recorder: list[str] = (), stages: bool = True,
                   render_module: str = RENDER) -> list[ServiceSpec]:
    """Router (listening on ``ep``, with its extra arguments ``router``), recorder (``tmp/rec.mcap``,
    extra arguments ``recorder``), with ``stages`` flow, motion and render (:func:`stage_specs`) and,
    with ``capture`` arguments, a capture waiting for all of them. Every service connects to ``ep``
    with the extra flags ``flags``."""
    z = ["-e", ep, "--no-multicast-scouting", *flags]
    run = [s for s in topology.SERVICES if (s != topology.RECORDER or record)
           and (s not in topology.STAGES or stages) and (s != topology.SOURCE or capture is not None)]
    own = {"recorder": [*recorder, "--output", str(tmp / "rec.mcap")], "render": render, "capture": capture or []}
    return [ServiceSpec("router", ["-m", "quick_stream", "router", "-l", ep, "--no-multicast-scouting", *router]),
            *stream_specs(lambda _: z, own, run=run, modules={"render": render_module})]


def start_pipeline(specs: list[ServiceSpec], tmp: Path, ep: str, max_restarts: int = 0,
                   env: dict[str, str] | None = None) -> Supervisor:
    """A supervisor of ``specs`` (logs in ``tmp/logs``): the router (``specs[0]``) started and
    answering at ``ep``, then every other service."""
    sup = Supervisor(specs, tmp / "logs", max_restarts=max_restarts, env=env)
    start_router(sup, ep)
    for s in specs[1:]:
        sup.start(s.name)
    return sup


def pipeline(tmp: Path, render: list[str] = (), record: bool = True, capture: list[str] | None = None,
             max_restarts: int = 0, render_module: str = RENDER,
             env: dict[str, str] | None = None) -> tuple[Supervisor, str]:
    """Router + recorder (``tmp/rec.mcap``) + flow + motion + render (+ capture with ``capture``
    arguments) on a free loopback port, started (router first); returns (supervisor, endpoint)."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    specs = pipeline_specs(tmp, ep, render, record, capture, render_module=render_module)
    return start_pipeline(specs, tmp, ep, max_restarts, env), ep


def start_router(sup: Supervisor, endpoint: str, timeout: float = 60) -> None:
    """Start the supervisor's ``router`` and wait until it answers a session at ``endpoint``."""
    sup.start("router")
    open_when_up(endpoint, timeout).close()


def wait_for_log(sup: Supervisor, log: Path, text: str, timeout: float = 120) -> None:
    """Poll the supervisor until ``text`` appears in ``log``; AssertionError with the logs' tails after ``timeout``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        time.sleep(0.5)
        sup.poll()
        if log.exists() and text in log.read_text():
            return
    raise AssertionError({p.name: p.read_text()[-800:] for p in log.parent.glob("*.log")})


def recorded(path: Path) -> tuple[dict[str, dict], dict[str, list]]:
    """From a recording: each service's last ``stats`` values, and the decoded messages by type
    (the ``quick/`` wire channels; a message that does not decode is listed under ``undecodable``)."""
    stats: dict[str, dict] = {}
    by_type: dict[str, list] = {}
    for topic, _, data in read_messages(path):
        if not topic.startswith("quick/"):
            continue  # Foxglove channels
        try:
            m = decode(data)
        except WireError:
            by_type.setdefault("undecodable", []).append(data)
            continue
        if m.type == "stats":
            stats[m.obj.service] = m.obj.values
        by_type.setdefault(m.type, []).append(m)
    return stats, by_type

"""Bad input at the command-line and config-file boundary (docs/reliability.md, "Bad input"), table-driven.

Every entry point (the ``quick-stream`` sub-commands, the five services and the test tools) is run with bad
flags, config files, environment variables, source specs and output paths. Each must exit
non-zero (2 for usage and config errors, as argparse does) with a message that names what
was wrong, print no traceback, not hang, and stop before any real work: no zenoh session is
opened and no process is started (both are patched to fail the test if reached).

The rows run in-process through ``main(argv)`` (fast, and the same code path as the
console script); tests/integration/test_cli_processes.py runs a few as real processes to check
the exit code and output as a user sees them, including a listen endpoint already in use,
which only zenoh can find.
"""
from __future__ import annotations

import importlib
import logging
import os
import shlex
import signal
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import pytest

import quick_stream.cli
import quick_stream.services.recorder as recorder_service
from quick_stream.io.recording import Recorder
from quick_stream.io.sources import open_source
from quick_stream.stream import argtypes
from quick_stream.stream.keys import key
from quick_stream.stream.transport import ENV, check_endpoint, config_from_args
from quick_stream.stream.wire import encode_frame
from tests.tools.fuzz_mcap import watchdog

REPO = Path(__file__).resolve().parents[2]
SERVICES = ("capture", "flow", "motion", "render", "recorder")
CASE_TIMEOUT_S = 10.0  # a hang becomes a failure, not a stuck test run


# ---------------------------------------------------------------- the inputs the rows refer to ({d})

CONFIGS = {
    "empty.json5": "\n",
    "invalid.json5": "{ mode: ",
    "mode5.json5": "{ mode: 5 }",
    "modebogus.json5": '{ mode: "bogus" }',
    "connect_str.json5": '{ connect: { endpoints: "tcp/127.0.0.1:7447" } }',
    "nohost.json5": '{ connect: { endpoints: ["tcp/nohost"] } }',
    "listen_port.json5": '{ listen: { endpoints: ["tcp/0.0.0.0:99999"] } }',
    "unknownkey.json5": "{ bogus_key: 1 }",
}


def bad_inputs(root: Path) -> Path:
    """``root`` filled with bad (and a few good) inputs: config files, a non-MCAP file, a recording of
    stream cam0, a regular file where a folder should be, TUM folders without their index."""
    for name, text in CONFIGS.items():
        (root / name).write_text(text)
    (root / "file.txt").write_text("a regular file in the way of a folder\n")
    (root / "bad.mcap").write_text("not an MCAP file\n")
    with Recorder(root / "rec.mcap") as rec:
        for f in open_source("synthetic:frames=3,width=64,height=48"):
            rec.write(key("cam0", "frame"), encode_frame(f, "cam0", color="raw", depth="raw", depth_scale=1000.0),
                      log_time_ns=10**9 + f.timestamp_ns)
    (root / "tum_norgb").mkdir()
    (root / "tum_norgb" / "depth.txt").write_text("# depth\n")
    (root / "tls_empty").mkdir()
    return root


@pytest.fixture(scope="module")
def d(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder of bad inputs (:func:`bad_inputs`)."""
    return bad_inputs(tmp_path_factory.mktemp("bad_input"))


# ---------------------------------------------------------------- the table

@dataclass(frozen=True)
class Case:
    entry: str  # a service name, "qs" for the quick-stream command, or tools.NAME for a test tool
    argv: str  # shell words; {d} is the inputs folder
    names: tuple[str, ...]  # what the message must contain (the flag, file, key or value at fault)
    env: dict[str, str] = field(default_factory=dict)
    code: int = 2

    def __str__(self) -> str:
        env = " ".join(f"{k}={v}" for k, v in self.env.items())
        return f"{env + ' ' if env else ''}{self.entry} {self.argv}"


def c(entry: str, argv: str, *names: str, env: dict[str, str] | None = None) -> Case:
    return Case(entry, argv, names, env or {})


ZENOH = [  # the standard zenoh flags, config files and environment (every service shares them; flow here)
    c("flow", "-c {d}/missing.json5", "--config", "missing.json5", "no such file"),
    c("flow", "-c {d}", "--config", "not a regular file"),
    c("flow", "-c {d}/empty.json5", "empty.json5", "empty"),
    c("flow", "-c {d}/invalid.json5", "invalid.json5", "line 1, column 9"),
    c("flow", "-c {d}/mode5.json5", "mode5.json5", "integer `5`", "line 1, column 9"),
    c("flow", "-c {d}/modebogus.json5", "modebogus.json5", "`bogus`"),
    c("flow", "-c {d}/connect_str.json5", "connect_str.json5", "expected list of endpoints"),
    c("flow", "-c {d}/nohost.json5", "nohost.json5", "connect/endpoints", "'tcp/nohost'", "HOST:PORT"),
    c("flow", "-c {d}/listen_port.json5", "listen_port.json5", "listen/endpoints", "'99999'"),
    c("flow", "-c {d}/unknownkey.json5", "unknownkey.json5", "bogus_key"),
    c("flow", "-m bogus", "--mode", "'bogus'"),
    c("flow", "-e tcp/nohost", "--connect", "'tcp/nohost'", "HOST:PORT"),
    c("flow", "-e nohost", "--connect", "'nohost'", "<protocol>/<address>"),
    c("flow", "-e tcp/127.0.0.1:0", "--connect", "port", "'0'"),
    c("flow", "-e tcp/127.0.0.1:99999", "--connect", "'99999'"),
    c("flow", "-e tcp/::1:7447", "--connect", "IPv6"),
    c("flow", "-l tcp/127.0.0.1:70000", "--listen", "'70000'"),
    c("flow", "--cfg nocolon", "--cfg", "KEY:VALUE", "'nocolon'"),
    c("flow", "--cfg mode:{bad", "--cfg mode:{bad", "line 1, column 1"),
    c("flow", "--cfg mode:5", "--cfg mode:5", "integer `5`"),
    c("flow", "--cfg bogus/key:1", "--cfg bogus/key:1", "unknown key"),
    c("flow", "--cfg connect/endpoints:5", "--cfg connect/endpoints:5"),
    c("flow", "--cfg 'connect/endpoints:[\"tcp/x\"]'", "--cfg connect/endpoints", "'tcp/x'"),
    c("flow", "", "QUICK_STREAM_ZENOH_CONFIG", "missing.json5", "no such file",
      env={"CONFIG": "{d}/missing.json5"}),
    c("flow", "", "QUICK_STREAM_ZENOH_CONFIG", "invalid.json5", env={"CONFIG": "{d}/invalid.json5"}),
    c("flow", "", "QUICK_STREAM_ZENOH_MODE", "'bogus'", env={"MODE": "bogus"}),
    c("flow", "", "QUICK_STREAM_ZENOH_CONNECT", "'tcp/nohost'", env={"CONNECT": "tcp/nohost"}),
    c("flow", "", "QUICK_STREAM_ZENOH_LISTEN", "'udp/1.2.3.4'", env={"LISTEN": "udp/1.2.3.4"}),
    c("flow", "--tls-dir {d}/tls_empty --tls-name flow", "--tls-dir", "ca.pem"),
    c("flow", "--tls-dir {d}/nosuchdir --tls-name flow", "--tls-dir", "nosuchdir", "no such directory"),
    c("flow", "--tls-name flow", "--tls-name without --tls-dir"),
    c("flow", "--tls-dir {d}/tls_empty", "--tls-dir without --tls-name"),
    c("flow", "", "QUICK_STREAM_ZENOH_TLS_NAME without --tls-dir", env={"TLS_NAME": "flow"}),
]

STREAMS = [c(s, "--stream ''", "--stream", "stream id", "''") for s in SERVICES] + [
    c("flow", f"--stream '{bad}'", "--stream", "stream id", bad) for bad in ("a/b", "cam*", "cam$", "a b", "x" * 65)
] + [
    c("qs", "up --stream a/b", "--stream", "'a/b'"),
    c("qs", "rerun flow {d}/rec.mcap --stream 'cam*'", "--stream", "'cam*'"),
]

SETTINGS = [  # the stabilizer settings every stage and the offline commands share
    c("flow", "--keyframe-interval 0", "--keyframe-interval", "0"),
    c("motion", "--keyframe-interval 1", "--keyframe-interval", "1"),
    c("flow", "--keyframe-interval abc", "--keyframe-interval", "'abc'"),
    c("flow", "--lowpass-sigma -1", "--lowpass-sigma", "-1"),
    c("render", "--lowpass-sigma nan", "--lowpass-sigma", "nan"),
    c("flow", "--lowpass-sigma inf", "--lowpass-sigma", "inf"),
    c("flow", "--crop-zoom 0.5", "--crop-zoom", "0.5"),
    c("flow", "--crop-zoom nan", "--crop-zoom", "nan"),
    c("flow", "--path-weights 1,2", "--path-weights", "6 positive numbers"),
    c("flow", "--path-weights 1,1,1,1,1,-1", "--path-weights", "-1.0"),
    c("flow", "--path-weights 1,1,1,1,1,nan", "--path-weights", "nan"),
    c("flow", "--path-weights a,b", "--path-weights", "'a,b'"),
    c("flow", "--path-weights ''", "--path-weights", "''"),
    c("flow", "--group so3", "--group", "'so3'"),
    c("flow", "--estimator bogus", "--estimator", "'bogus'"),
    c("flow", "--end bogus", "--end", "'bogus'"),
    c("flow", "--framing bogus", "--framing", "'bogus'"),
    c("qs", "stabilize --crop-zoom nan", "--crop-zoom", "nan"),
    c("qs", "up --path-weights 1,2", "--path-weights", "6 positive numbers"),
    c("qs", "up --lowpass-sigma nan", "--lowpass-sigma", "nan"),
    c("qs", "rerun motion {d}/rec.mcap --lowpass-sigma -1", "--lowpass-sigma", "-1"),
]

CAPTURE = [
    *(c("capture", f"--fps {v}", "--fps", f"'{v}'") for v in ("0", "-30", "nan", "inf", "abc")),
    *(c("capture", f"--speed {v}", "--speed", f"'{v}'") for v in ("0", "-1", "nan")),
    c("capture", "--window -1", "--window", "'-1'"),
    *(c("capture", f"--quality {v}", "--quality", f"'{v}'") for v in ("0", "101", "-1", "abc")),
    *(c("capture", f"--frames {v}", "--frames", f"'{v}'") for v in ("0", "-1")),
    *(c("capture", f"--wait-timeout {v}", "--wait-timeout", f"'{v}'") for v in ("-1", "nan")),
    c("capture", "--wait-for flow,a/b", "--wait-for", "'a/b'"),
    c("capture", "--pace bogus", "--pace", "'bogus'"),
    c("capture", "--color png", "--color", "'png'"),
    c("capture", "--depth bogus", "--depth", "'bogus'"),
]

SOURCES = [  # source specs, through the capture service (open_source; quick-stream commands share it)
    c("capture", "--source bogus:x", "unknown source kind 'bogus'"),
    c("capture", "--source synthetic:bogus=1", "unknown option 'bogus'"),
    c("capture", "--source synthetic:width=-5", "width", "-5"),
    c("capture", "--source synthetic:width=abc", "width", "'abc'"),
    c("capture", "--source synthetic:width=100000,height=100000", "width", "8192"),
    c("capture", "--source synthetic:frames=0", "frames", "0"),
    c("capture", "--source synthetic:fps=nan", "fps", "nan"),
    c("capture", "--source synthetic:shake=-1", "shake", "-1"),
    c("capture", "--source tum:{d}/nosuchfolder", "nosuchfolder", "not found"),
    c("capture", "--source tum:{d}/tum_norgb", "tum_norgb", "rgb.txt"),
    c("capture", "--source tum:{d}/bad.mcap", "bad.mcap", "is a file", "mcap:FILE"),
    c("capture", "--source tum:", "tum:PATH"),
    c("capture", "--source tum:{d}/tum_norgb,max_dt=abc", "max_dt", "'abc'"),
    c("capture", "--source tum:{d}/tum_norgb,bogus=1", "unknown option 'bogus'"),
    c("capture", "--source mcap:{d}/missing.mcap", "missing.mcap", "not found"),
    c("capture", "--source mcap:{d}/bad.mcap", "bad.mcap", "not a valid MCAP file"),
    c("capture", "--source mcap:{d}/rec.mcap,stream=cam9", "rec.mcap", "'cam9'", "cam0"),
    c("capture", "--source mcap:{d}/rec.mcap,bogus=1", "unknown option 'bogus'"),
    c("capture", "--source mcap:", "mcap:FILE"),
    c("capture", "--source depthai:dev,width=abc", "width='abc'"),
    c("capture", "--source depthai:dev,fps=0", "fps='0'"),
    c("capture", "--source depthai:dev,retries=-1", "retries='-1'"),
    c("capture", "--source depthai:dev,bogus=1", "unknown option(s) bogus"),
    c("capture", "--source depthai:fake0,fake=1,height=nan", "height='nan'"),
]

RENDER_RECORDER_QUEUES = [
    *(c("render", f"--fps {v}", "--fps", f"'{v}'") for v in ("0", "nan")),
    *(c("render", f"--quality {v}", "--quality", f"'{v}'") for v in ("0", "101")),
    *(c("render", f"--max-frames {v}", "--max-frames", f"'{v}'") for v in ("0", "-1")),
    *(c("render", f"--max-held-mb {v}", "--max-held-mb", f"'{v}'") for v in ("0", "nan")),
    *(c("render", f"--frame-wait {v}", "--frame-wait", f"'{v}'") for v in ("-1", "nan")),
    *(c("tools.slow_render", f"--slow-ms {v}", "--slow-ms", f"'{v}'") for v in ("-1", "nan", "inf")),
    c("tools.slow_render", "--slow-ms 5 --max-frames 0", "--max-frames", "'0'"),  # the render service's own flags
    c("render", "--output {d}/file.txt/out.mp4", "--output", "file.txt", "not a directory"),
    c("render", "--output {d}/out.txt", "--output", "out.txt", ".mp4"),
    c("render", "--output {d}/out.m4v", "--output", "out.m4v", "cannot hold Motion JPEG", "--video-codec mp4v"),
    c("render", "--video-codec h264", "--video-codec", "'h264'"),
    c("render", "--png {d}/file.txt", "--png", "file.txt", "not a directory"),
    c("render", "--png {d}/file.txt/png", "--png", "file.txt", "not a directory"),
    *(c("recorder", f"--flush {v}", "--flush", f"'{v}'") for v in ("0", "-1", "nan")),
    c("recorder", "--queue 0", "--queue", "'0'"),
    *(c("recorder", f"--nice {v}", "--nice", f"'{v}'") for v in ("-5", "20", "abc")),
    c("recorder", "--output {d}/file.txt/rec.mcap", "--output", "file.txt", "not a directory"),
    c("recorder", "--output {d}", "--output", "is a directory"),
    c("recorder", "--compression bogus", "--compression", "'bogus'"),
    *(c("flow", f"--queue {v}", "--queue", f"'{v}'") for v in ("0", "-5", "abc")),
    *(c("motion", f"--queue {v}", "--queue", f"'{v}'") for v in ("0", "-1")),
]

SMALL = "--source synthetic:frames=3,width=64,height=48"
COMMANDS = [
    c("qs", "bogus", "'bogus'"),
    *(c("qs", f"stabilize {SMALL} --frames {v}", "--frames", f"'{v}'") for v in ("0", "-1")),
    c("qs", f"stabilize {SMALL} --threads 0", "--threads", "'0'"),
    c("qs", f"stabilize {SMALL} --output {{d}}/file.txt/o.mp4", "--output", "file.txt"),
    c("qs", f"stabilize {SMALL} --output {{d}}/o.txt", "--output", "o.txt"),
    c("qs", f"stabilize {SMALL} --output {{d}}/o.m4v --video-codec mjpeg", "--output", "o.m4v", "Motion JPEG"),
    c("qs", f"stabilize {SMALL} --report {{d}}/file.txt/r.json", "--report", "file.txt"),
    c("qs", f"stabilize {SMALL} --plot {{d}}/file.txt/p.png", "--plot", "file.txt"),
    c("qs", f"stabilize {SMALL} --plot {{d}}/p.xyz", "--plot", "'.xyz'"),
    c("qs", f"stabilize {SMALL} --png {{d}}/file.txt", "--png", "file.txt"),
    c("qs", "stabilize --source synthetic:width=abc", "width", "'abc'"),
    c("qs", "stabilize --source mcap:{d}/bad.mcap", "bad.mcap", "not a valid MCAP file"),
    c("qs", "stabilize --source mcap:{d}/rec.mcap,stream=cam9", "'cam9'"),
    c("qs", "stabilize --source tum:{d}/nosuchfolder", "nosuchfolder"),
    c("qs", "stabilize --source tum:{d}/file.txt", "file.txt", "is a file"),
    c("qs", f"motion {SMALL} --frames -1", "--frames", "'-1'"),
    *(c("qs", f"motion {SMALL} --flow-scale {v}", "--flow-scale", f"'{v}'") for v in ("0", "nan", "2")),
    c("qs", f"motion {SMALL} --max-points 0", "--max-points", "'0'"),
    c("qs", f"motion {SMALL} --threads 0", "--threads", "'0'"),
    c("qs", f"motion {SMALL} --preset bogus", "--preset", "'bogus'"),
    c("qs", f"motion {SMALL} --trajectory {{d}}/file.txt/t.txt", "--trajectory", "file.txt"),
    c("qs", "motion --source synthetic:frames=0", "frames", "0"),
    c("qs", "evaluate {d}/nosuchfolder", "nosuchfolder"),
    c("qs", "evaluate {d}/tum_norgb", "tum_norgb", "rgb.txt"),
    c("qs", "evaluate {d}/tum_norgb -k 0", "--subsequences", "'0'"),
    c("qs", "evaluate {d}/tum_norgb -l 2", "--length", "'2'"),
    c("qs", "evaluate {d}/tum_norgb --groups so3", "--groups", "'so3'"),
    c("qs", "evaluate {d}/tum_norgb --seed -1", "--seed", "'-1'"),
    c("qs", "evaluate {d}/tum_norgb --json {d}/file.txt/r.json", "--json", "file.txt"),
    *(c("tools.fuzz", f"--n {v}", "--n", f"'{v}'") for v in ("0", "-1")),
    c("tools.fuzz", "--target mcap --engine hypothesis", "--target mcap", "--engine"),
    c("tools.faults", "--size 640", "--size", "'640'"),
    c("tools.slow_viewer", "--frames 0", "--frames", "'0'"),
    c("tools.slow_viewer", "--out {d}/file.txt", "--out", "file.txt"),
    c("qs", "bench speed --pairs 0", "--pairs", "'0'"),
    c("qs", "bench speed --width -5", "--width", "'-5'"),
    c("qs", "bench speed --group bogus", "--group", "'bogus'"),
    *(c("qs", f"bench pipeline --fps {v}", "--fps", f"'{v}'") for v in ("0", "abc", "nan")),
    c("qs", "bench pipeline --fps 30,-1", "--fps", "'-1'"),
    c("qs", "bench pipeline --seconds -1", "--seconds", "'-1'"),
    c("qs", "bench pipeline --render-slow-ms 5", "--render-slow-ms"),  # a test tool's now (tests.tools.slow_render)
    *(c("qs", f"bench pipeline --size {v}", "--size", f"'{v}'") for v in ("640", "0x480", "640x480x3")),
    c("qs", "bench pipeline --streams 0", "--streams", "'0'"),
    c("qs", "bench pipeline --out {d}/file.txt", "--out", "file.txt"),
    c("qs", "bench odometry --groups bogus", "--groups", "'bogus'"),
    c("qs", "bench odometry --frames 0", "--frames", "'0'"),
    c("qs", "bench odometry --source bogus:x", "bench odometry", "'bogus'"),
    c("qs", "bench quality --data {d}/nosuchfolder --no-baselines", "bench quality", "nosuchfolder"),
    c("qs", "bench moving-objects --data {d}/nosuchfolder", "bench moving-objects", "nosuchfolder"),
    c("qs", "recover {d}/missing.mcap", "missing.mcap", "cannot open"),
    c("qs", "recover {d}/rec.mcap {d}/rec.mcap", "rec.mcap", "exists"),
    c("qs", "recover {d}/rec.mcap {d}/rec.mcap --force", "rec.mcap", "different output file"),
    c("qs", "recover {d}/bad.mcap {d}/bad-recovered.mcap", "bad.mcap", "not a valid MCAP file"),
    c("qs", "recover {d}/rec.mcap {d}/file.txt/x.mcap", "DST", "file.txt", "not a directory"),
    c("qs", "recover {d}", "Is a directory"),
    c("qs", "rerun capture {d}/rec.mcap", "stage", "'capture'"),
    c("qs", "rerun flow {d}/bad.mcap", "bad.mcap", "not a valid MCAP file"),
    c("qs", "rerun flow {d}/missing.mcap", "missing.mcap", "no such file"),
    c("qs", "rerun flow {d}", "not a regular file"),
    c("qs", "rerun flow {d}/rec.mcap --stream cam9", "cam9"),
    c("qs", "router -c {d}/missing.json5", "--config", "missing.json5"),
    c("qs", "router -c {d}/invalid.json5", "--config", "invalid.json5", "line 1"),
    c("qs", "router -l tcp/nohost", "--listen", "'tcp/nohost'"),
    c("qs", "router -l tcp/127.0.0.1:99999", "--listen", "'99999'"),
    c("qs", "router --cfg nocolon", "--cfg", "'nocolon'"),
    c("qs", "router --tls-name router", "--tls-name without --tls-dir"),
    c("qs", "up --source bogus:x", "--source", "'bogus'"),
    c("qs", "up --source synthetic:width=abc", "--source", "width", "'abc'"),
    c("qs", "up --source depthai:dev,width=-5", "--source", "width='-5'"),
    c("qs", "up --source mcap:{d}/bad.mcap", "--source", "bad.mcap"),
    c("qs", "up --source tum:{d}/tum_norgb", "--source", "rgb.txt"),
    c("qs", "up --fps 0", "--fps", "'0'"),
    *(c("qs", f"up --duration {v}", "--duration", f"'{v}'") for v in ("-1", "nan")),
    c("qs", "up --frames 0", "--frames", "'0'"),
    *(c("qs", f"up --port {v}", "--port", f"'{v}'") for v in ("70000", "-1")),
    c("qs", "up --out {d}/file.txt", "--out", "file.txt", "not a directory"),
    c("qs", "up --png {d}/file.txt/png", "--png", "file.txt"),
    c("qs", "up --pace bogus", "--pace", "'bogus'"),
    c("qs", "up --tls-dir {d}/nosuchfolder", "--tls-dir", "nosuchfolder", "make-certs.sh"),
    c("qs", "up --router-config {d}/rec.mcap", "--router-config goes with --tls-dir"),
    *(c("qs", f"acl --streams {v}", "--streams", f"'{v}'") for v in ("a/b", "cam0,cam0")),
    c("qs", "acl --streams ''", "--streams", "got ''"),
    # outputs are never overwritten silently; --json takes FILE or -; evaluate reads tum:PATH; a router is a router
    c("qs", "recover {d}/rec.mcap {d}/file.txt", "DST", "file.txt", "exists", "--force"),
    c("qs", "acl --output {d}/file.txt", "--output", "file.txt", "exists", "--force"),
    c("qs", f"stabilize {SMALL} --report {{d}}/file.txt", "--report", "file.txt", "exists", "--force"),
    c("qs", f"motion {SMALL} --json", "--json", "expected one argument"),
    c("qs", f"motion {SMALL} --json ''", "--json", "- for standard output"),
    c("qs", "evaluate mcap:{d}/rec.mcap", "CLIP", "tum:PATH"),
    c("qs", "evaluate tum:{d}/tum_norgb,count=3", "CLIP", "without options"),
    c("qs", "router -m peer", "--mode", "'peer'"),
    c("qs", "bench path --seed -1", "--seed", "'-1'"),
]

CASES = ZENOH + STREAMS + SETTINGS + CAPTURE + SOURCES + RENDER_RECORDER_QUEUES + COMMANDS


# ---------------------------------------------------------------- running a row in-process

class Reached(BaseException):
    """A bad input got past validation to real work (a BaseException: no ``except Exception`` hides it)."""


def _reached(what: str) -> Callable[..., None]:
    def fail(*_a: object, **_k: object) -> None:
        raise Reached(f"bad input reached {what}")

    return fail


@pytest.fixture
def no_work(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Iterator[None]:
    """Opening a zenoh session, starting a process or a benchmark fails the test; no
    QUICK_STREAM_ZENOH_* variable leaks in from outside; relative defaults land in tmp_path;
    signal handlers a command installs before failing do not outlive the row."""
    import zenoh

    from quick_stream.bench import pipeline
    from quick_stream.stream import launcher, runtime

    monkeypatch.setattr(runtime.ServiceRuntime, "__init__", _reached("a service session (ServiceRuntime)"))
    monkeypatch.setattr(recorder_service, "lower_priority", lambda _niceness: None)  # not this test process
    monkeypatch.setattr(zenoh, "open", _reached("zenoh.open"))
    monkeypatch.setattr(launcher.Supervisor, "start", _reached("starting a process (Supervisor.start)"))
    monkeypatch.setattr(pipeline, "main", _reached("the pipeline benchmark"))
    for name in list(os.environ):
        if name.startswith(ENV):
            monkeypatch.delenv(name)
    monkeypatch.chdir(tmp_path)
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    yield
    for s, h in handlers.items():
        signal.signal(s, h)


def entry_main(entry: str) -> Callable[[list[str]], int]:
    """``qs``: the quick-stream command; ``tools.NAME``: a test tool (tests/tools); else a service."""
    if entry == "qs":
        return quick_stream.cli.main
    module = f"tests.{entry}" if entry.startswith("tools.") else f"quick_stream.services.{entry}"
    return importlib.import_module(module).main


def run_in_process(entry: str, argv: list[str]) -> int:
    """The exit code of ``main(argv)``, whether returned or raised (argparse raises SystemExit)."""
    try:
        with watchdog(CASE_TIMEOUT_S):  # a hang fails the case
            return entry_main(entry)(argv)
    except SystemExit as e:
        return e.code if isinstance(e.code, int) else 1


def fill(text: str, d: Path) -> str:
    return text.replace("{d}", str(d))


@pytest.mark.parametrize("case", CASES, ids=str)
def test_bad_input_is_refused_by_name(case: Case, d: Path, no_work: None, monkeypatch: pytest.MonkeyPatch,
                                      capsys: pytest.CaptureFixture, caplog: pytest.LogCaptureFixture) -> None:
    for name, value in case.env.items():
        monkeypatch.setenv(ENV + name, fill(value, d))
    code = run_in_process(case.entry, shlex.split(fill(case.argv, d)))
    captured = capsys.readouterr()
    text = captured.out + captured.err + caplog.text
    assert code == case.code, f"exit {code}, expected {case.code}; output:\n{text}"
    assert "Traceback" not in text, text
    for name in case.names:
        assert fill(name, d) in text, f"{name!r} not named in:\n{text}"


# ---------------------------------------------------------------- good values still pass

GOOD = [  # boundary values that make sense: the validators must not refuse them
    ("capture", "--window 0 --wait-timeout 0 --quality 1 --fps 0.5 --speed 4 --frames 1 --wait-for ''"),
    ("capture", "--quality 100 --wait-for flow,motion,render,recorder --stream cam_0-B"),
    ("capture", "--source mcap:{d}/rec.mcap,stream=cam0"),
    ("render", "--frame-wait 0 --max-frames 1 --output {d}/new/out.mp4 --png {d}/new/png"),
    ("tools.slow_render", "--slow-ms 0 --frame-wait 0 --max-frames 1"),
    ("render", "--output '' --png '' --lowpass-sigma 0 --crop-zoom 1 --keyframe-interval 2"),
    ("recorder", "--nice 0 --flush 0.01 --queue 1 --output {d}/new/rec.mcap"),
    ("recorder", "--nice 19 --output {d}/rec.mcap"),
    ("flow", "--queue 1 --path-weights 1,1,1,50,50,50 -e tcp/127.0.0.1:7447 -l tcp/0.0.0.0:0"),
    ("flow", "-e tcp/[::1]:7447 -e tcp/localhost:7447#iface=lo -l unixsock-stream//tmp/qs-test.sock"),
    ("motion", "--queue 1 -m client -e tls/quick-router:7447 --cfg transport/shared_memory/enabled:false"),
]


@pytest.mark.parametrize("entry, argv", GOOD, ids=[f"{e} {a}" for e, a in GOOD])
def test_sensible_values_reach_the_session(entry: str, argv: str, d: Path, no_work: None,
                                           caplog: pytest.LogCaptureFixture) -> None:
    """Everything checked, the service goes on to open its session (here: the patched one)."""
    with pytest.raises(Reached, match="session"):
        run_in_process(entry, shlex.split(fill(argv, d)))
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR], caplog.text


@pytest.mark.parametrize("path", sorted((REPO / "deploy" / "zenoh").glob("*.json5")), ids=lambda p: p.name)
def test_deployment_configs_pass_the_checks(path: Path) -> None:
    import argparse

    from quick_stream.stream.transport import add_zenoh_args

    p = argparse.ArgumentParser()
    add_zenoh_args(p)
    config_from_args(p.parse_args(["-c", str(path)]), {})


def test_endpoint_check() -> None:
    for good in ("tcp/127.0.0.1:7447", "tcp/[::1]:7447", "udp/host:1", "tls/quick-router:7447?x=1#y=2",
                 "unixsock-stream//tmp/s.sock", "serial//dev/ttyUSB0"):
        assert check_endpoint(good) == good
    assert check_endpoint("tcp/0.0.0.0:0", listen=True)
    for bad in ("tcp/nohost", "tcp/:7447", "tcp/h:", "tcp/h:x", "tcp/h:65536", "tcp/h:0", "nohost", "/x", "tcp/",
                "tcp/::1:7447"):
        with pytest.raises(ValueError, match="endpoint"):
            check_endpoint(bad)


def test_output_check_names_the_flag(tmp_path: Path) -> None:
    (tmp_path / "f").write_text("x")
    argtypes.check_output(argtypes.OutputPath(str(tmp_path / "a" / "b" / "c.mp4"), "--output"))  # folders to create
    cases = {("--output", False, "f/x.mp4"): "f is a file", ("--png", True, "f"): "not a directory",
             ("--output", False, "."): "is a directory", ("--out", True, "f/g/h"): "f is a file"}
    for (flag, is_dir, rel), words in cases.items():
        with pytest.raises(ValueError) as e:
            argtypes.check_output(argtypes.OutputPath(str(tmp_path / rel), flag, directory=is_dir))
        assert str(e.value).startswith(f"{flag} ") and words in str(e.value)

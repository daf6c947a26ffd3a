"""Bad input as a user meets it: the services and `quick-stream` as real processes (exit 2, named, no
traceback), and a listen endpoint already in use, which only zenoh can find.
"""
from __future__ import annotations

import os
import shlex
import socket
import subprocess
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

import pytest

from quick_stream.stream.transport import ENV
from tests.unit.test_cli_bad_input import REPO, bad_inputs


@pytest.fixture(scope="module")
def d(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder of bad inputs (:func:`tests.unit.test_cli_bad_input.bad_inputs`)."""
    return bad_inputs(tmp_path_factory.mktemp("bad_input"))


@contextmanager
def processes() -> Iterator[Callable[..., subprocess.Popen]]:
    """``launch(args, env)`` runs ``python -m args``; whatever is still running at the end is killed,
    whether the test passed or not (a bad input that was accepted would keep running)."""
    started: list[subprocess.Popen] = []
    clean = {k: v for k, v in os.environ.items() if not k.startswith(ENV)}

    def launch(args: list[str], env: dict[str, str] | None = None) -> subprocess.Popen:
        started.append(subprocess.Popen([sys.executable, "-m", *args], cwd=REPO, env={**clean, **(env or {})},
                                        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True))
        return started[-1]

    try:
        yield launch
    finally:
        for p in started:
            if p.poll() is None:
                p.kill()
            p.communicate()


def finish(p: subprocess.Popen, timeout: float = 30.0) -> tuple[int, str]:
    """Exit code and output of ``p``; a process still running after ``timeout`` fails the test."""
    try:
        out, _ = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        pytest.fail(f"{shlex.join(p.args)} still running after {timeout:g} s")
    return p.returncode, out


def test_processes_refuse_bad_input_quickly(d: Path, tmp_path: Path) -> None:
    """One row per entry point as the user runs it, all at once: exit 2, named, no traceback."""
    rows = [
        (["quick_stream.services.flow", "--queue", "0"], {}, ["--queue", "'0'"]),
        (["quick_stream.services.capture", "--source", "synthetic:width=abc"], {}, ["width", "'abc'"]),
        (["quick_stream.services.render", "--output", f"{d}/file.txt/out.mp4"], {}, ["--output", "file.txt"]),
        (["quick_stream.services.recorder", "-c", f"{d}/invalid.json5", "--output", f"{tmp_path}/r.mcap"], {},
         ["invalid.json5"]),
        (["quick_stream.services.motion", "--stream", "a/b"], {}, ["--stream", "'a/b'"]),
        (["quick_stream.services.flow"], {ENV + "MODE": "bogus"}, [ENV + "MODE", "'bogus'"]),
        (["quick_stream.services.flow", "-e", "tcp/nohost"], {}, ["--connect", "'tcp/nohost'"]),
        (["quick_stream", "stabilize", "--frames", "0"], {}, ["--frames", "'0'"]),
        (["quick_stream", "up", "--source", "bogus:x", "--out", str(tmp_path / "up")], {}, ["--source", "'bogus'"]),
        (["quick_stream", "router", "-l", "tcp/nohost"], {}, ["--listen", "'tcp/nohost'"]),
    ]
    refused_as_processes(rows)
    assert not (tmp_path / "up").exists(), "up started something before refusing its source"


def test_command_line_conventions_as_processes(d: Path) -> None:
    """Router mode, evaluate's clip, an output that exists or cannot be created: exit 2, named, no traceback."""
    rows = [
        (["quick_stream", "router", "-m", "peer"], {}, ["--mode", "'peer'"]),
        (["quick_stream", "evaluate", f"mcap:{d}/rec.mcap"], {}, ["tum:PATH"]),
        (["quick_stream", "recover", f"{d}/rec.mcap", f"{d}/file.txt"], {}, ["DST", "file.txt", "exists", "--force"]),
    ]
    if Path("/proc/self").exists():  # where no file can be created, whatever the permission bits say
        rows += [(["quick_stream", "up", "--out", "/proc/foo"], {}, ["--out /proc/foo", "cannot create"]),
                 (["quick_stream", "stabilize", "--output", "/proc/x.mp4"], {}, ["--output /proc/x.mp4",
                                                                                 "cannot create"])]
    refused_as_processes(rows)


def refused_as_processes(rows: list[tuple[list[str], dict[str, str], list[str]]]) -> None:
    with processes() as launch:
        procs = [(launch(args, env), names) for args, env, names in rows]
        for p, names in procs:
            code, out = finish(p)
            assert code == 2 and "Traceback" not in out, f"{shlex.join(p.args)}: exit {code}\n{out}"
            for name in names:
                assert name in out, f"{shlex.join(p.args)}: {name!r} not named in:\n{out}"


def test_listen_endpoint_in_use_is_named_not_a_traceback() -> None:
    """Only zenoh can find this one (when it binds): the service and the router say so and exit 2."""
    with socket.socket() as s, processes() as launch:
        s.bind(("127.0.0.1", 0))
        s.listen()
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
        procs = [launch(["quick_stream.services.flow", "-l", endpoint, "--no-multicast-scouting"]),
                 launch(["quick_stream", "router", "-l", endpoint, "--no-multicast-scouting"])]
        for p in procs:
            code, out = finish(p)
            assert code == 2 and "Traceback" not in out, f"{shlex.join(p.args)}: exit {code}\n{out}"
            assert endpoint in out and "in use" in out, out


def test_service_modules_name_their_installed_command() -> None:
    """``python -m quick_stream.services.NAME -h`` shows the console script's name, which is installed."""
    import shutil

    with processes() as launch:
        procs = {name: launch([f"quick_stream.services.{name}", "-h"])
                 for name in ("capture", "flow", "motion", "render", "recorder")}
        for name, p in procs.items():
            code, out = finish(p)
            assert code == 0 and out.startswith(f"usage: quick-stream-{name} "), out
            assert shutil.which(f"quick-stream-{name}", path=str(Path(sys.executable).parent)), name

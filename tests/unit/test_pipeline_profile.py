"""``bench pipeline --profile``: a service profiles itself when asked, the profiles are summed up per
stabilized frame without the waits, and a process's CPU is split by thread."""
from __future__ import annotations

import argparse
import os
import threading
import time
from pathlib import Path

import pytest

from quick_stream.bench import pipeline, pipeline_profile
from quick_stream.bench.pipeline_profile import PROFILE_ENV, format_profile, summarise, thread_cpu, thread_shares
from quick_stream.stream import process


def _busy(frames: int) -> int:
    """CPU work a profile must find, with a wait between (which it must leave out)."""
    total = 0
    for _ in range(frames):
        total += sum(i * i for i in range(20_000))
        time.sleep(0.001)
    return total


def test_a_service_profiles_its_run_only_when_asked(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def run(args: argparse.Namespace, conf: object) -> int:
        _busy(10)
        return 7

    monkeypatch.delenv(PROFILE_ENV, raising=False)
    assert process._profiled("flow", run) is run  # not asked: the run itself, nothing written
    monkeypatch.setenv(PROFILE_ENV, str(tmp_path))
    assert process._profiled("flow", run)(argparse.Namespace(), None) == 7
    profs = list(tmp_path.glob("*.prof"))
    assert [p.name for p in profs] == [f"flow-{os.getpid()}.prof"]

    rows = summarise(tmp_path, frames=10)["flow"]
    names = [r["function"] for r in rows]
    assert any("_busy" in n or "genexpr" in n for n in names[:3]), names  # the work is on top
    assert not any("sleep" in n for n in names), names  # the waits are not
    busy = next(r for r in rows if "genexpr" in r["function"] or "_busy" in r["function"])
    assert busy["own_ms"] > 0 and busy["calls"] > 0
    text = format_profile({"flow": {"main": 90.0, "python": 5.0, "zenoh": 5.0}}, {"flow": rows})
    assert "flow main 90, python 5, zenoh 5" in text and "ms per stabilized frame" in text


def test_a_damaged_profile_is_left_out(tmp_path: Path) -> None:
    (tmp_path / "render-1.prof").write_bytes(b"not a profile")
    assert summarise(tmp_path, frames=5) == {}


def test_thread_cpu_splits_the_main_thread_from_python_and_named_threads() -> None:
    spent, done = threading.Event(), threading.Event()

    def burn() -> None:  # until this thread itself has used 0.2 s of CPU (however loaded the machine)
        while time.thread_time() < 0.2:
            sum(i for i in range(1000))
        spent.set()
        done.wait()  # alive until measured (an ended thread leaves /proc)

    before = thread_cpu(os.getpid())
    t = threading.Thread(target=burn)
    t.start()
    spent.wait()
    after = thread_cpu(os.getpid())
    done.set()
    t.join()
    assert set(after) == {"main", "python", "zenoh"}
    assert after["python"] - before.get("python", 0.0) >= 0.1
    shares = thread_shares(after)
    assert abs(sum(shares.values()) - 100.0) < 0.5
    assert thread_cpu(2**22 + 1) == {}  # no such process


def test_the_profiles_are_not_scratch(tmp_path: Path) -> None:
    (tmp_path / "profile").mkdir()
    (tmp_path / "profile" / "flow-1.prof").write_bytes(b"x")
    (tmp_path / "recording.mcap").write_bytes(b"x")
    assert list(pipeline.scratch_files(tmp_path, {})) == [tmp_path / "recording.mcap"]
    assert pipeline_profile.PROFILE_ENV == process.PROFILE_ENV

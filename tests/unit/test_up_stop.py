"""How ``quick-stream up`` stops (quick_stream/cli/up_cmd.py), on fake services: stopped before the
stream's end, the capture goes first and the frames it sent get ``--stop-wait`` to reach the outputs.
The processes themselves: tests/integration/test_up_failures.py."""
from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest

from quick_stream.cli import up_cmd
from quick_stream.cli.up_cmd import Outcome


class Sup:
    """Children that stop when told; ``events``: what was done, in order."""

    def __init__(self) -> None:
        self.children = {n: SimpleNamespace(finished=False, exit_code=None)
                         for n in ("router", "recorder", "flow", "motion", "render", "capture")}
        self.events: list[str] = []

    def stop(self, order, grace_s=5.0):
        self.events.append(f"stop {','.join(order)}")
        for n in order:
            self.children[n].finished = True
        return {n: 0 for n in order}

    def running(self, name):
        return not self.children[name].finished

    def poll(self):
        return []


class Board:
    """The render's stats: ``ended`` after ``render_after`` looks (None: never)."""

    def __init__(self, sent: int, render_after: int | None) -> None:
        self.sent, self.render_after, self.looks = sent, render_after, 0

    def get(self, stream, name):
        if name != "render":
            return {}
        self.looks += 1
        return {"ended": 1 if self.render_after is not None and self.looks > self.render_after else 0}

    def totals(self, stream, name):
        return {"sent": self.sent} if name == "capture" else {}

    def drain(self):
        pass

    def restarted(self, stream, name):
        pass


def drain(tmp_path: Path, board: Board, stop: list[str], stop_wait: float = 10.0, on_sleep=None):
    args = SimpleNamespace(stream="cam0", stop_wait=stop_wait, stop_grace=5.0, out=str(tmp_path))
    sup, o, clock = Sup(), Outcome(reason="--duration 6 s"), [0.0]

    def sleep(s):
        clock[0] += s
        if on_sleep:
            on_sleep()

    up_cmd._drain(args, sup, board, stop, tmp_path / "status.json", o, clock=lambda: clock[0], sleep=sleep)
    return sup, o, clock[0]


def test_a_run_stopped_early_stops_the_capture_then_waits_for_the_render_to_end(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(up_cmd, "write_status", lambda *a, **k: None)
    sup, o, took = drain(tmp_path, Board(sent=90, render_after=5), [])
    assert sup.events == ["stop capture"]  # the others are stopped after, by _run
    assert o.drained and o.cut is None and 0 < took < 1
    assert "the frames it sent get up to 10 s to reach the outputs" in capsys.readouterr().err


def test_a_second_signal_or_the_stop_wait_ends_the_wait_and_says_why(tmp_path, monkeypatch):
    monkeypatch.setattr(up_cmd, "write_status", lambda *a, **k: None)
    stop = ["Ctrl-C"]
    _, o, took = drain(tmp_path, Board(sent=90, render_after=None), stop, on_sleep=lambda: stop.append("Ctrl-C"))
    assert not o.drained and o.cut == "Ctrl-C while the frames sent were on their way to the outputs" and took < 1
    _, o, took = drain(tmp_path, Board(sent=90, render_after=None), [], stop_wait=3)
    assert not o.drained and "not all through the render within --stop-wait 3 s" in o.cut and 3 <= took < 3.5


def test_nothing_sent_no_wait(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(up_cmd, "write_status", lambda *a, **k: None)
    sup, o, took = drain(tmp_path, Board(sent=0, render_after=None), [])
    assert sup.events == ["stop capture"] and took == 0 and o.cut is None and not o.drained
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("quiet", [False, True])
def test_the_live_status_board_goes_to_stderr(tmp_path, monkeypatch, capsys, quiet):
    """The board went to stdout, where the results go (``up | tee`` and ``up > result.txt`` got it)."""
    now = [100.0]
    monkeypatch.setattr(up_cmd, "time", SimpleNamespace(sleep=lambda s: None, monotonic=lambda: now[0]))
    monkeypatch.setattr(up_cmd, "write_status", lambda *a, **k: None)
    stop: list[str] = []

    def lines(*a):
        stop.append("Ctrl-C")  # one board, then the loop ends
        return ["quick-stream up:    5.0 s   stream cam0", "render    up   30.0"]

    monkeypatch.setattr(up_cmd, "status_lines", lines)
    sup, board = Sup(), Board(sent=1, render_after=None)
    args = SimpleNamespace(stream="cam0", quiet=quiet, duration=None, out=str(tmp_path))
    o = Outcome()
    sleeps = []

    def sleep(s):  # quiet: no board to end the loop; the second pass's signal does
        sleeps.append(s)
        if len(sleeps) == 2:
            stop.append("Ctrl-C")

    monkeypatch.setattr(up_cmd, "time", SimpleNamespace(sleep=sleep, monotonic=lambda: now[0]))
    up_cmd._loop(args, sup, board, stop, tmp_path / "status.json", now[0] - 5.0, o)
    out, err = capsys.readouterr()
    assert out == ""
    assert ("render    up   30.0" in err) != quiet and o.reason == "Ctrl-C"

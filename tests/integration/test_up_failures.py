"""``quick-stream up`` when something fails: it stops loudly and at once, leaves nothing running, and
says what failed (issue 30, rows 1 and 10). A process misbehaves on purpose through
tests/tools/child_faults (on PYTHONPATH: ``QUICK_STREAM_TEST_FAULT=<process>:<fault>``).

Every wait is on an event (the process's exit, a file's content) with a generous timeout that only
guards against a hang: nothing here measures time.
"""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import time
from pathlib import Path

from tests.helpers import UP
from tests.unit.test_cli_motion import write_tum_clip

from quick_stream.stream.launcher import free_port

FAULTS = Path(__file__).resolve().parents[1] / "tools" / "child_faults"
GUARD_S = 180  # only a hang reaches it


def start_up(out: Path, port: int, *extra: str, fault: str | None = None) -> subprocess.Popen:
    env = dict(os.environ)
    if fault:
        env["PYTHONPATH"] = os.pathsep.join([str(FAULTS), *filter(None, [env.get("PYTHONPATH")])])
        env["QUICK_STREAM_TEST_FAULT"] = fault
    return subprocess.Popen([*UP, "--out", str(out), "--port", str(port), *extra], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)


def ours(out: Path, port: int) -> dict[int, str]:
    """The processes of that run still alive: a service (its settings file is under ``out``) or the
    router (its port), not zombies."""
    found = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit() or int(d.name) == os.getpid():
            continue
        try:
            cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            state = next(x for x in (d / "status").read_text().splitlines() if x.startswith("State:"))
        except (OSError, StopIteration):
            continue
        if (str(out) in cmd or f"127.0.0.1:{port}" in cmd) and " up " not in cmd and "Z" not in state.split()[1]:
            found[int(d.name)] = cmd
    return found


def finish(p: subprocess.Popen, out: Path, port: int) -> tuple[int, str, str]:
    """Wait for ``up`` to end (a hang fails the test); leave nothing running whatever happens."""
    try:
        text, err = p.communicate(timeout=GUARD_S)
    except subprocess.TimeoutExpired:
        p.kill()
        text, err = p.communicate()
        raise AssertionError(f"up did not end within {GUARD_S} s: {text[-2000:]}\n{err[-2000:]}") from None
    finally:
        if p.poll() is None:
            p.kill()
    return p.returncode, text, err


def no_leftovers(out: Path, port: int) -> None:
    left = ours(out, port)
    for pid in left:  # leave nothing behind, then fail
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    assert not left, f"still running after up ended: {left}"


def wait_for(cond, what: str) -> None:
    deadline = time.monotonic() + GUARD_S
    while not cond():
        assert time.monotonic() < deadline, f"{what}: not within {GUARD_S} s"
        time.sleep(0.05)


def test_a_status_file_that_cannot_be_written_stops_up_at_once_and_says_so(tmp_path):
    # row 1: the first write of status.json that failed (a full disk) raised out of `up`, which
    # stopped its children, then hung in zenoh's threads at exit and ignored SIGTERM
    out, port = tmp_path / "out", free_port()
    p = start_up(out, port, "--source", "synthetic:frames=100000,width=160,height=120")
    # where status.json is written first, made not a file once the run has its logs folder (made before it:
    # the run would take logs-1, an earlier run's folder being left alone)
    wait_for(lambda: (out / "logs" / "settings.toml").exists() or p.poll() is not None, "the run's logs folder")
    while True:
        try:
            (out / "logs" / "status.tmp").mkdir()
            break
        except FileExistsError:  # a write of status.json under way, between its temporary file and the rename
            time.sleep(0.01)
    code, text, err = finish(p, out, port)
    no_leftovers(out, port)
    assert code == 1 and "Traceback" not in err, err
    assert f"cannot write {out / 'logs' / 'status.json'}: Is a directory" in err
    assert "stopped: cannot write" in text
    st = json.loads((out / "logs" / "status.json").read_text())  # the end, shortened, written in place
    assert st["exit_code"] == 1 and "status.json" in st["error"]


def test_a_router_that_exits_before_answering_ends_up_at_once_naming_why(tmp_path):
    out = tmp_path / "out"
    with socket.socket() as squatter:  # bound, not listening: the router cannot listen there, a connect is refused
        squatter.bind(("127.0.0.1", 0))
        port = squatter.getsockname()[1]
        code, text, err = finish(start_up(out, port), out, port)
    no_leftovers(out, port)
    assert code == 1, text + err
    assert "router exited" in err and "Address already in use" in err, err  # was: "did not come up ... Timeout!"
    assert not (out / "logs" / "flow.log").exists()  # nothing else was started
    assert json.loads((out / "logs" / "status.json").read_text())["error"].startswith("router exited")


def test_up_answers_sigterm_while_the_router_hangs(tmp_path):
    # before: SIGTERM waited for the router to answer (20 s, each try up to 30 s), then the run started
    out, port = tmp_path / "out", free_port()
    p = start_up(out, port, "--stop-grace", "1", fault="router:hang")  # killed 1 s after SIGTERM, not 5
    wait_for(lambda: any(" router " in c for c in ours(out, port).values()), "the router process")
    p.send_signal(signal.SIGTERM)
    code, text, err = finish(p, out, port)
    no_leftovers(out, port)  # the router ignored SIGTERM: killed
    assert code == 1 and "signal SIGTERM while the router was starting" in text, text + err
    assert "exit codes: router -9" in err and "router did not stop within 1 s of SIGTERM" in err, err
    assert not (out / "logs" / "flow.log").exists()


def test_up_answers_sigterm_while_a_service_hangs(tmp_path):
    out, port = tmp_path / "out", free_port()
    p = start_up(out, port, "--source", "synthetic:frames=100000,width=160,height=120", "--stop-grace", "1",
                 fault="motion:hang")
    status = out / "logs" / "status.json"
    wait_for(lambda: status.exists() and json.loads(status.read_text() or "{}").get("services", {})
             .get("motion", {}).get("running"), "motion started")
    p.send_signal(signal.SIGTERM)
    code, text, err = finish(p, out, port)
    no_leftovers(out, port)
    assert "stopped: signal SIGTERM" in text and "motion -9" in err, text + err
    assert "motion did not stop within 1 s of SIGTERM" in err, err
    st = json.loads(status.read_text())
    assert st["stopped"] == "signal SIGTERM" and st["services"]["motion"]["exit_codes"] == [-9]


def test_a_service_that_cannot_start_ends_the_run_after_a_few_tries(tmp_path):
    out, port = tmp_path / "out", free_port()
    code, text, err = finish(start_up(out, port, fault="flow:exit1"), out, port)
    no_leftovers(out, port)
    assert code == 1 and "flow exited 1 3 times in a row" in err, text + err
    st = json.loads((out / "logs" / "status.json").read_text())
    assert st["services"]["flow"]["restarts"] == 2 and st["services"]["flow"]["exit_codes"] == [1, 1, 1]  # was 20
    assert st["error"].startswith("flow exited 1 3 times in a row")


def test_frames_lost_before_flow_show_in_the_drops_and_the_summary(tmp_path):
    # row 10: frames that never reached flow showed as drops 0 everywhere; the only sign was a note
    out, port = tmp_path / "out", free_port()
    p = start_up(out, port, "--source", "synthetic:frames=60,width=160,height=120", "--pace", "fast",
                 fault="flow:lose=20-29")
    code, text, err = finish(p, out, port)
    assert code == 0, text + err
    st = json.loads((out / "logs" / "status.json").read_text())
    frames = st["frames"]
    assert frames["offered"] == frames["sent"] == 60 and frames["shed"] == 0 and frames["missing_at_flow"] == 10
    assert frames["stabilized"] + frames["uncorrected"] + frames["lost"] + frames["dropped_render"] == 60
    assert st["services"]["flow"]["drops"] == 10
    assert st["services"]["render"]["drops"] == frames["uncorrected"] + frames["dropped_render"]
    summary = next(x for x in text.splitlines() if x.startswith("stabilized "))
    assert summary == st["summary"]
    assert summary.startswith(f"stabilized {frames['stabilized']} of 60 frames: 0 shed at the capture")
    assert "flow missed 10 of the frames sent" in summary
    flow_row = next(x for x in text.splitlines() if x.startswith("flow "))
    assert flow_row.split()[5] == "10", flow_row  # the drops column
    assert f"wrote {out / 'stabilized.avi'}, {out / 'recording.mcap'}" in text


def test_a_run_stopped_by_duration_lets_every_frame_sent_reach_the_video(tmp_path):
    # `up --duration 6` sent 90 frames and the video held 60: every service was stopped at once, the
    # frames in flight (flow behind the capture) with them (a 640x480 run: 174 sent, 135 in the video)
    from quick_stream.io.video_check import video_frames

    out, port = tmp_path / "out", free_port()
    p = start_up(out, port, "--source", "synthetic:frames=100000,width=160,height=120", "--pace", "fast",
                 "--duration", "5", "--quiet", fault="flow:slow=40")
    code, text, err = finish(p, out, port)
    no_leftovers(out, port)
    assert code == 0, text + err
    frames = json.loads((out / "logs" / "status.json").read_text())["frames"]
    assert frames["sent"] > 0 and frames["rendered"] == frames["sent"] and frames["lost"] == 0, frames
    assert video_frames(out / "stabilized.avi") == frames["sent"]
    assert "the capture has ended the stream; the frames it sent get up to 10 s to reach the outputs" in err
    assert "stopped: --duration 5 s" in text and "0 lost in transit" in text


def test_a_run_that_produced_nothing_exits_non_zero(tmp_path):
    clip = tmp_path / "clip"
    write_tum_clip(clip, n=10)
    for f in (clip / "depth").iterdir():
        f.unlink()  # every frame's depth is missing: the source cannot deliver one
    out, port = tmp_path / "out", free_port()
    code, text, err = finish(start_up(out, port, "--source", f"tum:{clip}", "--pace", "fast"), out, port)
    assert code == 1, text + err
    assert "stabilized 0 of 10 frames" in err and "10 the source could not deliver: nothing was produced" in err
    assert "stabilized.avi" not in text  # not said to be written

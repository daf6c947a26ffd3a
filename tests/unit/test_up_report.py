"""What ``quick-stream up`` tells: every frame not stabilized counted where the user looks (the drops
column, the final account), outputs called written only when whole, and the supervisor/status-board
pieces that keep ``up`` from hanging (quick_stream/cli/up_report.py, quick_stream/stream/launcher.py,
quick_stream/io/file_checks.py). The processes themselves: tests/integration/test_up_failures.py."""
from __future__ import annotations

import threading
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Callable

import cv2
import numpy as np
import pytest

from quick_stream.cli.up_report import frame_account, frame_drops, write_status
from quick_stream.io.file_checks import incomplete
from quick_stream.stream.launcher import ServiceSpec, StatusBoard, Supervisor, open_when_up
from quick_stream.stream.process import close_within
from quick_stream.stream.wire import Stats, encode_stats

# row 10 of issue 30, as the services' stats said it (a loaded machine, real-time pacing)
ROW10 = {"capture": {"sent": 203, "shed": 47, "bad_frames": 0},
         "flow": {"missing_frames": 47, "inbox0_dropped": 0},
         "motion": {"invalid_motions": 6, "inbox0_dropped": 0},
         "render": {"render_total": 203, "flagged": 0, "dropped": 0, "orphans": 0, "inbox0_dropped": 0},
         "recorder": {"inbox0_dropped": 0}}


def totals(stats: dict) -> Callable[[str], dict]:
    return lambda name: stats.get(name, {})


def test_frames_shed_at_the_capture_are_in_its_drops_and_in_the_account():
    t = totals(ROW10)
    assert frame_drops("capture", t) == 47  # was 0: the drops column summed queue drops only
    assert frame_drops("flow", t) == 0  # missing at flow, but the capture's (shed), counted there
    acc = frame_account(t)
    assert (acc.offered, acc.stabilized, acc.shed, acc.lost, acc.uncorrected) == (250, 203, 47, 0, 0)
    line = acc.line("realtime")
    assert line.startswith("stabilized 203 of 250 frames: 47 shed at the capture (because the pipeline took frames "
                           "more slowly than the capture offered them")
    assert "--pace fast" in line


def test_frames_lost_on_the_way_to_flow_dropped_or_flagged_at_render_are_counted_once_each():
    stats = {"capture": {"sent": 300, "shed": 20, "bad_frames": 2},
             "flow": {"missing_frames": 20 + 2 + 12, "inbox0_dropped": 3},  # 12 lost on the way (3 of them its queue's)
             "render": {"render_total": 285, "flagged": 9, "dropped": 4, "refused_frames": 1, "inbox1_dropped": 0}}
    t = totals(stats)
    assert frame_drops("flow", t) == 12
    assert frame_drops("render", t) == 9 + 4 + 1
    acc = frame_account(t)
    assert acc.offered == 322 and acc.stabilized == 276 and acc.missing_at_flow == 12
    assert acc.dropped_render == 5 and acc.lost == 300 - 285 - 5
    parts = acc.stabilized + acc.shed + acc.bad_source + acc.lost + acc.uncorrected + acc.dropped_render
    assert parts == acc.offered  # each frame once
    line = acc.line("realtime")
    assert ("stabilized 276 of 322 frames: 20 shed at the capture" in line and "10 lost in transit" in line
            and "9 rendered uncorrected (flagged)" in line and "5 dropped at render" in line
            and "2 the source could not deliver" in line and "flow missed 12 of the frames sent" in line)
    assert "in flight when the run stopped" in acc.line("realtime", whole_stream=False)


def test_a_foreign_flood_shed_from_a_queue_is_no_drop_of_the_streams_frames():
    """10,000 forged frames in a live fuzz: flow's queue shed 1,190 of them (``inbox0_dropped_foreign``) and
    no real frame, yet the board showed flow with 1,190 drops (2,380 with the forged stats counted twice)."""
    t = totals({"capture": {"sent": 300}, "flow": {"missing_frames": 0, "inbox0_dropped": 1195,
                                                   "inbox0_dropped_foreign": 1190},
                "motion": {"inbox0_dropped": 4, "inbox0_dropped_foreign": 4}})
    assert frame_drops("flow", t) == 5 and frame_drops("motion", t) == 0


def test_frames_the_flow_service_shed_are_in_its_drops_and_in_the_account():
    """A publisher faster than the pipeline (not our capture, which sheds before sending): flow sheds,
    once, before decoding (``shed``; ``shed_backlog`` of them dropped by its full queue, also in its
    queue's count) and render lets them go. They are flow's drops and "shed at flow" in the account,
    not frames lost in transit."""
    t = totals({"capture": {"sent": 7000},  # (the frames the publisher sent)
                "flow": {"shed": 2000, "shed_backlog": 300, "inbox0_dropped": 300},
                "render": {"render_total": 5000, "flagged": 0, "shed_upstream": 2000}})
    assert frame_drops("flow", t) == 2000
    acc = frame_account(t)
    assert (acc.stabilized, acc.shed_flow, acc.lost) == (5000, 2000, 0)
    parts = acc.stabilized + acc.shed + acc.bad_source + acc.shed_flow + acc.lost + acc.uncorrected + acc.dropped_render
    assert parts == acc.offered == 7000
    assert "2000 shed at flow" in acc.line("fast")


def test_no_stats_from_render_is_said_not_taken_for_zero():
    acc = frame_account(totals({"capture": {"sent": 10}}))
    assert not acc.render_known and acc.rendered == 0
    assert acc.line("fast").startswith("stabilized frames not known (render published no stats) of 10 frames")


def _ring_board() -> tuple[StatusBoard, list]:
    ring: list = []
    board = StatusBoard(SimpleNamespace(declare_subscriber=lambda key, handler: SimpleNamespace(
        try_recv=lambda: ring.pop(0) if ring else None, undeclare=lambda: None)))
    return board, ring


def _stats(ring: list, service: str, seq: int, **values) -> None:
    data = encode_stats(Stats(service, values), "cam0", seq)
    ring.append(SimpleNamespace(key_expr="quick/@v1/cam0/stats", payload=SimpleNamespace(to_bytes=lambda: data)))


def test_a_restarted_service_counts_its_predecessors_frames():
    board, ring = _ring_board()
    for seq, sent in enumerate((30, 60, 90)):
        _stats(ring, "capture", seq, sent=sent, shed=5, send_fps=30.0)
    _stats(ring, "capture", 0, sent=12, shed=1, send_fps=30.0)  # its successor numbers its stats from 0 again
    assert board.get("cam0", "capture")["sent"] == 12  # the current process's
    t = board.totals("cam0", "capture")
    assert t["sent"] == 102 and t["shed"] == 6 and t["send_fps"] == 30.0


def _clocked_board(service: str):
    """A status board on a test clock ``t`` ([seconds]) and ``put(who, seq, **values)``: one stats message
    of ``service`` from publisher ``who``, taken in."""
    board, ring = _ring_board()
    t = [0.0]
    board.clock = lambda: t[0]

    def put(who: str, seq: int, **values) -> None:
        _stats(ring, service, seq, **values)
        ring[-1].timestamp = SimpleNamespace(get_id=lambda: who)
        board.drain()

    return board, t, put


def test_stats_forged_under_a_live_services_name_are_not_taken():
    """A stats message under flow's name from another publisher, with a lower seq, passed for a restarted
    flow: flow's counts were added to its totals again (the live fuzz: refused frames 731 on flow's own
    stats, 1,462 in the final summary). A real successor is taken once its predecessor is quiet."""
    board, t, put = _clocked_board("flow")

    for seq in range(5):
        t[0] += 1.0
        put("flow-1", seq, refused_frames=100 * seq)
    put("forger", 4, refused_frames=7)
    t[0] += 1.0
    put("flow-1", 5, refused_frames=500)
    assert board.totals("cam0", "flow")["refused_frames"] == 500 and board.foreign == 1
    t[0] += 10.0  # flow-1 killed: quiet since; its successor numbers its stats from 0 again
    put("flow-2", 0, refused_frames=3)
    assert board.totals("cam0", "flow")["refused_frames"] == 503 and board.foreign == 1


def test_a_restarted_services_stats_are_taken_at_once():
    """A recorder restarted 2 s after its kill, near the stream's end: its successor's stats (with the hole
    it logged) came within the 3 s its predecessor counted as alive and were ignored to the end
    (test_faults[recorder]: restart_hole 0 in status.json). The supervisor's word opens the name."""
    board, t, put = _clocked_board("recorder")

    for seq in range(3):
        t[0] += 1.0
        put("rec-1", seq, restart_hole=0)
    t[0] += 1.5  # killed, restarted by up at once
    board.restarted("cam0", "recorder")
    put("rec-2", 0, restart_hole=812)
    assert board.get("cam0", "recorder")["restart_hole"] == 812 and board.foreign == 0
    put("forger", 0, restart_hole=1)  # the name is the new process's again
    assert board.get("cam0", "recorder")["restart_hole"] == 812 and board.foreign == 1


def test_status_json_that_cannot_be_written_raises_naming_it_and_leaves_no_part(tmp_path):
    sup = Supervisor([], tmp_path / "logs")
    board, _ = _ring_board()
    path = tmp_path / "status.json"
    path.with_suffix(".tmp").mkdir()  # the part file cannot be made
    with pytest.raises(OSError) as e:
        write_status(path, board, sup, "cam0", None)
    assert e.value.filename == str(path)
    # the run's end still gets in, shortened, written in place
    write_status(path, board, sup, "cam0", "stopped", {"error": "x failed", "exit_code": 1, "summary": "s"})
    assert '"error": "x failed"' in path.read_text()


def test_a_service_that_keeps_failing_at_start_is_not_restarted_again(tmp_path):
    sup = Supervisor([ServiceSpec("bad", ["-c", "import sys; sys.exit(1)"])], tmp_path, restart_delay_s=0.0)
    sup.start()
    deadline = time.monotonic() + 120  # a failure guard only
    while not sup.children["bad"].finished and time.monotonic() < deadline:
        sup.poll()
        time.sleep(0.02)
    c = sup.children["bad"]
    assert c.finished and c.restarts == 2 and c.exit_code == 1  # was restarted 20 times
    assert "3 times in a row" in sup.events[-1]["event"]


def test_a_killed_service_is_restarted_however_soon(tmp_path):
    sup = Supervisor([ServiceSpec("s", ["-c", "import os, signal; os.kill(os.getpid(), signal.SIGKILL)"])], tmp_path,
                     restart_delay_s=0.0, max_restarts=5)
    sup.start()
    deadline = time.monotonic() + 120
    while not sup.children["s"].finished and time.monotonic() < deadline:
        sup.poll()
        time.sleep(0.02)
    assert sup.children["s"].restarts == 5  # the restart budget, not the crash-loop guard


def test_waiting_for_the_router_gives_up_when_told():
    class Gone(Exception):
        pass

    calls = []

    def waiting() -> None:
        calls.append(1)
        if len(calls) == 2:
            raise Gone

    with pytest.raises(Gone):  # nothing listens there: each try ends within its own short timeout
        open_when_up(f"tcp/127.0.0.1:{_closed_port()}", timeout_s=600, waiting=waiting)


def _closed_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_close_that_hangs_does_not_hang_its_caller():
    release = threading.Event()
    done = []
    assert close_within([lambda: done.append(1), lambda: release.wait(600)], timeout_s=0.2).startswith("did not finish")
    assert done == [1]
    release.set()
    assert close_within([lambda: 1 / 0], timeout_s=60).startswith("ZeroDivisionError")
    assert close_within([lambda: None], timeout_s=60) is None


def _video(path: Path, n: int = 5) -> None:
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30, (64, 48))
    assert w.isOpened()
    for i in range(n):
        w.write(np.full((48, 64, 3), i * 40, np.uint8))
    w.release()


def test_a_video_is_whole_only_with_its_index_and_every_box_there(tmp_path):
    good = tmp_path / "v.mp4"
    _video(good)
    assert incomplete(good) is None
    data = good.read_bytes()
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(data[:-100])  # the last box runs past the end
    assert "cut off" in incomplete(cut)
    moov = data.find(b"moov") - 4
    unindexed = tmp_path / "unindexed.mp4"
    unindexed.write_bytes(data[:moov])  # a writer that never closed the file
    assert "no 'moov' box" in incomplete(unindexed)
    assert incomplete(tmp_path / "none.mp4") == "not there"
    (tmp_path / "empty.mp4").write_bytes(b"")
    assert incomplete(tmp_path / "empty.mp4") == "empty"


def test_a_recording_is_whole_only_with_its_footer(tmp_path):
    from quick_stream.io.recording import Recorder

    path = tmp_path / "r.mcap"
    with Recorder(path) as rec:
        rec.write("quick/@v1/cam0/stats", encode_stats(Stats("x", {"i": 1}), "cam0", 0), 1)
    assert incomplete(path) is None
    (tmp_path / "torn.mcap").write_bytes(path.read_bytes()[:-40])
    assert "quick-stream recover" in incomplete(tmp_path / "torn.mcap")



def test_a_service_whose_session_close_hangs_still_finishes(monkeypatch):
    """The router went away with a SIGKILLed up: the session's close hangs. The runtime gives it
    SESSION_CLOSE_S, logs it and goes on (a recorder then finishes its file), and the process is marked
    to exit without finalising zenoh again (a recorder ran on for over a minute after its SIGTERM)."""
    import zenoh

    from quick_stream.stream import process
    from quick_stream.stream.runtime import ServiceRuntime

    monkeypatch.setattr(process, "_unclosed", [])
    monkeypatch.setattr("quick_stream.stream.runtime.SESSION_CLOSE_S", 0.2)
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    rt = ServiceRuntime("flow", "cam0", conf, install_signals=False)
    real, release = rt.session, threading.Event()

    class Hung:
        def close(self):
            release.wait(600)

        def __getattr__(self, name):
            return getattr(real, name)

    rt.session = Hung()
    try:
        rt.close()  # returns: the close is left behind
        assert process._unclosed and process._unclosed[0].startswith("did not finish within 0.2 s")
    finally:
        release.set()
        real.close()

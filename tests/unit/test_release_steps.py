"""``bench pipeline``'s split of a release's first frame into the stages it crosses
(quick_stream.bench.release_steps)."""
from __future__ import annotations

from quick_stream.bench.pipeline_report import format_report
from quick_stream.bench.release_steps import STEPS, release_steps, step_times
from quick_stream.io.recording import Recorder
from quick_stream.stream import keys
from quick_stream.stream.wire.codec import pack

MS = 1_000_000


def release(first: int, size: int, closed_by: int | None, t0_ms: int, stabilized: bool = True,
            stream: str = "cam0") -> list[tuple[str, int, bytes]]:
    """The messages of one release as a recorder logs them: the closing frame at ``t0_ms``, its flow 12 ms
    later, its motion 15 ms after that, the corrections 1-3 ms after that, the first frame out 60 ms later."""
    k = lambda stage: keys.key(stream, stage)  # noqa: E731
    closing = closed_by if closed_by is not None else first + size
    out = [(k("frame"), t0_ms * MS, pack({"t_ns": 0}, "frame", stream, closing)),
           (k("flow"), (t0_ms + 12) * MS, pack({"seq_next": closed_by or 0}, "flow", stream, (closed_by or 1) - 1)),
           (k("motion"), (t0_ms + 27) * MS, pack({"seq_next": closed_by or 0}, "motion", stream, (closed_by or 1) - 1))]
    for i in range(size):
        out.append((k("correction"), (t0_ms + 28 + i) * MS,
                    pack({"batch": [first, i, size], "closed_by": closed_by}, "correction", stream, first + i)))
    if stabilized:
        out.append((k("stabilized"), (t0_ms + 88) * MS, pack({"t_ns": 0}, "stabilized", stream, first)))
    return out


def test_each_release_first_frame_is_split_into_the_stages_it_crosses():
    msgs = (release(0, 5, 7, 100)  # before from_seq: left out
            + release(5, 5, 12, 300) + release(10, 4, 16, 500)
            + release(14, 3, None, 700)  # the end of a stream closed it: no closing frame to time from
            + release(17, 3, 22, 900, stabilized=False)  # its first frame never came out
            + release(20, 3, 25, 1100, stream="cam1")  # another stream
            + [(keys.key("cam0", "correction"), 1200 * MS, b"\xc1"),  # malformed: skipped
               (keys.key("cam0", "correction"), 1201 * MS,
                pack({"last_seq": 19, "reason": "stopped"}, "end", "cam0", 19))])
    got = step_times(sorted(msgs, key=lambda m: m[1]), "cam0", from_seq=5)
    assert got == {"flow": [12.0, 12.0], "motion and path": [15.0, 15.0], "correction": [1.0, 1.0],
                   "render": [60.0, 60.0]}
    assert list(got) == list(STEPS)
    assert step_times(msgs, "cam1")["render"] == [60.0]


def test_the_steps_are_read_from_a_recording_and_printed_with_the_latencies(tmp_path):
    path = tmp_path / "recording.mcap"
    with Recorder(path) as rec:
        for topic, t_ns, data in sorted(release(0, 4, 6, 100) + release(4, 4, 10, 300), key=lambda m: m[1]):
            rec.write(topic, data, log_time_ns=t_ns)
    steps = release_steps(path, "cam0")
    assert steps["render"] == {"p50": 60.0, "p90": 60.0, "max": 60.0, "n": 2}
    r = {"size": "640x480", "fps_target": 30.0, "seconds": 30, "capture": "replay of a pre-encoded recording",
         "recording": True, "frames_sent": 8, "frames_stabilized": 8, "stabilized_fps": 30.0, "frames_flagged": 0,
         "drops": {}, "latency": {}, "processes": {}, "queues": {}, "release_steps_ms": steps}
    assert ("first frame of a release, by step (the recorder's arrival times): flow p50 12.0 p90 12.0 ms, "
            "motion and path p50 15.0 p90 15.0 ms, correction p50 1.0 p90 1.0 ms, render p50 60.0 p90 60.0 ms (n=2)"
            in format_report(r))
    r["release_steps_ms"] = {"error": f"{path}: cannot read"}
    assert f"by step (the recorder's arrival times): {path}: cannot read" in format_report(r)

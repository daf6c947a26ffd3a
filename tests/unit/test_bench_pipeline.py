"""``bench pipeline``'s report: the CPU each process spends per stabilized frame against what the cores give."""
from __future__ import annotations

from quick_stream.bench.pipeline import cpu_per_frame, format_report


def proc(cpu_pct: float) -> dict:
    return {"cpu_pct": cpu_pct, "rss_mb_warm": 100.0, "rss_mb_end": 101.0, "rss_growth_pct": 1.0, "peak_rss_mb": 102.0,
            "rss_mb_series": [90.0, 100.0, 101.0]}


def test_cpu_per_frame_is_each_process_cpu_over_the_rate_against_the_cores_budget():
    procs = {"flow": proc(60.0), "render": proc(80.0), "router": proc(1.0)}
    c = cpu_per_frame(procs, 40.0, 2)
    # 60 % of a core at 40 frames/s: 0.6 s/s / 40 = 15 ms a frame; two cores give 2 s/s / 40 = 50 ms a frame
    assert c == {"ms": {"flow": 15.0, "render": 20.0, "router": 0.25}, "total_ms": 35.25, "cores": 2,
                 "budget_ms": 50.0, "rate_fps": 40.0}
    assert cpu_per_frame(procs, 0.0, 2) == {}


def test_the_report_prints_cpu_per_frame_and_how_much_of_the_budget_it_uses():
    procs = {"flow": proc(60.0), "render": proc(80.0)}
    r = {"size": "640x480", "fps_target": "fast", "seconds": 30, "capture": "replay of a pre-encoded recording",
         "recording": True, "frames_sent": 1200, "frames_stabilized": 1190, "stabilized_fps": 40.0, "frames_flagged": 0,
         "drops": {}, "latency": {}, "processes": procs, "queues": {}, "cpu_per_frame": cpu_per_frame(procs, 40.0, 2)}
    text = format_report(r)
    row = next(line for line in text.splitlines() if line.strip().startswith("render"))
    assert row.split()[1:3] == ["80.0", "20.0"]
    assert "CPU per stabilized frame: 35.0 ms of the 50.0 ms that 2 cores give per frame at 40 fps (70 % used)" in text
    del r["cpu_per_frame"]  # a report without it (nothing stabilized): no ms column values, no budget line
    assert "CPU per stabilized frame" not in format_report(r)

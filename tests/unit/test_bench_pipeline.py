"""``bench pipeline``'s report: the CPU each process spends per stabilized frame against what the cores give."""
from __future__ import annotations

import pytest

from quick_stream.bench.pipeline import cpu_per_frame
from quick_stream.bench.pipeline_report import format_report


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
    assert row.split()[1:4] == ["80.0", "20.0", "50"]  # CPU %, ms a frame, frames/s on a core of its own
    assert "CPU per stabilized frame: 35.0 ms of the 50.0 ms that 2 cores give per frame at 40 fps (70 % used)" in text
    del r["cpu_per_frame"]  # a report without it (nothing stabilized): no ms column values, no budget line
    assert "CPU per stabilized frame" not in format_report(r)


@pytest.mark.parametrize("keep", [False, True])
def test_bench_pipeline_says_where_it_wrote_and_how_much_and_deletes_its_scratch(tmp_path, monkeypatch, capsys, keep):
    """``bench pipeline`` left 0.8-1.3 GB in out/ without a word. Its recordings and videos are scratch now:
    deleted once measured (the logs kept) unless --keep; the last line says where and how much."""
    from quick_stream.bench import pipeline

    out = tmp_path / "bench"
    earlier = out / "fps-30.0" / "recording.mcap"  # an earlier run's, kept: not this run's to delete
    earlier.parent.mkdir(parents=True)
    earlier.write_bytes(b"x" * 10)

    def run(folder, *a, **k):
        (folder / "logs").mkdir(parents=True, exist_ok=True)
        (folder / "logs" / "render.log").write_text("log")
        (folder / "recording-1.mcap").write_bytes(b"r" * 2_000_000)
        (folder / "stabilized-cam0.avi").write_bytes(b"v" * 500_000)
        return {}

    monkeypatch.setattr(pipeline, "run_pipeline", run)
    monkeypatch.setattr(pipeline, "format_report", lambda r: "REPORT")
    assert pipeline.main([30.0], 1.0, str(out), None, keep=keep) == 0
    text = capsys.readouterr().out
    folder = out / "fps-30.0"
    left = sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())
    if keep:
        assert f"wrote 2.5 MB in {folder} (avi, mcap; kept: delete {folder} when done); logs in {folder / 'logs'}" in text
        assert left == ["logs/render.log", "recording-1.mcap", "recording.mcap", "stabilized-cam0.avi"]
    else:
        assert f"deleted 2.5 MB of scratch files (avi, mcap) from {folder} (--keep keeps them)" in text
        assert left == ["logs/render.log", "recording.mcap"]
    assert text.index("REPORT") < text.index(str(folder))


class _Started(Exception):
    pass


@pytest.mark.parametrize("preset", [None, "0.5s"])
def test_a_latency_preset_goes_to_the_motion_service_only(tmp_path, monkeypatch, preset):
    from quick_stream.bench import pipeline

    seen = {}

    def supervisor(specs, *a, **k):
        seen.update({s.name: s.argv for s in specs})
        raise _Started

    monkeypatch.setattr(pipeline, "Supervisor", supervisor)
    with pytest.raises(_Started):
        pipeline.run_pipeline(tmp_path, 30.0, 1.0, latency=preset)
    flagged = [name for name, argv in seen.items() if "--latency" in argv]
    if preset is None:
        assert flagged == []
    else:
        assert flagged == ["motion"]
        argv = seen["motion"]
        assert argv[argv.index("--latency") + 1] == preset


def test_bench_pipeline_runs_each_rate_with_each_preset_and_tables_their_delay(tmp_path, monkeypatch, capsys):
    from quick_stream.bench import pipeline

    runs = []

    def run(folder, fps, seconds, **k):
        runs.append((folder.name, fps, k["latency"]))
        wait = {"0.5s": 400.0, "1s": 900.0}[k["latency"]]
        lat = {"total_ms": {"p50": wait + 60.0, "p90": wait + 90.0, "p99": wait + 130.0, "max": wait + 200.0, "n": 10},
               "segment_wait_ms": {"p50": wait, "p90": wait, "p99": wait, "max": wait, "n": 10},
               "processing_ms": {"p50": 60.0, "p90": 90.0, "p99": 130.0, "max": 200.0, "n": 10}}
        return {"fps_target": fps, "latency_preset": k["latency"], "latency": lat, "frames_stabilized": 300,
                "frames_flagged": 0, "drops": {"capture.shed": 2}}

    monkeypatch.setattr(pipeline, "run_pipeline", run)
    monkeypatch.setattr(pipeline, "format_report", lambda r: "REPORT")
    assert pipeline.main([30.0], 1.0, str(tmp_path), None, presets=["0.5s", "1s"]) == 0
    assert runs == [("fps-30.0-latency-0.5s", 30.0, "0.5s"), ("fps-30.0-latency-1s", 30.0, "1s")]
    text = capsys.readouterr().out
    rows = {ln.split()[0]: ln.split()[1:] for ln in text.splitlines() if ln.strip().startswith(("0.5s", "1s"))}
    # fps, total p50 / p99 / max, wait p50, processing p99, stabilized, flagged, shed
    assert rows == {"0.5s": ["30.0", "460", "530", "600", "400", "130", "300", "0", "2"],
                    "1s": ["30.0", "960", "1030", "1100", "900", "130", "300", "0", "2"]}

"""``quick-stream bench speed --versus-vidstab``: ours and vid.stab on one clip, alternated, with the ratios."""
from __future__ import annotations

import pytest

from quick_stream.bench import speed_versus
from quick_stream.cli import main as cli_main
from tests.unit.test_cli_motion import write_tum_clip


def test_both_run_alternated_on_the_same_frames_and_the_ratios_are_theirs(tmp_path):
    write_tum_clip(tmp_path / "clip", n=12)
    msgs: list[str] = []
    r = speed_versus.run(f"tum:{tmp_path / 'clip'}", repeat=2, work=tmp_path / "work", progress=msgs.append)
    assert [m.split(": ", 1)[-1] for m in msgs[1:]] == ["quick-stream stabilize", "vid.stab (2 passes)"] * 2
    assert r["frames"] == 12 and len(r["rounds"]["ours"]) == len(r["rounds"]["vidstab"]) == 2
    assert all(x["frames"] == 12 for x in r["rounds"]["vidstab"])
    o, v = r["ours"], r["vidstab"]
    assert 0 < o["compute_ms"] <= o["wall_ms"] and v["wall_ms"] > 0 and v["cpu_ms"] > 0
    assert {"flow", "motion", "render"} <= set(o["stages_ms"])
    assert r["ratio_compute"] == pytest.approx(o["compute_ms"] / v["wall_ms"])
    assert r["ratio_wall"] == pytest.approx(o["wall_ms"] / v["wall_ms"])
    assert (tmp_path / "work" / "vidstab.mp4").stat().st_size > 0 and (tmp_path / "work" / "ours.mp4").exists()
    text = speed_versus.format_report(r)
    assert f"ratio compute / vid.stab: {r['ratio_compute']:.2f}x" in text


def test_a_clip_that_is_not_a_tum_folder_is_refused(capsys):
    assert cli_main(["bench", "speed", "--versus-vidstab", "synthetic", "--repeat", "1"]) == 2
    assert "the side-by-side clip is a TUM folder, tum:PATH" in capsys.readouterr().err

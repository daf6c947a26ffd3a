"""``quick-stream bench quality`` on real footage and degraded sensors (the benchmark itself is run
by hand, not here): ``--real``, ``--clip SRC:SEED:A-B``, ``--degrade`` and ``--degrade-grid``
parsing and checks, the degrade cells' flags (against the real degrade tool when ../shared is
present), the cache of degraded copies, the robustness grid and its table from a made-up
result, ours' uncorrected frames and fallback counts, and a small run through stand-in tools.
"""
from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from quick_stream.bench import quality, quality_tables
from quick_stream.bench.degrade_clips import DegradeCell, grid_cells, make_degraded, parse_degrade
from quick_stream.bench.quality_clips import ShakeClip, prepare_clips, select_sources
from quick_stream.bench.quality_robustness import format_robustness, is_peer, robustness_rows
from quick_stream.bench.shake_clips import RECORD, ShakeSpec
from quick_stream.cli import main
from quick_stream.io.sources import SourceError

SHARED = Path(__file__).resolve().parents[3] / "shared"
OFF = ["--stereo-k", "0", "--holes", "0", "--shift", "0,0", "--depth-lag", "0", "--blur", "0", "--gain-jitter", "0",
       "--jpeg", "0"]


def off_but(**values: str) -> list[str]:
    """degrade.py's seven flags, all off but those given (flag name with _ for -)."""
    out = list(OFF)
    for k, v in values.items():
        out[out.index("--" + k.replace("_", "-")) + 1] = v
    return out


# --------------------------------------------------------------------------------------------
# parsing


def test_clip_takes_a_source_and_keeps_the_old_form():
    c = ShakeClip.parse("7:0-149")
    assert c.source == "7scenes_redkitchen" and c.shake == ShakeSpec.parse("7:0-149")
    assert c.label == "7scenes_redkitchen:7:0-149"
    assert c.shake.folder_name(Path("d/7scenes_redkitchen")) == "7scenes_redkitchen_s7_f0-149_p0.6_y0.6_r0.8"
    t = ShakeClip.parse(" tum_fr1_rpy:3:0-149 ")
    assert (t.source, t.shake.seed, t.shake.first, t.shake.last) == ("tum_fr1_rpy", 3, 0, 149)
    assert t.shake.folder_name(Path("d/tum_fr1_rpy")) == "tum_fr1_rpy_s3_f0-149_p0.6_y0.6_r0.8"
    a = t.with_amplitudes((1.0, 0.0, 2.5))
    assert (a.source, a.shake.seed, a.shake.pitch, a.shake.yaw, a.shake.roll) == ("tum_fr1_rpy", 3, 1.0, 0.0, 2.5)
    for bad, says in (("a/b:3:0-9", "SRC a folder name"), (":3:0-9", "SRC a folder name"), ("..:3:0-9", "folder"),
                      ("x:7", r"\[SRC:\]SEED:FIRST-LAST"), ("tum:7:9-3", "0 <= FIRST <= LAST"), ("", "SEED")):
        with pytest.raises(ValueError, match=says):
            ShakeClip.parse(bad)


def test_degrade_flags_start_from_off():
    c = parse_degrade("oak=--stereo-k 0.006 --depth-lag 1 --blur 0.8")
    assert c.name == "oak" and not c.is_clean
    assert c.argv() == off_but(stereo_k="0.006", depth_lag="1", blur="0.8")
    assert parse_degrade("s='--shift' '4,-2.5'").argv() == off_but(shift="4,-2.5")
    assert parse_degrade("none=").argv() == OFF  # every effect off: a plain copy
    for bad, says in (("nameonly", "NAME="), ("=--blur 1", "NAME="), ("clean=--blur 1", "not 'clean'"),
                      ("a b=--blur 1", "cell name"), ("x=--seed 3", "unrecognized"), ("x=--frames 0-9", "unrecognized"),
                      ("x=--stereo 0.1", "unrecognized"),  # no abbreviations
                      ("x=--stereo-k -1", "--stereo-k"), ("x=--stereo-k nan", "--stereo-k"), ("x=--holes 1", "--holes"),
                      ("x=--shift 4", "--shift"), ("x=--depth-lag 0.5", "--depth-lag"), ("x=--jpeg 101", "--jpeg"),
                      ("x=--gain-jitter 1", "--gain-jitter"), ("x='--blur", "degrade cell x")):
        with pytest.raises(ValueError, match=says):
            parse_degrade(bad)


def test_the_grid_isolates_each_effect():
    cells = {c.name: c for c in grid_cells()}
    assert list(cells) == ["clean", "k006", "k012", "lag1", "blur1", "holes02", "shift42", "all"]
    assert cells["clean"].is_clean and cells["clean"].argv() == []
    assert cells["k006"].argv() == off_but(stereo_k="0.006")
    assert cells["k012"].argv() == off_but(stereo_k="0.012")
    assert cells["lag1"].argv() == off_but(depth_lag="1")
    assert cells["blur1"].argv() == off_but(blur="1")
    assert cells["holes02"].argv() == off_but(holes="0.2")
    assert cells["shift42"].argv() == off_but(shift="4,2")
    assert cells["all"].argv() == ["--stereo-k", "0.012", "--holes", "0.2", "--shift", "4,2", "--depth-lag", "1",
                                   "--blur", "1", "--gain-jitter", "0.03", "--jpeg", "75"]
    assert cells["k006"].folder_name("clip_s3", 3) == "clip_s3_deg_k0.006_h0_sh0,0_lag0_b0_g0_q0_seed3"


# --------------------------------------------------------------------------------------------
# degraded copies: made once, cached by their parameters


STAND_IN = "import json, os, shutil, sys\nsrc, out = sys.argv[1], sys.argv[2]\n"  # every stand-in script's start
LOG = "open(os.path.join(os.path.dirname(__file__), 'calls.txt'), 'a').write(' '.join(sys.argv[1:]) + '\\n')\n"
SHAKE = "ts = [ln.split()[0] for ln in open(os.path.join(src, 'rgb.txt')) if ln.strip() and ln[0] != '#']\n" \
        "open(os.path.join(out, 'shake.txt'), 'w').write(''.join(t + ' 0 0 0 1 0 0 0 0\\n' for t in ts))\n"
SCORE = "removed = [0.9, 0.8, 0.7, 0.75] if '--reference' in sys.argv else [0.5, 0.4, 0.3, 0.35]\n" \
        "print(json.dumps({'removed_fraction': removed, 'injected_hp_rms_deg': [0.5, 0.5, 0.7, 1.0]}))\n"
COPY = "shutil.copytree(src, out, dirs_exist_ok=True)\n"


def stand_in(folder: Path, **scripts: str) -> Path:
    """A tool folder of small scripts (name without .py -> body after STAND_IN)."""
    folder.mkdir(parents=True)
    for name, body in scripts.items():
        (folder / f"{name}.py").write_text(STAND_IN + body)
    return folder


def fake_shake_tool(folder: Path) -> Path:
    """inject.py copies the clip and writes a shake.txt; score_rotation.py prints a fixed score."""
    return stand_in(folder, inject=COPY + SHAKE, score_rotation=SCORE)


def fake_degrade_tool(folder: Path) -> Path:
    """degrade.py logs its argv and copies the clip (seed 666 fails)."""
    return stand_in(folder, degrade=LOG + "if sys.argv[sys.argv.index('--seed') + 1] == '666': sys.exit('boom')\n" + COPY)


def calls(tool: Path) -> list[list[str]]:
    path = tool / "calls.txt"
    return [ln.split() for ln in path.read_text().splitlines()] if path.exists() else []


def test_degraded_copies_are_cached_by_parameters(tmp_path):
    src = tmp_path / "clips" / "clip_s7"
    src.mkdir(parents=True)
    (src / "rgb.txt").write_text("0.0 rgb/0.png\n")
    (src / RECORD).write_text('{"spec": 1}')
    tool = fake_degrade_tool(tmp_path / "tool")
    cache = tmp_path / "clips"
    k006 = parse_degrade("k006=--stereo-k 0.006")
    folder, cmd = make_degraded(src, k006, 7, cache, tool)
    assert folder == cache / "clip_s7_deg_k0.006_h0_sh0,0_lag0_b0_g0_q0_seed7" and (folder / "rgb.txt").is_file()
    assert cmd[0] == sys.executable and cmd[-1] == "--force" and cmd[cmd.index("--seed") + 1] == "7"
    assert cmd[cmd.index("--seed") + 2:-1] == k006.argv()
    assert json.loads((folder / RECORD).read_text())["degrade"] == k006.argv()
    assert make_degraded(src, k006, 7, cache, tool) == (folder, None)  # cached
    assert make_degraded(src, parse_degrade("other=--stereo-k 0.006"), 7, cache, tool) == (folder, None)  # same values
    assert make_degraded(src, k006, 8, cache, tool)[1] is not None  # another seed: another copy
    (src / RECORD).write_text('{"spec": 2}')  # the source clip was made again differently
    assert make_degraded(src, k006, 7, cache, tool)[1] is not None
    (folder / RECORD).unlink()  # an interrupted copy is made again
    assert make_degraded(src, k006, 7, cache, tool)[1] is not None
    assert len(calls(tool)) == 4
    with pytest.raises(RuntimeError, match="boom"):
        make_degraded(src, k006, 666, cache, tool)
    assert not (cache / k006.folder_name(src.name, 666) / RECORD).exists()
    with pytest.raises(FileNotFoundError, match="--degrade-tool"):
        make_degraded(src, parse_degrade("b=--blur 1"), 7, cache, tmp_path / "nowhere")
    with pytest.raises(ValueError, match="clean"):
        make_degraded(src, DegradeCell("clean"), 7, cache, tool)


def test_every_cell_is_made_for_the_clip_and_its_reference_with_one_seed(tmp_path):
    data = tmp_path / "data"
    (data / "src").mkdir(parents=True)
    (data / "src" / "rgb.txt").write_text("0.0 rgb/0.png\n")
    shake, degrade = fake_shake_tool(tmp_path / "shake"), fake_degrade_tool(tmp_path / "degrade")
    cells = [DegradeCell("clean"), parse_degrade("k=--stereo-k 0.01"), parse_degrade("b=--blur 1")]
    clips = prepare_clips(data, ["src"], [ShakeClip.parse("src:5:0-0")], cells, tmp_path / "work", shake, degrade)
    assert [c.name for c in clips] == ["src", "src_s5_f0-0_p0.6_y0.6_r0.8",
                                       "src_s5_f0-0_p0.6_y0.6_r0.8_deg_k0.01_h0_sh0,0_lag0_b0_g0_q0_seed5",
                                       "src_s5_f0-0_p0.6_y0.6_r0.8_deg_k0_h0_sh0,0_lag0_b1_g0_q0_seed5"]
    assert clips[0].spec is None and clips[1].cell.is_clean and [c.cell.name for c in clips[2:]] == ["k", "b"]
    assert all(c.label == "src:5:0-0" and c.source == "src" for c in clips[1:])
    made = calls(degrade)
    assert len(made) == 4 and {m[m.index("--seed") + 1] for m in made} == {"5"}
    assert sorted(Path(m[0]).name for m in made) == sorted(["src_s5_f0-0_p0.6_y0.6_r0.8", "src_s5_f0-0_p0_y0_r0"] * 2)
    assert clips[2].reference.name == "src_s5_f0-0_p0_y0_r0_deg_k0.01_h0_sh0,0_lag0_b0_g0_q0_seed5"
    again = prepare_clips(data, ["src"], [ShakeClip.parse("src:5:0-0")], cells, tmp_path / "work", shake, degrade)
    assert len(calls(degrade)) == 4 and again[2].made["degrade"] == {"shaken": "cached", "reference": "cached"}


def test_real_degrade_tool_takes_the_cells_flags(tmp_path):
    from tests.unit.test_cli_motion import write_tum_clip

    tool = SHARED / "tools" / "degrade"
    if not (tool / "degrade.py").is_file():
        pytest.skip(f"{tool} not present")
    write_tum_clip(tmp_path / "clip", n=4)
    for c in grid_cells()[1:]:
        folder, cmd = make_degraded(tmp_path / "clip", c, 3, tmp_path / "cache", tool)
        rec = json.loads((folder / "degrade.json").read_text())
        assert rec["seed"] == 3 and rec["frames_written"] == 4, c.name
        got = [rec["stereo_k"], rec["holes"], rec["shift"], rec["depth_lag"], rec["blur"], rec["gain_jitter"], rec["jpeg"]]
        want = c.argv()[1::2]
        assert [str(g) if isinstance(g, str) else f"{g:g}" for g in got] == want, c.name


# --------------------------------------------------------------------------------------------
# which clips run: defaults skipped with a note, named ones required


def test_select_sources(tmp_path):
    (tmp_path / "tum_fr1_rpy").mkdir()
    real, shakes, notes = select_sources(tmp_path, None, None)
    assert real == ["tum_fr1_rpy"] and shakes == []
    assert any("7scenes_redkitchen skipped" in n for n in notes) and any("7:0-149" in n for n in notes)
    real, shakes, _ = select_sources(tmp_path, None, [ShakeClip.parse("tum_fr1_rpy:3:0-9")], no_shake=False)
    assert [s.label for s in shakes] == ["tum_fr1_rpy:3:0-9"]
    assert select_sources(tmp_path, ["tum_fr1_rpy"], None, no_shake=True)[:2] == (["tum_fr1_rpy"], [])
    with pytest.raises(SourceError, match="--real nope"):
        select_sources(tmp_path, ["tum_fr1_rpy", "nope"], None)
    with pytest.raises(SourceError, match="--clip nope:3:0-9"):
        select_sources(tmp_path, None, [ShakeClip.parse("nope:3:0-9")])
    with pytest.raises(SourceError, match="none of the clips"):
        select_sources(tmp_path / "empty", None, None)


@pytest.mark.parametrize("argv, says", [
    (["--real", "nope"], "--real nope"),
    (["--real", "a/b"], "--real"),
    (["--clip", "nope:3:0-9"], "--clip nope:3:0-9"),
    (["--clip", "a/b:3:0-9"], "--clip"),
    (["--degrade", "x=--stereo-k -1"], "--degrade"),
    (["--degrade", "x=--seed 1"], "--degrade"),
    (["--degrade", "k006=--blur 1", "--degrade-grid"], "--degrade: name(s) used twice: k006"),
    (["--no-shake", "--degrade-grid"], "--no-shake"),
    (["--degrade-grid", "--degrade-tool", "NOWHERE"], "--degrade-tool"),
])
def test_bench_quality_rejects_bad_sources_and_cells(argv, says, tmp_path, capsys):
    (tmp_path / "7scenes_redkitchen").mkdir()
    shake = fake_shake_tool(tmp_path / "shake")
    argv = [str(tmp_path / "nowhere") if a == "NOWHERE" else a for a in argv]
    try:
        code = main(["bench", "quality", "--data", str(tmp_path), "--work", str(tmp_path / "w"),
                     "--shake-tool", str(shake), *argv])
    except SystemExit as e:
        code = e.code
    assert code == 2
    assert says in capsys.readouterr().err
    assert not (tmp_path / "w" / "clips").exists()  # refused before any work


# --------------------------------------------------------------------------------------------
# ours' frames not corrected, by how their motion was known


def test_correction_counts():
    counts = quality.CorrectionCounts()
    for valid, motion in ((True, "fit"), (True, "fit"), (False, "restart"), (True, "rotation"), (True, "bridge"),
                          (True, "fit"), (False, "restart"), (True, "something new")):
        counts.add(SimpleNamespace(valid=valid, motion=motion))
    d = counts.as_dict()
    assert d["uncorrected"] == 2
    assert d["motion_kinds"] == {"fit": 3, "restart": 2, "rotation": 1, "bridge": 1, "something new": 1}
    assert list(d["motion_kinds"])[:2] == ["fit", "restart"]  # most frames first
    assert quality.CorrectionCounts().as_dict() == {"uncorrected": 0, "motion_kinds": {}}


def method(jpx: float, jdeg: float, **kw: object) -> dict:
    return {"status": "ok", "jitter_px": jpx, "jitter_deg": jdeg, "cropping": 0.9, "border_free_cropping": 0.85,
            "distortion": 0.97, "stability": 0.8, "ms_per_frame": 5.0, "failed": False, **kw}


def made_up_clip(cell: str, deshake_failed: bool) -> dict:
    nan = float("nan")
    return {
        "name": f"src_s3_f0-9_p0.6_y0.6_r0.8{'' if cell == 'clean' else '_deg_' + cell}", "frames": 10,
        "size": "64x48", "fps": 30.0, "known_shake": "src:3:0-9",
        "shake": {"seed": 3, "first": 0, "last": 9, "pitch": 0.6, "yaw": 0.6, "roll": 0.8},
        "degrade": {"cell": cell, "argv": [] if cell == "clean" else off_but(blur="1")},
        "methods": {
            "ours": method(0.5, 0.05, uncorrected=2, motion_kinds={"fit": 7, "restart": 2, "rotation": 1}),
            "ours [lp0]": method(0.1, 0.01, uncorrected=0, motion_kinds={"fit": 10}),
            "vid.stab 2-pass (ffmpeg)": method(0.4, 0.09),
            "deshake (ffmpeg)": method(0.2, 0.5, failed=deshake_failed, failure_reason="frame 4: only 3 matches (< 20)"),
            "vidstab (python)": {"status": "not run", "reason": "vidstab does not import"},
            "vidgear Stabilizer": method(0.3, nan),
            "LK moving average": method(0.9, 0.02),
            "input (unstabilized)": method(0.01, 0.001),
        },
        "shake_removed": {"ours": {"with_reference": {"removed_fraction": [0.9, 0.8, 0.7, 0.75]},
                                   "without_reference": {"removed_fraction": [0.5, 0.4, 0.3, 0.35],
                                                         "injected_hp_rms_deg": [0.5, 0.5, 0.7, 1.0]}}},
    }


def test_robustness_grid_and_its_table():
    r = {"clips": [{"name": "src", "frames": 10, "methods": {}}, made_up_clip("clean", False),
                   made_up_clip("blur1", True)]}
    rows = robustness_rows(r)
    assert [(x["clip"], x["cell"]) for x in rows] == [("src:3:0-9", "clean"), ("src:3:0-9", "blur1")]
    clean, blur = rows
    # best = lowest, per column separately; never ours, a variant or the input
    assert clean["best_peer"]["jitter_px"] == {"method": "deshake (ffmpeg)", "value": 0.2}
    assert clean["best_peer"]["jitter_deg"] == {"method": "LK moving average", "value": 0.02}
    assert blur["best_peer"]["jitter_px"] == {"method": "vidgear Stabilizer", "value": 0.3}  # deshake failed
    assert set(clean["peers_not_scored"]) == {"vidstab (python)", "vidgear Stabilizer"}
    assert clean["peers_not_scored"]["vidgear Stabilizer"] == "jitter_deg is NaN"
    assert blur["peers_not_scored"]["deshake (ffmpeg)"].startswith("scorer failed: frame 4")
    assert clean["ours"]["uncorrected"] == 2 and clean["removed_with_reference"] == [0.9, 0.8, 0.7, 0.75]
    text = format_robustness(rows)
    lines = text.splitlines()
    assert lines[0].startswith("robustness") and "best peer px" in lines[1] and "uncorr" in lines[1]
    assert lines[2].split()[:7] == ["src:3:0-9", "clean", "0.500", "0.200", "deshake", "0.0500", "0.0200"]
    assert "   90.0%    80.0%    70.0%    75.0%  " in lines[2] and lines[2].endswith("vidstab.py, vidgear")
    assert lines[3].split()[:5] == ["src:3:0-9", "blur1", "0.500", "0.300", "vidgear"]
    assert "deshake" in lines[3].split("%")[-1]
    assert any("blur1: deshake (ffmpeg): scorer failed: frame 4" in ln for ln in lines[4:])
    assert any("vidstab (python): not run: vidstab does not import" in ln for ln in lines[4:])
    # the whole report: robustness after the clip tables, uncorrected and fallbacks in each table
    r.update(robustness=rows, versions={}, settings={"notes": ["default real clip x skipped"],
                                                   "degrade_cells": {"blur1": off_but(blur="1")}})
    r["clips"] = r["clips"][1:]
    full = quality_tables.format_tables(r)
    assert full.index("robustness:") > full.rindex("LK moving average")
    assert "uncorrect." in full
    assert "  ours: frames by motion: fit 7, restart 2, rotation 1; reached over 0; lifted loose 0; not corrected 2" in full
    assert "note: default real clip x skipped" in full and "degrade cell blur1: degrade.py --seed SEED" in full
    json.dumps(r, default=quality_tables.json_default)


def test_a_no_peer_cell_shows_dashes():
    clip = made_up_clip("blur1", True)
    clip["methods"] = {k: v for k, v in clip["methods"].items() if not is_peer(k)}  # --no-baselines
    clip.pop("shake_removed")
    row = robustness_rows({"clips": [clip]})[0]
    assert row["best_peer"] == {"jitter_px": None, "jitter_deg": None} and row["removed_with_reference"] is None
    line = format_robustness([row]).splitlines()[2]
    assert line.count(" - ") >= 2 and line.endswith("-")


# --------------------------------------------------------------------------------------------
# a small run through stand-in tools: every method on every cell, the JSON complete


def test_run_with_a_degrade_cell_through_stand_in_tools(tmp_path):
    from tests.unit.test_cli_motion import write_tum_clip

    write_tum_clip(tmp_path / "data" / "src", n=10)
    cfg = quality.QualityConfig(data=tmp_path / "data", frames=8, real=["src"], clips=[ShakeClip.parse("src:2:0-9")],
                                shake_tool=fake_shake_tool(tmp_path / "shake"),
                                degrade=[parse_degrade("b=--blur 1")],
                                degrade_tool=fake_degrade_tool(tmp_path / "degrade"), work=tmp_path / "work",
                                baselines=False, notes=["a note"])
    r = quality.run(cfg)
    assert [c.get("degrade", {}).get("cell") for c in r["clips"]] == [None, "clean", "b"]
    s = r["settings"]
    assert s["real"] == ["src"] and s["clips"] == ["src:2:0-9"] and s["notes"] == ["a note"]
    assert s["degrade_cells"] == {"b": off_but(blur="1")} and s["degrade_tool"] == str(tmp_path / "degrade")
    for c in r["clips"]:
        assert set(c["methods"]) == {"ours", "input (unstabilized)"}
        ours = c["methods"]["ours"]
        assert ours["uncorrected"] >= 0 and sum(ours["motion_kinds"].values()) == ours["frames_out"] == 8
    degraded = r["clips"][2]
    assert degraded["made"]["degrade"]["shaken"][-1] == "--force" and degraded["source"] == "src"
    assert [(x["clip"], x["cell"]) for x in r["robustness"]] == [("src:2:0-9", "clean"), ("src:2:0-9", "b")]
    assert r["robustness"][1]["removed_with_reference"] == [0.9, 0.8, 0.7, 0.75]
    ref_run = degraded["shake_removed"]["ours"]["reference_run"]
    assert ref_run["frames_out"] == 8 and sum(ref_run["motion_kinds"].values()) == 8
    text = quality_tables.format_tables(r)
    assert "robustness:" in text and "degrade cell b: " in text and "ours on the unshaken reference: frames by" in text
    json.dumps(r, default=quality_tables.json_default)
    shutil.rmtree(tmp_path / "work")


def test_with_the_peers_ours_also_runs_bordered_and_the_grid_shows_it():
    """Peers that show black borders are compared like for like: ours leaving borders too (no budget,
    zoom or fill); the robustness table shows it beside ours, '-' where it did not run."""
    from quick_stream.cli import build_parser
    from quick_stream.cli.bench_quality_cmd import ours_variants

    parse = build_parser().parse_args
    names = [v.name for v in ours_variants(parse(["bench", "quality"]))]
    assert names == ["bordered"]
    p = ours_variants(parse(["bench", "quality"]))[0].params
    assert p.planner.budget.max_zoom == 0 and p.framing.mode == "black"
    assert ours_variants(parse(["bench", "quality", "--no-baselines"])) == []
    mine = ours_variants(parse(["bench", "quality", "--variant", "bordered=--max-zoom 1.3"]))
    assert [v.name for v in mine] == ["bordered"] and mine[0].params.planner.budget.max_zoom == 1.3
    clip = made_up_clip("clean", False)
    clip["methods"]["ours [bordered]"] = method(0.15, 0.012)
    rows = robustness_rows({"clips": [clip, made_up_clip("blur1", False)]})
    assert rows[0]["ours_bordered"] == {"jitter_px": 0.15, "jitter_deg": 0.012} and rows[1]["ours_bordered"] is None
    lines = format_robustness(rows).splitlines()
    assert "bordered px / deg" in lines[1]
    assert lines[2].split()[7:11] == ["LK", "avg", "0.150", "0.0120"]
    assert lines[3].split()[7:10] == ["LK", "avg", "-"]

"""Settings as data (docs/settings.md): the tree to TOML/JSON and back, strict checks naming the key,
the precedence defaults/recording < --settings FILE < flags, and the settings record of a recording."""
from __future__ import annotations

import argparse
import dataclasses
import json
import struct
from pathlib import Path

import pytest

from quick_stream.cli import main as cli_main
from quick_stream.core.settings import SettingsError, settings_dict, settings_digest, settings_from_dict
from quick_stream.core.stabilizer import StabilizerParams
from quick_stream.io.recording import Recorder, recover
from quick_stream.io.settings_file import (RECORD_NAME, load_settings_file, recorded_settings, recording_settings,
                                           settings_record, settings_toml)
from quick_stream.io.stabilizer_flags import add_stabilizer_args, default_settings, stabilizer_params
from quick_stream.io.stream_recording import StreamRecording


def flags(*argv: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    add_stabilizer_args(p)
    return p.parse_args(list(argv))


def unusual() -> StabilizerParams:
    """Settings off every default, with floats whose text is long (0.1 + 0.2) and a tuple."""
    p = stabilizer_params(flags("--group", "sim3", "--latency", "low", "--path", "ep", "--path-weights",
                                "1,2,3,4,5,6,7", "--max-zoom", "1.3", "--fill-frames", "3"))
    return dataclasses.replace(p, flow=dataclasses.replace(p.flow, fb_threshold_px=0.1 + 0.2, max_points=1234),
                               warp=dataclasses.replace(p.warp, grid=(3, 2), alpha=1e-7))


@pytest.mark.parametrize("make", [default_settings, unusual, StabilizerParams])
def test_toml_and_json_read_back_as_the_same_tree_bit_for_bit(make, tmp_path: Path):
    params = make()
    f = tmp_path / "s.toml"
    f.write_text(settings_toml(params, "a header\nof two lines"))
    assert load_settings_file(f, base=StabilizerParams()) == params
    assert load_settings_file(f, base=unusual()) == params  # the file sets every key: the base does not show
    j = tmp_path / "s.json"
    j.write_text(json.dumps(settings_dict(params)))
    assert load_settings_file(j) == params
    assert settings_from_dict(json.loads(settings_record(params)["settings"])) == params


def test_a_file_changes_only_the_keys_it_holds(tmp_path: Path):
    f = tmp_path / "s.toml"
    f.write_text("[planner.keyframes]\ninterval = 20\n\n[warp]\nalpha = 1\n")
    base = unusual()
    got = load_settings_file(f, base)
    assert got.planner.keyframes.interval == 20 and got.warp.alpha == 1.0 and isinstance(got.warp.alpha, float)
    want = dataclasses.replace(base, planner=dataclasses.replace(
        base.planner, keyframes=dataclasses.replace(base.planner.keyframes, interval=20)),
        warp=dataclasses.replace(base.warp, alpha=1.0))
    assert got == want


@pytest.mark.parametrize("text, named", [
    ("[planner]\nlookahed = 3\n", "planner.lookahed: unknown setting"),
    ("[nope]\nx = 1\n", "nope: unknown setting"),
    ("[planner.keyframes]\ninterval = 'thirty'\n", "planner.keyframes.interval: expected an integer, got 'thirty'"),
    ("[planner.keyframes]\ninterval = 2.5\n", "planner.keyframes.interval: expected an integer"),
    ("[flow]\nfb_check = 1\n", "flow.fb_check: expected true or false"),
    ("[warp]\ngrid = [2]\n", "warp.grid: expected 2 values, got 1"),
    ("[warp]\ngrid = [2, 'x']\n", "warp.grid[1]: expected an integer"),
    ("planner = 3\n", "planner: expected a table of settings"),
    ("[motion]\ngroup = 'sim3'\n", "motion.group/planner.group"),
    ("[motion]\ngroup = 'so3'\n[planner]\ngroup = 'so3'\n", "motion:"),
    ("[planner]\nlookahead = 40\n", "planner: look-ahead must be >= 0 and below the keyframe interval"),
    ("[planner.path]\nweights = [1, 2]\n", "planner.path.weights: path weights must be 6 positive numbers"),
    ("[planner]\nlowpass_sigma = -1.0\n", "planner.lowpass_sigma: must be a finite number >= 0"),
    ("[framing]\ncrop_zoom = 0.5\n", "framing:"),
    ("[flow\n", "not valid TOML"),
])
def test_a_bad_file_is_an_error_naming_the_file_and_the_key(tmp_path: Path, text: str, named: str):
    f = tmp_path / "bad.toml"
    f.write_text(text)
    with pytest.raises(SettingsError) as e:
        load_settings_file(f)
    assert str(e.value).startswith(f"{f}: ") and named in str(e.value), str(e.value)


def test_files_that_are_not_settings_files_are_named(tmp_path: Path):
    for name, data, named in [("s.yaml", b"a: 1", "a settings file is .toml or .json"),
                              ("s.json", b"[1, 2]", "expected a table of settings"),
                              ("s.json", b"{", "not valid JSON"),
                              ("s.toml", b"\xff\xfe", "not UTF-8 text"),
                              ("missing.toml", None, "cannot read")]:
        f = tmp_path / name
        if data is not None:
            f.write_bytes(data)
        with pytest.raises(SettingsError, match=named):
            load_settings_file(f)


def test_no_flags_give_the_product_defaults_and_the_flags_keep_their_meaning():
    assert stabilizer_params(flags()) == default_settings()
    d = default_settings()
    assert (d.framing.mode, d.framing.max_zoom, d.planner.keyframes.interval, d.planner.lookahead) == ("auto", 1.25, 30, 15)
    low = stabilizer_params(flags("--latency", "0.5s"))
    assert (low.planner.keyframes.interval, low.planner.lookahead, low.planner.smoothness) == (15, 10, 3000.0)
    assert low.planner.keyframes.min_interval == 10
    # the presets are named by their delay at 30 fps; the earlier names still mean the same
    assert stabilizer_params(flags("--latency", "low")) == low
    assert stabilizer_params(flags("--latency", "normal")) == stabilizer_params(flags("--latency", "1s")) == d
    with pytest.raises(SystemExit):
        flags("--latency", "2s")
    k = stabilizer_params(flags("--keyframe-interval", "20"))  # between the 0.5s and 1s presets' windows
    assert (k.planner.keyframes.interval, k.planner.lookahead, k.planner.keyframes.min_interval) == (20, 12, 10)
    assert 3000.0 < k.planner.smoothness < 1e4
    k = stabilizer_params(flags("--keyframe-interval", "20", "--lookahead", "5", "--smoothness", "50"))
    assert (k.planner.lookahead, k.planner.smoothness) == (5, 50.0)  # given wins
    g = stabilizer_params(flags("--group", "ga3"))
    assert g.motion.group == g.planner.group == "ga3"
    nofill = stabilizer_params(flags("--fill-frames", "0"))
    assert (nofill.framing.fill_frames, nofill.planner.budget.fill, nofill.planner.budget.fill_reach) == (0, 0.0, 0)
    nobudget = stabilizer_params(flags("--max-zoom", "0"))
    assert nobudget.planner.budget.max_zoom == 0 and nobudget.framing.max_zoom > 1


def test_a_window_given_alone_takes_the_look_ahead_and_smoothness_between_the_presets():
    from quick_stream.core.params import LATENCY_PRESETS, window_settings

    for interval, lookahead, smoothness in LATENCY_PRESETS.values():  # a preset's own window: the preset
        assert window_settings(interval) == (lookahead, smoothness)
        p = stabilizer_params(flags("--keyframe-interval", str(interval)))
        assert (p.planner.lookahead, p.planner.smoothness) == (lookahead, smoothness)
    got = [window_settings(n) for n in range(1, 91)]
    lam = [x[1] for x in got]
    assert all(b > a for a, b in zip(lam, lam[1:]))  # a longer window smooths more
    assert all(0 <= la < max(n, 2) for n, (la, _) in zip(range(1, 91), got))  # a look-ahead is inside its window
    assert got[59] == (30, 1e4 * 8)  # beyond the presets: the nearest one's share, lambda with the window cubed


def test_flags_override_the_file_which_overrides_the_recording(tmp_path: Path):
    recorded = stabilizer_params(flags("--group", "sim3", "--crop-zoom", "1.3", "--fill-band", "0.05"))
    f = tmp_path / "s.toml"
    f.write_text("[framing]\ncrop_zoom = 1.2\nmode = 'crop'\n\n[planner.budget]\nmax_zoom = 1.25\n")
    got = stabilizer_params(flags("--settings", str(f), "--crop-zoom", "1.1"), recorded=recorded)
    assert got.framing.crop_zoom == 1.1  # flag over file
    assert got.framing.mode == "crop" and got.planner.budget.max_zoom == 1.25  # file over recording
    assert got.motion.group == "sim3" and got.planner.budget.fill == 0.05  # the recording's, untouched
    assert stabilizer_params(flags(), recorded=recorded) == recorded


def test_a_bad_flag_is_named_after_the_file(tmp_path: Path):
    f = tmp_path / "s.toml"
    f.write_text("[planner]\nlookahead = 6\n\n[planner.keyframes]\ninterval = 12\n")
    assert stabilizer_params(flags("--settings", str(f))).planner.lookahead == 6
    with pytest.raises(ValueError, match="--lookahead/--smoothness: look-ahead must be"):
        stabilizer_params(flags("--settings", str(f), "--lookahead", "12"))
    with pytest.raises(ValueError, match="--lowpass-sigma: must be a finite number"):
        stabilizer_params(flags("--lowpass-sigma", "nan"))


def test_the_digest_changes_with_any_setting():
    a, b = default_settings(), default_settings()
    assert settings_digest(a) == settings_digest(b) and len(settings_digest(a)) == 12
    c = dataclasses.replace(a, continuity=dataclasses.replace(a.continuity, confirm=6))
    assert settings_digest(c) != settings_digest(a)


def test_every_file_of_a_split_recording_starts_with_its_settings_record(tmp_path: Path):
    params = unusual()
    out = tmp_path / "rec.mcap"
    with StreamRecording(str(out), settings=settings_record(params), split_mb=0.001) as rec:
        for i in range(6):  # each big enough to split the recording
            rec.files.rec.write("quick/@v1/cam0/raw", bytes(2000))
            rec.files.wrote(2000)
    files = sorted(tmp_path.glob("rec*.mcap"))
    assert len(files) >= 3
    assert all(recording_settings(f) == params for f in files)


def test_the_settings_record_survives_a_kill_and_recover(tmp_path: Path):
    params = unusual()
    torn = tmp_path / "torn.mcap"
    rec = Recorder(torn)
    rec.metadata(RECORD_NAME, settings_record(params))
    for i in range(3):
        rec.write("quick/@v1/cam0/raw", struct.pack("<i", i))
    rec.flush()
    rec.abandon()  # no footer, as after SIGKILL
    assert recording_settings(torn) == params  # read by streaming
    recover(torn, tmp_path / "fixed.mcap")
    assert recording_settings(tmp_path / "fixed.mcap") == params  # and through the index


def test_a_recording_without_the_record_has_none_and_a_damaged_record_is_named(tmp_path: Path):
    plain = tmp_path / "plain.mcap"
    with Recorder(plain) as rec:
        rec.write("quick/@v1/cam0/raw", b"x")
    assert recorded_settings(plain) is None and recording_settings(plain) is None
    bad = tmp_path / "bad.mcap"
    with Recorder(bad) as rec:
        rec.metadata(RECORD_NAME, {"version": "1", "settings": json.dumps({"planner": {"nope": 1}})})
    with pytest.raises(Exception, match=f"{bad}: its settings record: planner.nope: unknown setting"):
        recording_settings(bad)


def test_settings_show_prints_a_settings_file_and_names_a_bad_one(tmp_path: Path, capsys):
    assert cli_main(["settings", "show", "--group", "sa3"]) == 0
    printed = capsys.readouterr().out
    assert cli_main(["settings", "show", "--output", str(tmp_path / "s.toml"), "--group", "sa3"]) == 0
    assert capsys.readouterr().out == "" and printed == (tmp_path / "s.toml").read_text()
    assert load_settings_file(tmp_path / "s.toml") == stabilizer_params(flags("--group", "sa3"))
    assert cli_main(["config", "show", "--settings", str(tmp_path / "s.toml"), "--json", "-"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["settings"]["motion"]["group"] == "sa3" and doc["digest"] == settings_digest(
        stabilizer_params(flags("--group", "sa3")))
    (tmp_path / "bad.toml").write_text("[warp]\nalpah = 1\n")
    assert cli_main(["settings", "show", "--settings", str(tmp_path / "bad.toml")]) == 2
    err = capsys.readouterr().err
    assert f"{tmp_path / 'bad.toml'}: warp.alpah: unknown setting" in err


def test_the_environment_names_the_file_when_no_flag_does(tmp_path: Path, monkeypatch):
    a, b = tmp_path / "a.toml", tmp_path / "b.toml"
    a.write_text("[warp]\nalpha = 0.3\n")
    b.write_text("[warp]\nalpha = 0.4\n")
    monkeypatch.setenv("QUICK_STREAM_SETTINGS", str(a))
    assert stabilizer_params(flags()).warp.alpha == 0.3
    assert stabilizer_params(flags("--settings", str(b))).warp.alpha == 0.4  # the flag wins
    a.write_text("[warp]\nalpha = 'x'\n")
    with pytest.raises(SettingsError, match=f"QUICK_STREAM_SETTINGS={a}: warp.alpha: expected a number"):
        stabilizer_params(flags())


@pytest.mark.parametrize("argv, named", [(("--max-zoom", "0.5"), "--max-zoom/--fill-band: max zoom"),
                                         (("--smoothness", "-1"), "--lookahead/--smoothness: smoothness")])
def test_a_bad_flag_value_is_blamed_on_its_own_flag(argv, named):
    """The planner's check also checks the crop budget: a bad --max-zoom was blamed on --lookahead/--smoothness."""
    with pytest.raises(ValueError) as e:
        stabilizer_params(flags(*argv))
    assert str(e.value).startswith(named), e.value


def test_settings_show_output_writes_the_file_and_says_only_where(tmp_path, capsys):
    out = tmp_path / "s.toml"
    assert cli_main(["settings", "show", "--output", str(out)]) == 0
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.strip() == f"wrote {out}"
    assert out.read_text().startswith("# quick-stream settings ")


@pytest.mark.parametrize("argv, usage", [(["stabilize", "--bogus"], "usage: quick-stream stabilize"),
                                         (["bench", "pipeline", "--bogus"], "usage: quick-stream bench pipeline"),
                                         (["settings", "show", "--bogus"], "usage: quick-stream settings show")])
def test_a_mistyped_flag_is_refused_with_its_commands_usage(argv, usage, capsys):
    with pytest.raises(SystemExit) as e:
        cli_main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.startswith(usage) and "unrecognized arguments: --bogus" in err, err

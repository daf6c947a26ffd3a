"""Pieces of ``quick-stream bench quality`` (the benchmark itself is run by hand, not here).

The LK moving-average baseline on a small synthetic clip with known shake, the peers' output
alignment, the shake-clip specs and cache, ours' settings and variants, the correction file
format (through the shake tool's own reader when ../shared is present), and a small end-to-end
run of one clip.
"""
from __future__ import annotations

import importlib.util
import json
import math
import sys
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from quick_stream.bench import lk_average, peers, quality, quality_tables, variants
from quick_stream.bench.shake_clips import (ShakeSpec, is_cached, make_clip, parse_amplitudes, read_corrections,
                                            rotation_part, seconds_text, write_corrections)
from quick_stream.cli import main
from quick_stream.quality.metrics import evaluate_sequence

SHARED = Path(__file__).resolve().parents[3] / "shared"
W, H = 256, 192


@lru_cache(maxsize=1)
def texture() -> np.ndarray:
    rng = np.random.default_rng(3)
    acc = np.zeros((500, 640), np.float32)
    for sigma, weight in ((1.5, 0.6), (4.0, 1.0), (10.0, 1.5)):
        acc += weight * sigma * cv2.GaussianBlur(rng.normal(0, 1, acc.shape).astype(np.float32), (0, 0), sigma)
    grey = np.clip(128 + 45 * (acc - acc.mean()) / acc.std(), 20, 255).astype(np.uint8)
    return cv2.merge([grey, np.roll(grey, 7, axis=1), np.roll(grey, 5, axis=0)])


def shaken_clip(n: int, shake_px: float, shake_deg: float, seed: int = 2) -> list[np.ndarray]:
    """A slow pan across the texture plus i.i.d. per-frame translation and rotation shake."""
    tex = texture()
    rng = np.random.default_rng(seed)
    t = np.arange(n)
    x = 1.5 * t + rng.uniform(-shake_px, shake_px, n)
    y = 0.5 * t + rng.uniform(-shake_px, shake_px, n)
    a = rng.uniform(-shake_deg, shake_deg, n)
    out = []
    for i in range(n):
        c = (200 + x[i], 150 + y[i])
        M = cv2.getRotationMatrix2D(c, a[i], 1.0)
        M[:, 2] += np.array([(W - 1) / 2, (H - 1) / 2]) - np.array(c)
        out.append(cv2.warpAffine(tex, M, (W, H), flags=cv2.INTER_CUBIC))
    return out


# --------------------------------------------------------------------------------------------
# LK moving-average baseline


def test_lk_moving_average_removes_known_shake():
    frames = shaken_clip(36, shake_px=3.0, shake_deg=0.6)
    out = lk_average.stabilize(frames)
    assert len(out) == len(frames) and all(o.shape == f.shape for o, f in zip(out, frames))
    m = evaluate_sequence(frames, out, 30.0)
    assert not m.failed
    assert m.input_jitter_px > 1.5
    assert m.jitter_px < 0.4 * m.input_jitter_px
    assert m.jitter_deg < 0.5 * m.input_jitter_deg


def test_pixel_jitter_made_border_free_grows_by_the_crop():
    """A method that leaves black borders must crop them away to be border-free: its pixel jitter then
    grows by 1 / its border-free scale (quality_scoring); a border-free method's stays as it is."""
    from quick_stream.bench.quality_scoring import score_frames

    frames = shaken_clip(24, shake_px=3.0, shake_deg=0.6)
    out = lk_average.stabilize(frames)  # black borders where it moved the frames
    r = score_frames(frames, out, 30.0)
    assert 0 < r["border_free_scale"] < 1
    assert r["jitter_px_border_free"] == pytest.approx(r["jitter_px"] / r["border_free_scale"])
    same = score_frames(frames, frames, 30.0)
    assert same["border_free_scale"] == 1.0 and same["jitter_px_border_free"] == same["jitter_px"]
    # the least jitter a border-free output at that cropping can have (docs/method.md 6.3): the LK average
    # cropped border-free is such an output; the input (cropping ~1, no room) is at its own bound
    assert 0 <= r["jitter_bound_px"] <= r["jitter_px_border_free"] and 0 <= r["jitter_bound_deg"] <= r["jitter_deg"]
    assert r["jitter_bound_px"] < 0.5 * same["jitter_px"]
    assert same["jitter_bound_px"] == pytest.approx(same["jitter_px"], rel=0.05)


def test_lk_moving_average_pieces():
    assert np.allclose(lk_average.moving_average(np.arange(10.0), 2)[2:-2], np.arange(10.0)[2:-2])
    assert np.allclose(lk_average.moving_average(np.ones(5), 15), 1.0)  # ends padded with the end values
    f = shaken_clip(2, 0.0, 0.0)[0]
    assert lk_average.pair_motion(np.zeros((H, W), np.uint8), np.zeros((H, W), np.uint8)) is None
    assert np.array_equal(lk_average.warp(f, 0.0, 0.0, 0.0), f)
    assert lk_average.stabilize([]) == []


# --------------------------------------------------------------------------------------------
# peers: vidstab and vidgear hand back frame k for input k


def coded_frames(n: int) -> list[np.ndarray]:
    """Identical texture, frame index coded in the red channel: the peers' warps stay ~identity."""
    grey = cv2.resize(texture()[:, :, 0], (128, 96))
    grey = cv2.normalize(grey, None, 40, 160, cv2.NORM_MINMAX)
    return [cv2.merge([grey, grey, np.full_like(grey, 40 + 2 * k)]) for k in range(n)]


def decode(frame: np.ndarray) -> int:
    return int(round((float(np.median(frame[30:66, 40:88, 2])) - 40) / 2))


@pytest.mark.peers
@pytest.mark.parametrize("name", ["vidstab", "vidgear"])
def test_peer_outputs_are_aligned_with_inputs(name):
    assert not peers.available()[name], peers.available()[name]  # `pytest -m peers` needs the extra
    frames = coded_frames(70)
    run = peers.run_vidstab(frames) if name == "vidstab" else peers.run_vidgear(frames)
    assert len(run.frames) == len(frames)
    assert [decode(o) for o in run.frames] == list(range(len(frames)))
    assert all(o.shape == frames[0].shape and o.dtype == np.uint8 for o in run.frames)
    assert run.seconds >= 0 and run.notes


@pytest.mark.peers
def test_vidstab_shim_leaves_cv2_alone():
    assert not peers.available()["vidstab"], peers.available()["vidstab"]
    had = hasattr(cv2, "BRISK_create")
    peers.import_vidstab()
    assert hasattr(cv2, "BRISK_create") == had


# --------------------------------------------------------------------------------------------
# shake clips: specs, cache


def test_shake_spec_parsing_and_names():
    s = ShakeSpec.parse("7:0-149")
    assert (s.seed, s.first, s.last, s.pitch, s.yaw, s.roll) == (7, 0, 149, 0.6, 0.6, 0.8)
    assert s.inject_args() == ["--seed", "7", "--frames", "0-149", "--pitch", "0.6", "--yaw", "0.6", "--roll", "0.8"]
    r = s.reference()
    assert (r.seed, r.frames, r.pitch, r.yaw, r.roll) == (7, "0-149", 0.0, 0.0, 0.0)
    assert s.folder_name(Path("x/7scenes")) == "7scenes_s7_f0-149_p0.6_y0.6_r0.8"
    assert r.folder_name(Path("x/7scenes")) == "7scenes_s7_f0-149_p0_y0_r0"
    assert ShakeSpec.parse(" 11:100-249 ", (1.0, 0.0, 2.5)).roll == 2.5
    for bad in ("7", "7:0", "a:0-9", "7:9-3", "7:-1-5", "7:0-x", ""):
        with pytest.raises(ValueError):
            ShakeSpec.parse(bad)
    assert parse_amplitudes("0.6,0.6,0.8") == (0.6, 0.6, 0.8)
    for bad in ("1,2", "1,2,x", "1,-2,3", "1,nan,3"):
        with pytest.raises(ValueError):
            parse_amplitudes(bad)


def fake_tool(folder: Path) -> Path:
    """A stand-in shake tool: inject.py copies rgb.txt and logs its argv (counts the calls)."""
    folder.mkdir(parents=True)
    (folder / "inject.py").write_text(
        "import sys, os, shutil\n"
        "src, out = sys.argv[1], sys.argv[2]\n"
        "os.makedirs(out, exist_ok=True)\n"
        "shutil.copy(os.path.join(src, 'rgb.txt'), out)\n"
        "open(os.path.join(os.path.dirname(__file__), 'calls.txt'), 'a').write(' '.join(sys.argv[3:]) + '\\n')\n"
        "if '--seed' in sys.argv and sys.argv[sys.argv.index('--seed') + 1] == '666': sys.exit('boom')\n")
    (folder / "score_rotation.py").write_text("")
    return folder


def test_made_clips_are_cached_by_parameters(tmp_path):
    src = tmp_path / "data" / "clip"
    src.mkdir(parents=True)
    (src / "rgb.txt").write_text("0.0 rgb/0.png\n")
    tool = fake_tool(tmp_path / "tool")
    cache = tmp_path / "cache"
    spec = ShakeSpec.parse("7:0-9")
    folder, cmd = make_clip(src, spec, cache, tool)
    assert cmd is not None and cmd[0] == sys.executable and "--force" in cmd and "7" in cmd
    assert folder == cache / "clip_s7_f0-9_p0.6_y0.6_r0.8" and (folder / "rgb.txt").is_file()
    assert is_cached(folder, spec, src)
    again, cmd2 = make_clip(src, spec, cache, tool)
    assert again == folder and cmd2 is None
    ref, cmd3 = make_clip(src, spec.reference(), cache, tool)
    assert ref != folder and cmd3 is not None and "--pitch" in cmd3 and cmd3[cmd3.index("--pitch") + 1] == "0.0"
    assert len((tool / "calls.txt").read_text().splitlines()) == 2
    (folder / "bench-clip.json").unlink()  # an interrupted clip is made again
    _, cmd4 = make_clip(src, spec, cache, tool)
    assert cmd4 is not None
    assert not is_cached(folder, ShakeSpec.parse("7:0-9", (0.6, 0.6, 0.9)), src)
    with pytest.raises(RuntimeError, match="boom"):
        make_clip(src, ShakeSpec.parse("666:0-9"), cache, tool)
    assert not is_cached(cache / ShakeSpec.parse("666:0-9").folder_name(src), ShakeSpec.parse("666:0-9"), src)
    with pytest.raises(FileNotFoundError, match="inject.py"):
        make_clip(src, ShakeSpec.parse("8:0-9"), cache, tmp_path / "nowhere")


# --------------------------------------------------------------------------------------------
# ours: the default settings are stabilize's, variants use the same flags


def test_default_settings_are_those_of_stabilize_without_flags():
    from quick_stream.cli import build_parser
    from quick_stream.io.stabilizer_flags import stabilizer_params

    args = build_parser().parse_args(["stabilize"])
    assert variants.default_settings().params == stabilizer_params(args)
    assert variants.default_settings().argv == []


def test_variants_parse_like_stabilize_flags():
    v = variants.parse_variant("ga3-id=--group ga3 --end identity")
    assert v.name == "ga3-id" and v.argv == ["--group", "ga3", "--end", "identity"]
    assert v.params.motion.group == "ga3" and v.params.planner.end == "identity"
    q = variants.parse_variant("lp0='--lowpass-sigma' 0")
    assert q.params.planner.lowpass_sigma == 0.0
    assert variants.parse_variant("plain=").params == variants.default_settings().params
    for bad, what in (("nogroup", "NAME="), ("=--group se3", "NAME="), ("ours=--group se3", "not 'ours'"),
                      ("x y=--group se3", "variant name"), ("x=--group so3", "variant x"),
                      ("x=--bogus 1", "variant x"), ("x=--lowpass-sigma -1", "--lowpass-sigma"),
                      ("x='--group", "variant x")):
        with pytest.raises(ValueError, match=what):
            variants.parse_variant(bad)
    names = [g.name for g in variants.grid_variants()]
    assert len(names) == 9 and len(set(names)) == 9 and "paper-path" in names


@pytest.mark.parametrize("argv, says", [
    (["--variant", "x=--group so3"], "--variant"),
    (["--clip", "7:9-3"], "--clip"),
    (["--amplitude", "1,2"], "--amplitude"),
    (["--variant", "a=--end identity", "--variant", "a=--end smoothed"], "used twice"),
])
def test_bench_quality_rejects_bad_flags(argv, says, tmp_path, capsys):
    (tmp_path / "7scenes_redkitchen").mkdir()
    try:
        code = main(["bench", "quality", "--data", str(tmp_path), "--work", str(tmp_path / "w"), *argv])
    except SystemExit as e:
        code = e.code
    assert code == 2
    assert says in capsys.readouterr().err


# --------------------------------------------------------------------------------------------
# corrections: file format, and the shake tool's reader and scorer


def test_correction_rows_roundtrip(tmp_path):
    rng = np.random.default_rng(0)
    rots = Rotation.from_rotvec(rng.normal(0, 0.02, (20, 3)))
    gs = []
    for i, r in enumerate(rots):
        g = np.eye(4)
        g[:3, :3] = r.as_matrix() * (1.1 if i % 2 else 1.0)  # a SIM(3)-like scale is dropped
        g[:3, 3] = rng.normal(0, 0.01, 3)
        gs.append(g)
    stamps = [1_305_031_102_175_304_000 + 33_333_333 * i for i in range(20)]
    path = tmp_path / "c" / "ours.txt"
    assert write_corrections(path, zip(stamps, gs)) == 20
    ts, q = read_corrections(path)
    assert np.allclose(ts, np.array(stamps) / 1e9, atol=1e-6)
    assert (Rotation.from_quat(q) * rots.inv()).magnitude().max() < 1e-9
    assert seconds_text(33_333_333) == "0.033333333" and seconds_text(2_000_000_001) == "2.000000001"
    assert np.allclose(rotation_part(np.diag([2.0, 2.0, 2.0, 1.0])), np.eye(3))


def shake_tool_module():
    if not SHARED.is_dir():
        pytest.skip(f"{SHARED} not present")
    path = SHARED / "tools" / "shake" / "score_rotation.py"
    spec = importlib.util.spec_from_file_location("score_rotation_under_test", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_correction_file_is_read_by_score_rotation(tmp_path):
    sr = shake_tool_module()
    rng = np.random.default_rng(1)
    n = 90
    ts_ns = [i * 33_333_333 for i in range(n)]
    t = np.arange(n) / 30.0
    shake = Rotation.from_rotvec(np.radians(np.stack([0.6 * np.sin(2 * math.pi * 4 * t),
                                                      0.5 * np.sin(2 * math.pi * 5 * t + 1),
                                                      0.8 * rng.normal(0, 1, n)], 1)))
    # a perfect stabiliser: C_i = S_i^-1 (X_input = C_i X_stab; the tool's S: X_orig = S_i X_shaken)
    gs = []
    for s in shake.inv():
        g = np.eye(4)
        g[:3, :3] = s.as_matrix()
        gs.append(g)
    est = tmp_path / "est.txt"
    write_corrections(est, zip(ts_ns, gs))
    ts, rots = sr.read_rot_file(str(est))
    assert len(ts) == n and np.allclose(ts, t, atol=1e-8)
    assert (rots * shake).magnitude().max() < 1e-9
    r = sr.score(t, shake, ts, rots)
    assert all(x > 0.999 for x in r["removed_fraction"])
    none = sr.score(t, shake, ts, Rotation.identity(n))
    assert all(abs(x) < 1e-9 for x in none["removed_fraction"])


# --------------------------------------------------------------------------------------------
# one clip end to end (small synthetic TUM clip)


def test_run_clip_end_to_end(tmp_path):
    from tests.unit.test_cli_motion import write_tum_clip

    root = tmp_path / "clip"
    write_tum_clip(root, n=12)
    cfg = quality.QualityConfig(data=tmp_path, clips=[], work=tmp_path / "work", baselines=True)
    r = quality.run_clip(quality.Clip("clip", root), cfg)
    names = list(r["methods"])
    assert names[0] == "ours" and names[-1] == "input (unstabilized)"
    assert {"LK moving average", "vid.stab 2-pass (ffmpeg)", "deshake (ffmpeg)", "vidstab (python)",
            "vidgear Stabilizer"} <= set(names)
    for name, m in r["methods"].items():
        if m["status"] != "ok":
            assert m["reason"], name
            continue
        for k in ("jitter_px", "jitter_deg", "cropping", "border_free_cropping", "distortion", "stability",
                  "ms_per_frame", "failed"):
            assert k in m, (name, k)
        assert m["frames"] == 12, name
        assert m["border_free_cropping"] <= m["cropping"] + 1e-12
    if peers.available()["vidstab"] == "":  # 12 frames: shorter than vidstab's 30-frame window
        assert "shorter than vidstab's smoothing window" in r["methods"]["vidstab (python)"]["reason"]
    inp = r["methods"]["input (unstabilized)"]
    assert inp["cropping"] == pytest.approx(1.0, abs=1e-6) and inp["border_free_scale"] == 1.0
    assert r["methods"]["ours"]["settings"]["group"] == "se3"
    ours = r["methods"]["ours"]
    assert ours["uncorrected"] >= 0 and sum(ours["motion_kinds"].values()) == ours["frames_out"] == 12
    assert inp["border_frames_unaligned"] == 0  # every frame's border judged with its input-output homography
    text = quality_tables.format_clip(r)
    assert "bf crop" in text and "LK moving average" in text and "uncorrect." in text
    assert "  ours: frames by motion: " in text
    json.dumps(r, default=quality_tables.json_default)

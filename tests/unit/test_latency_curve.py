"""The quality-against-latency curve of ``quick-stream bench quality --latency-curve``
(quick_stream/bench/latency_curve.py)."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from quick_stream.bench import latency_curve as lc, quality, quality_peers, quality_tables
from quick_stream.cli import main
from quick_stream.core.params import window_settings


def test_a_look_ahead_is_frames_at_the_clip_s_rate_and_ours_releases_within_it():
    assert [lc.delay_frames(s, 30.0) for s in lc.DEFAULT_LOOKAHEADS_S] == [3, 6, 10, 15, 30]
    assert lc.delay_frames(0.01, 30.0) == 2 and lc.delay_frames(0.5, 15.0) == 8
    for d in (3, 10, 30):
        p = lc.ours_at(d).params.planner
        assert p.keyframes.interval == d and (p.lookahead, p.smoothness) == window_settings(d)  # its preset's


def point(ours: tuple[float, float], **peers: tuple[float, float]) -> dict:
    row = lambda px, deg: {"jitter_px": px, "jitter_deg": deg, "border_free_cropping": 0.9, "distortion": 0.99,
                           "failed": False, "status": "ok"}  # noqa: E731
    return {"delay_frames": 6, "lookahead_s": 0.2,
            "methods": {"ours": row(*ours), **{k: row(*v) for k, v in peers.items()}}}


def test_ours_wins_a_point_only_below_every_scored_peer_in_both_units():
    assert lc.wins(point((1.0, 0.1), a=(1.2, 0.2), b=(1.1, 0.11))) is True
    assert lc.wins(point((1.0, 0.1), a=(1.2, 0.2), b=(0.9, 0.11))) is False  # pixels
    assert lc.wins(point((1.0, 0.1), a=(1.2, 0.09))) is False  # degrees
    p = point((1.0, 0.1), a=(0.5, 0.05))
    p["methods"]["a"].update(failed=True)  # a peer the scorer failed on is not a peer it beat or lost to
    assert lc.wins(p) is None
    p["methods"]["b"] = {"status": "not run", "reason": "not installed"}
    assert lc.wins(p) is None


def test_like_for_like_a_peer_showing_borders_is_compared_with_ours_bordered():
    p = point((1.0, 0.1), a=(0.8, 0.2))  # a has less px jitter than ours, at the same cropping: ours loses
    assert lc.wins(p) is False and lc.wins_like_for_like(p) is False
    p["methods"]["a"]["border_free_cropping"] = 0.2  # a shows black borders where ours crops
    assert lc.wins_like_for_like(p) is None  # no bordered run of ours to set against it
    p["methods"][lc.OURS_BORDERED] = dict(p["methods"]["ours"], jitter_px=0.7, jitter_deg=0.15, border_free_cropping=0.1)
    assert lc.wins(p) is False and lc.wins_like_for_like(p) is True  # ours bordered is no peer of ours
    p["methods"][lc.OURS_BORDERED]["jitter_px"] = 0.85
    assert lc.wins_like_for_like(p) is False
    assert "+" not in lc.format_curve("c", {"points": [p], "presets": {}})[2][:14]
    p["methods"][lc.OURS_BORDERED]["jitter_px"] = 0.7
    row = lc.format_curve("c", {"points": [p], "presets": {}})[2]
    assert row[:14].rstrip().endswith("6f+") and "ours bordered" in lc.format_curve("c", {"points": [p], "presets": {}})[1]


def test_the_peers_are_set_to_the_same_look_ahead(monkeypatch, tmp_path):
    seen: dict = {}

    def fake_ffmpeg(frames, fps, workdir=None, params=None):
        seen["vid.stab smoothing"] = params.smoothing
        out = quality_peers.ffmpeg_baselines.BaselineOutputs()
        out["vidstab"], out["deshake"] = list(frames), list(frames)
        out.seconds.update(vidstab=0.0, deshake=0.0)
        out.cpu_seconds.update(vidstab=0.0, deshake=0.0)
        return out

    def fake_peer(key):
        def run(frames, **kw):
            seen[key] = kw
            return quality_peers.peers.PeerRun(list(frames), 0.0, len(frames))
        return run

    def fake_lk(frames, p=None):
        seen["LK radius"] = p.radius
        return list(frames)

    monkeypatch.setattr(quality_peers.ffmpeg_baselines, "ffmpeg_problem", lambda: "")
    monkeypatch.setattr(quality_peers.ffmpeg_baselines, "run_baselines", fake_ffmpeg)
    monkeypatch.setattr(quality_peers.peers, "available", lambda: {"vidstab": "", "vidgear": ""})
    monkeypatch.setattr(quality_peers.peers, "run_vidstab", fake_peer("vidstab"))
    monkeypatch.setattr(quality_peers.peers, "run_vidgear", fake_peer("vidgear"))
    monkeypatch.setattr(quality_peers.lk_average, "stabilize", fake_lk)
    monkeypatch.setattr(quality_peers, "score_frames", lambda a, b, fps: {"jitter_px": 1.0})
    frames = [np.zeros((8, 8, 3), np.uint8)] * 4
    rows, _ = quality_peers.peer_rows(frames, 30.0, tmp_path, None, delay=7)
    assert seen == {"vid.stab smoothing": 7, "vidstab": {"window": 7}, "vidgear": {"radius": 7}, "LK radius": 7}
    assert set(rows) == {"vid.stab 2-pass (ffmpeg)", "vidstab (python)", "vidgear Stabilizer", "LK moving average"}
    seen.clear()
    rows, _ = quality_peers.peer_rows(frames, 30.0, tmp_path, None)  # the defaults, deshake too
    assert seen == {"vid.stab smoothing": 10, "vidstab": {}, "vidgear": {}, "LK radius": 15}
    assert "deshake (ffmpeg)" in rows


def test_the_curve_of_a_clip_end_to_end(tmp_path):
    """Ours at two look-aheads and at the presets on a small clip, the table and the plot."""
    from tests.unit.test_cli_motion import write_tum_clip

    root = tmp_path / "clip"
    write_tum_clip(root, n=12)
    cfg = quality.QualityConfig(data=tmp_path, clips=[], work=tmp_path / "work", baselines=False,
                                lookaheads=[0.1, 0.2])
    r = quality.run_clip(quality.Clip("clip", root), cfg)
    c = r["latency_curve"]
    fps = r["fps"]
    assert [p["delay_frames"] for p in c["points"]] == [lc.delay_frames(0.1, fps), lc.delay_frames(0.2, fps)]
    for p in c["points"]:
        ours = p["methods"]["ours"]
        assert set(p["methods"]) == {"ours"} and np.isfinite(ours["jitter_px"]) and not ours["failed"]
        assert lc.wins(p) is None  # no peer ran
    assert set(c["presets"]) == set(lc.PRESETS) and c["presets"]["1s"]["delay_frames"] == 30
    for name, pr in c["presets"].items():  # a preset at a point's window is that point's row
        same = [p for p in c["points"] if p["delay_frames"] == pr["delay_frames"]]
        assert not same or pr["jitter_px"] == same[0]["methods"]["ours"]["jitter_px"]
    lines = lc.format_curve("clip", c)
    assert lines[0].startswith("latency curve, clip") and "ours --latency 0.5s (15 frames" in "\n".join(lines)
    # the bound of docs/method.md 6.3 at ours' border-free cropping, one per look-ahead
    bound = [ln for ln in lines if ln.startswith("  least px of a 2D crop")]
    assert len(bound) == 1 and bound[0].count(" s ") == len(c["points"])
    assert all(0 <= p["methods"]["ours"]["jitter_bound_px"] for p in c["points"])
    lc.plot([r], tmp_path / "curve.png")
    img = cv2.imread(str(tmp_path / "curve.png"))
    assert img is not None and img.shape[0] > 200
    full = quality_tables.format_tables({"clips": [r], "versions": {}, "latency_plot": "x.png"})
    assert "latency curve, clip" in full and "latency curve plot: x.png" in full
    json.dumps(r, default=quality_tables.json_default)


@pytest.mark.parametrize("value", ["0", "-1", "x", "0.2,20"])
def test_bad_look_aheads_are_refused_naming_the_flag(value, tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["bench", "quality", "--data", str(tmp_path), "--latency-curve", value])
    assert "--latency-curve" in capsys.readouterr().err

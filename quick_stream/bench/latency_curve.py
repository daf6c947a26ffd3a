"""Quality against latency (``quick-stream bench quality --latency-curve``): ours and each online 2D
stabiliser configured to see the same number of frames ahead, on the same clip, by the same scorer.

A look-ahead of L seconds is D = round(L x fps) frames (at least 2). At D:

* ours: ``--keyframe-interval D`` (a frame's correction is released at most D frames after the frame),
  with the look-ahead and smoothness that go with that window (:func:`quick_stream.core.params.window_settings`:
  a preset's own at its window, between presets interpolated), every other setting the default; and the
  latency presets at their own windows (``--latency 0.1s``: 3 frames ... ``1s``: 30; a preset whose
  window is one of the points is that point's row, not run twice);
* python vidstab with ``smoothing_window=D`` (it returns frame k - D at call k), vidgear's Stabilizer
  with ``smoothing_radius=D`` (D - 1 calls behind), the LK moving average over +-D frames, and FFmpeg
  vid.stab with ``smoothing=D`` (its Gaussian over +-D frames; two passes, so it reads the whole clip,
  but no frame's correction uses more than D frames after it) (:func:`.quality_peers.peer_rows`).

Rows per D: each method's jitter (px, deg), border-free cropping, distortion and whether it failed, and
ours leaving black borders as most peers do (``ours [bordered]``: no budget, zoom or fill; the
like-for-like row for a peer that shows borders). The table marks the look-aheads where ours is below
every scored peer in both jitters (``*``), or below each peer like for like (``+``: ours against a peer
whose border-free cropping is at least ours', ours bordered against one that shows more border). The plot: jitter
against look-ahead, one panel per clip and jitter unit (:func:`quick_stream.io.plot.plot_xy`).
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from ..core.params import LATENCY_PRESETS
from .quality_peers import peer_rows
from .variants import BORDERED, BORDERED_FLAGS, Variant, parse_settings

DEFAULT_LOOKAHEADS_S = (0.1, 0.2, 1 / 3, 0.5, 1.0)
PRESETS = {name: p[0] for name, p in LATENCY_PRESETS.items()}  # --latency presets: their delay in frames
PEERS = ("vid.stab 2-pass (ffmpeg)", "vidstab (python)", "vidgear Stabilizer", "LK moving average")
COLUMNS = ("jitter_px", "jitter_deg", "border_free_cropping", "distortion")
OURS_BORDERED = f"ours [{BORDERED}]"

RunOurs = Callable[[Variant], dict]
Progress = Callable[[str], None]


def delay_frames(seconds: float, fps: float) -> int:
    """The look-ahead in frames: ``seconds`` x ``fps``, rounded, at least 2 (a window needs a frame ahead)."""
    return max(2, int(round(seconds * fps)))


def ours_at(delay: int, bordered: bool = False) -> Variant:
    """Ours with corrections released at most ``delay`` frames after their frame (module docstring);
    ``bordered``: leaving black borders (:data:`.variants.BORDERED_FLAGS`)."""
    flags = ["--keyframe-interval", str(delay)]
    if bordered:
        return parse_settings([*flags, *BORDERED_FLAGS], name=f"ours {delay}f [{BORDERED}]")
    return parse_settings(flags, name=f"ours {delay}f")


def curve(images: list[np.ndarray], fps: float, lookaheads: list[float], run_ours: RunOurs, work: Path,
          baselines: bool = True, progress: Progress | None = None) -> dict:
    """The curve of one clip: per look-ahead the rows of ours and the peers at that delay, and ours' presets.

    ``run_ours(variant)`` scores ours with that variant on the clip (the benchmark's own runner)."""
    def say(what: str) -> None:
        if progress:
            progress(f"latency curve: {what}")

    points = []
    for delay in sorted({delay_frames(s, fps) for s in lookaheads}):
        say(f"ours at {delay} frames")
        methods = {"ours": _kept(run_ours(ours_at(delay)))}
        if baselines:  # the like-for-like row for a peer that shows borders
            say(f"ours [{BORDERED}] at {delay} frames")
            methods[OURS_BORDERED] = _kept(run_ours(ours_at(delay, bordered=True)))
            rows, _ = peer_rows(images, fps, Path(work) / f"d{delay}", lambda w: say(f"{w} at {delay} frames"),
                                delay=delay)
            methods.update({k: _kept(v) for k, v in rows.items()})
        points.append({"delay_frames": delay, "lookahead_s": delay / fps, "methods": methods})
    presets = {}
    at = {pt["delay_frames"]: pt["methods"]["ours"] for pt in points}
    for name, delay in PRESETS.items():  # a preset's window is ours at that delay (window_settings): run once
        if delay not in at:
            say(f"ours --latency {name}")
        row = at.get(delay) or _kept(run_ours(parse_settings(["--latency", name], name=f"latency {name}")))
        presets[name] = {"delay_frames": delay, "lookahead_s": delay / fps, **row}
    return {"points": points, "presets": presets}


def _kept(row: dict) -> dict:
    keep = {k: row[k] for k in (*COLUMNS, "jitter_bound_px", "failed", "failure_reason", "status", "reason")
            if k in row}
    return keep


def _peers(point: dict) -> list[dict]:
    return [r for name, r in point["methods"].items() if not name.startswith("ours") and _scored(r)]


def _below(a: dict, b: dict) -> bool:
    return a["jitter_px"] < b["jitter_px"] and a["jitter_deg"] < b["jitter_deg"]


def wins(point: dict) -> bool | None:
    """Whether ours is below every scored peer at this point in both jitters (None: no peer scored)."""
    ours, peers = point["methods"]["ours"], _peers(point)
    if not peers or not _scored(ours):
        return None
    return all(_below(ours, r) for r in peers)


def wins_like_for_like(point: dict) -> bool | None:
    """Whether ours is below each scored peer like for like: ours against a peer whose border-free cropping
    is at least ours' (it keeps as much of the frame clear), ours bordered against a peer that shows more
    border than ours crops (None: no peer scored, or a bordered comparison without ours bordered)."""
    ours, bordered, peers = point["methods"]["ours"], point["methods"].get(OURS_BORDERED), _peers(point)
    if not peers or not _scored(ours):
        return None
    verdicts = []
    for r in peers:
        if r["border_free_cropping"] >= ours["border_free_cropping"]:
            verdicts.append(_below(ours, r))
        elif bordered is None or not _scored(bordered):
            return None
        else:
            verdicts.append(_below(bordered, r))
    return all(verdicts)


def _scored(row: dict) -> bool:
    return row.get("status", "ok") == "ok" and not row.get("failed") and np.isfinite(row.get("jitter_px", np.nan))


def format_curve(name: str, c: dict) -> list[str]:
    """The curve's table for one clip."""
    short = {"vid.stab 2-pass (ffmpeg)": "vid.stab", "vidstab (python)": "vidstab.py", "vidgear Stabilizer": "vidgear",
             "LK moving average": "LK avg", OURS_BORDERED: "ours bordered"}
    methods = ["ours", *[p for p in (OURS_BORDERED, *PEERS) if any(p in pt["methods"] for pt in c["points"])]]
    lines = [f"latency curve, {name}: jitter px / deg, border-free cropping, distortion at each look-ahead "
             "(peers at the same look-ahead in frames); * ours below every scored peer in px and deg, + ours "
             "below each like for like (ours bordered against a peer showing more border than ours crops)",
             f"{'look-ahead':<14}" + "".join(f"{short.get(m, m):>27}" for m in methods)]
    for pt in c["points"]:
        cells = []
        for m in methods:
            r = pt["methods"].get(m)
            if r is None or not _scored(r):
                why = "-" if r is None else (r.get("reason") or r.get("failure_reason") or r.get("status", ""))[:25]
                cells.append(f"{why:>27}")
            else:
                cells.append(f"{r['jitter_px']:7.3f} / {r['jitter_deg']:.4f} {r['border_free_cropping']:.2f} "
                             f"{r['distortion']:.2f}".rjust(27))
        mark = {True: "*", False: "+" if wins_like_for_like(pt) else " ", None: "?"}[wins(pt)]
        lines.append(f"{pt['lookahead_s']:5.2f} s {pt['delay_frames']:3d}f{mark}" + "".join(cells))
    bounds = [(pt["lookahead_s"], pt["methods"]["ours"].get("jitter_bound_px")) for pt in c["points"]]
    if any(b is not None and np.isfinite(b) for _, b in bounds):
        lines.append("  least px of a 2D crop at ours' border-free cropping (docs/method.md 6.3): "
                     + ", ".join(f"{s:.2f} s {b:.3f}" for s, b in bounds if b is not None and np.isfinite(b))
                     + " (constant zoom)")
    for name_, p in c["presets"].items():
        if _scored(p):
            lines.append(f"  ours --latency {name_} ({p['delay_frames']} frames, {p['lookahead_s']:.2f} s): "
                         f"{p['jitter_px']:.3f} px / {p['jitter_deg']:.4f} deg, border-free cropping "
                         f"{p['border_free_cropping']:.3f}, distortion {p['distortion']:.3f}")
    return lines


def plot(clips: list[dict], path: Path) -> None:
    """Jitter against look-ahead: a panel per clip and unit, a line per method."""
    from ..io.plot import plot_xy

    panels = []
    for c in clips:
        cv = c.get("latency_curve")
        if not cv:
            continue
        for col, unit in (("jitter_px", "px"), ("jitter_deg", "deg")):
            series = {}
            for m in ["ours", OURS_BORDERED, *PEERS]:
                pts = [(p["lookahead_s"], p["methods"][m][col]) for p in cv["points"]
                       if m in p["methods"] and _scored(p["methods"][m])]
                if pts:
                    series[m] = (np.array([x for x, _ in pts]), np.array([y for _, y in pts]))
            panels.append((f"{c['name']}: jitter ({unit}) against look-ahead (s)", series))
    if panels:
        plot_xy(panels, str(path))

"""The tables ``quick-stream bench quality`` prints, and its JSON's encoder (:mod:`.quality` runs it)."""
from __future__ import annotations

import math
import shlex
from pathlib import Path

import numpy as np

from .quality import AXES, COLUMNS

def _fmt(fmt: str, v: object) -> str:
    if isinstance(v, float) and not math.isfinite(v):
        return f"{'nan':>10}"
    return fmt.format(v)


def format_clip(c: dict) -> str:
    title = f"{c['name']}: {c['frames']} frames {c['size']} @ {c['fps']:.3g} fps"
    if "shake" in c:
        s = c["shake"]
        title += (f"; known shake seed {s['seed']}, frames {s['first']}-{s['last']}, "
                  f"RMS {s['pitch']:g}/{s['yaw']:g}/{s['roll']:g} deg (pitch/yaw/roll)")
    width = max(30, *(len(k) for k in c["methods"]))
    lines = [title, f"{'method':{width}s} " + " ".join(f"{h:>10s}" for _, h, _ in COLUMNS)]
    for name, m in c["methods"].items():
        if m.get("status") != "ok":
            lines.append(f"{name:{width}s} {m.get('status')}: {m.get('reason', '')}")
            continue
        lines.append(f"{name:{width}s} " + " ".join(_fmt(f, m.get(k, float('nan'))) for k, _, f in COLUMNS))
    for name, m in c["methods"].items():
        if m.get("status") == "ok" and m.get("failed"):
            lines.append(f"  {name} failed: {m.get('failure_reason')}")
    sr = c.get("shake_removed")
    if sr:
        lines.append("injected high-frequency rotation removed (score_rotation.py, kind correction, > 1 Hz):")
        lines.append(f"{'':{width}s} " + " ".join(f"{a:>7s}" for a in AXES) + "   | with --reference: "
                     + " ".join(f"{a:>7s}" for a in AXES))
        for name, s in sr.items():
            if "error" in s:
                lines.append(f"{name:{width}s} error: {s['error']}")
                continue
            a = " ".join(f"{100 * x:6.1f}%" for x in s["without_reference"]["removed_fraction"])
            b = " ".join(f"{100 * x:6.1f}%" for x in s["with_reference"]["removed_fraction"])
            lines.append(f"{name:{width}s} {a}   |                   {b}")
            for key in ("without_reference", "with_reference"):
                if "warning" in s[key]:
                    lines.append(f"  {name} ({key.replace('_', ' ')}): WARNING {s[key]['warning']}")
        first = next((s for s in sr.values() if "error" not in s), None)
        if first:
            inj = first["without_reference"]["injected_hp_rms_deg"]
            lines.append(f"{'(injected HP RMS, deg)':{width}s} " + " ".join(f"{x:7.3f}" for x in inj))
    return "\n".join(lines)


def format_tables(r: dict) -> str:
    out = [format_clip(c) for c in r["clips"]]
    v = r["versions"]
    out.append("versions: " + ", ".join(f"{k} {v[k]}" for k in ("ffmpeg", "vidstab", "vidgear", "opencv") if v.get(k)))
    cmds = next((c.get("ffmpeg_commands") for c in r["clips"] if c.get("ffmpeg_commands")), None)
    if cmds:
        out.append("ffmpeg commands (first clip; W, H, FPS per clip):\n" + "\n".join(f"  {k}: ffmpeg {c}"
                                                                                  for k, c in cmds.items()))
    for name, var in r.get("variants", {}).items():
        out.append(f"variant {name}: {' '.join(shlex.quote(a) for a in var['argv'])}")
    return "\n\n".join(out)


def json_default(o: object) -> object:
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    return str(o)

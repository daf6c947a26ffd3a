"""The tables ``quick-stream bench quality`` prints, and its JSON's encoder (:mod:`.quality` runs it)."""
from __future__ import annotations

import math
import shlex
from pathlib import Path

import numpy as np

from .latency_curve import format_curve

from .quality_robustness import AXES, format_robustness

COLUMNS = (("jitter_px", "jitter px", "{:10.3f}"), ("jitter_deg", "jitter deg", "{:10.4f}"),
           ("jitter_px_border_free", "bf jit px", "{:10.3f}"),
           ("jitter_bound_px", "bound px", "{:10.3f}"), ("jitter_bound_deg", "bound deg", "{:10.4f}"),
           ("cropping", "cropping", "{:10.3f}"), ("border_free_cropping", "bf crop", "{:10.3f}"),
           ("distortion", "distortion", "{:10.3f}"), ("stability", "stability", "{:10.3f}"),
           ("ms_per_frame", "ms/frame", "{:10.1f}"), ("failed", "failed", "{!s:>10}"),
           ("uncorrected", "uncorrect.", "{:10d}"))


def _fmt(fmt: str, v: object) -> str:
    if v is None:  # a column the method has not (uncorrected: ours and its variants only)
        return f"{'-':>10}"
    if isinstance(v, float) and not math.isfinite(v):
        return f"{'nan':>10}"
    return fmt.format(v)


def motion_lines(methods: dict) -> list[str]:
    """Ours' (and each variant's) frames by how their motion was known, and those not corrected."""
    out = []
    for name, m in methods.items():
        kinds = m.get("motion_kinds")
        if m.get("status") == "ok" and kinds is not None:
            out.append(f"  {name}: frames by motion: " + ", ".join(f"{k} {n}" for k, n in kinds.items())
                       + f"; reached over {m.get('reached_over', 0)}; lifted loose {m.get('loose_flows', 0)}"
                       + f"; not corrected {m.get('uncorrected', 0)}")
    return out


def format_clip(c: dict) -> str:
    title = f"{c['name']}: {c['frames']} frames {c['size']} @ {c['fps']:.3g} fps"
    if "shake" in c:
        s = c["shake"]
        what = c.get("known_shake") or f"seed {s['seed']}, frames {s['first']}-{s['last']}"
        title += f"; known shake {what}, RMS {s['pitch']:g}/{s['yaw']:g}/{s['roll']:g} deg (pitch/yaw/roll)"
    if c.get("degrade", {}).get("argv"):
        title += f"; degrade cell {c['degrade']['cell']}: {' '.join(c['degrade']['argv'])}"
    width = max(30, *(len(k) for k in c["methods"]))
    lines = [title, f"{'method':{width}s} " + " ".join(f"{h:>10s}" for _, h, _ in COLUMNS)]
    for name, m in c["methods"].items():
        if m.get("status") != "ok":
            lines.append(f"{name:{width}s} {m.get('status')}: {m.get('reason', '')}")
            continue
        lines.append(f"{name:{width}s} " + " ".join(_fmt(f, m.get(k, None if k == "uncorrected" else float("nan")))
                                                    for k, _, f in COLUMNS))
    for name, m in c["methods"].items():
        if m.get("status") == "ok" and m.get("failed"):
            lines.append(f"  {name} failed: {m.get('failure_reason')}")
    lines += motion_lines(c["methods"])
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
            run = s.get("reference_run")
            if run:
                lines.append(f"  {name} on the unshaken reference: frames by motion: "
                             + ", ".join(f"{k} {n}" for k, n in run["motion_kinds"].items())
                             + f"; reached over {run.get('reached_over', 0)}; lifted loose {run.get('loose_flows', 0)}"
                             + f"; not corrected {run['uncorrected']}")
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
    if r.get("robustness"):
        out.append(format_robustness(r["robustness"]))
    out += ["\n".join(format_curve(c["name"], c["latency_curve"])) for c in r["clips"] if c.get("latency_curve")]
    if r.get("latency_plot"):
        out.append(f"latency curve plot: {r['latency_plot']}")
    out += [f"note: {n}" for n in r.get("settings", {}).get("notes", [])]
    v = r["versions"]
    out.append("versions: " + ", ".join(f"{k} {v[k]}" for k in ("ffmpeg", "vidstab", "vidgear", "opencv") if v.get(k)))
    cmds = next((c.get("ffmpeg_commands") for c in r["clips"] if c.get("ffmpeg_commands")), None)
    if cmds:
        out.append("ffmpeg commands (first clip; W, H, FPS per clip):\n" + "\n".join(f"  {k}: ffmpeg {c}"
                                                                                  for k, c in cmds.items()))
    for name, var in r.get("variants", {}).items():
        out.append(f"variant {name}: {' '.join(shlex.quote(a) for a in var['argv'])}")
    for name, argv in r.get("settings", {}).get("degrade_cells", {}).items():
        out.append(f"degrade cell {name}: " + (f"degrade.py --seed SEED {' '.join(argv)}" if argv else "no degrade"))
    return "\n\n".join(out)


def json_default(o: object) -> object:
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    return str(o)

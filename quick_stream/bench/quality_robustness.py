"""The robustness grid of ``quick-stream bench quality``: ours against the best peer on every
known-shake clip x degrade cell (the ``clean`` cell is the known-shake clip itself).

One row per (known-shake clip, cell), from the benchmark's result (:func:`robustness_rows`, the
JSON's ``robustness``): ours' residual jitter (px, deg), the best peer's for each of the two
columns separately (best = lowest, among the peers that ran and were scored: status "ok", not
``failed``, a finite value), ours' border-free cropping, distortion and frames not corrected,
and the share of the injected shake ours removed per axis with ``--reference``; with the peers, also
ours leaving black borders as they mostly do (the ``bordered`` variant: no budget, zoom or fill), the
like-for-like value for a peer that shows borders. Peers are every
method but ours, its variants and the unstabilised input. A peer that did not run, or whose
scorer failed on the cell (heavy blur can leave the feature matching too few matches), or
whose value is NaN, is named in the row's ``peers_not_scored`` with why, and in the table.
"""
from __future__ import annotations

import math

from .variants import BORDERED

AXES = ("pitch", "yaw", "roll", "total")
INPUT = "input (unstabilized)"
SHORT = {"vid.stab 2-pass (ffmpeg)": "vid.stab", "deshake (ffmpeg)": "deshake", "vidstab (python)": "vidstab.py",
         "vidgear Stabilizer": "vidgear", "LK moving average": "LK avg"}
JITTER = ("jitter_px", "jitter_deg")


def is_peer(name: str) -> bool:
    return not (name == "ours" or name.startswith("ours [") or name == INPUT)


def short(name: str) -> str:
    """A peer's short name for the table."""
    return SHORT.get(name, name[:12])


def _finite(v: object) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _not_scored(m: dict, key: str | None = None) -> str:
    """Why a method's row (or its ``key``) cannot be ranked; '' when it can."""
    if m.get("status") != "ok":
        return f"{m.get('status')}: {m.get('reason', '')}".strip()
    if m.get("failed"):
        return f"scorer failed: {m.get('failure_reason', '')}".strip()
    if key is not None and not _finite(m.get(key)):
        return f"{key} is NaN"
    return ""


def robustness_row(clip: dict) -> dict:
    """The grid's row of one known-shake clip (or degraded copy) of the benchmark's result."""
    methods = clip["methods"]
    ours = methods.get("ours", {})
    row: dict = {"clip": clip["known_shake"], "cell": clip["degrade"]["cell"], "name": clip["name"],
                 "ours": {k: ours.get(k) for k in (*JITTER, "border_free_cropping", "distortion", "uncorrected",
                                                   "failed", "failure_reason")},
                 "best_peer": {}, "peers_not_scored": {}}
    bordered = methods.get(f"ours [{BORDERED}]")
    row["ours_bordered"] = None if bordered is None else {k: bordered.get(k) for k in JITTER}
    peers = {n: m for n, m in methods.items() if is_peer(n)}
    for key in JITTER:
        ranked = [(m[key], n) for n, m in peers.items() if not _not_scored(m, key)]
        row["best_peer"][key] = ({"method": min(ranked)[1], "value": min(ranked)[0]} if ranked else None)
    for n, m in peers.items():
        why = _not_scored(m) or "; ".join(w for w in (_not_scored(m, k) for k in JITTER) if w)
        if why:
            row["peers_not_scored"][n] = why
    sr = clip.get("shake_removed", {}).get("ours", {})
    if "with_reference" in sr:
        row["removed_with_reference"] = list(sr["with_reference"]["removed_fraction"])
    else:
        row["removed_with_reference"] = None
        row["removed_error"] = sr.get("error", "not scored")
    return row


def robustness_rows(r: dict) -> list[dict]:
    """Rows of every known-shake clip and degraded copy in ``r['clips']``, in run order."""
    return [robustness_row(c) for c in r["clips"] if "degrade" in c]


def _num(v: object, fmt: str, width: int) -> str:
    return format(v, fmt).rjust(width) if _finite(v) else "nan".rjust(width)


def format_robustness(rows: list[dict]) -> str:
    """The grid as text: a line per row, then the peers not scored and ours' failures, named."""
    cw = max(16, *(len(x["clip"]) for x in rows))
    nw = max(7, *(len(x["cell"]) for x in rows))
    head = (f"{'known-shake clip':{cw}s} {'cell':{nw}s} {'ours px':>8s} {'  best peer px':21s} {'ours deg':>8s} "
            f"{'  best peer deg':21s} {'bordered px / deg':>17s} {'bf crop':>7s} {'distort':>7s} {'uncorr':>6s} "
            + " ".join(f"{a:>8s}" for a in AXES) + "  peers not scored")
    lines = ["robustness: ours vs the best peer per column (lowest jitter); ours bordered: leaving black borders as "
             "the peers mostly do; shake removed with --reference, per axis", head]
    notes = []
    for x in rows:
        o = x["ours"]
        cells = [f"{x['clip']:{cw}s}", f"{x['cell']:{nw}s}"]
        for key, fmt in (("jitter_px", ".3f"), ("jitter_deg", ".4f")):
            b = x["best_peer"].get(key)
            best = "-".rjust(21) if b is None else f"{_num(b['value'], fmt, 8)} {short(b['method']):<12s}"
            cells += [_num(o.get(key), fmt, 8), best]
        ob = x.get("ours_bordered")
        cells.append("-".rjust(17) if ob is None else
                     f"{_num(ob.get('jitter_px'), '.3f', 8)} {_num(ob.get('jitter_deg'), '.4f', 8)}")
        cells += [_num(o.get("border_free_cropping"), ".3f", 7), _num(o.get("distortion"), ".3f", 7),
                  str(o.get("uncorrected", "-")).rjust(6)]
        rm = x.get("removed_with_reference")
        removed = (" ".join(f"{100 * v:7.1f}%" for v in rm) if rm else
                   " ".join("-".rjust(8) for _ in AXES))
        unscored = ", ".join(short(n) for n in x["peers_not_scored"]) or "-"
        lines.append(" ".join(cells) + " " + removed + "  " + unscored)
        where = f"  {x['clip']} {x['cell']}:"
        if o.get("failed"):
            notes.append(f"{where} ours: scorer failed: {o.get('failure_reason', '')}")
        if rm is None:
            notes.append(f"{where} ours: shake removed not scored: {x.get('removed_error', '')}")
        notes += [f"{where} {n}: {why}" for n, why in x["peers_not_scored"].items()]
    return "\n".join(lines + notes)

"""``quick-stream bench quality``: its flags, their checks (exit 2 naming the flag) and the run
(:mod:`quick_stream.bench.quality` does the work, :mod:`quick_stream.bench.quality_tables` prints it)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from ..stream import argtypes as at
from .jsonout import add_json, text_out, write_json

if TYPE_CHECKING:
    from ..bench.degrade_clips import DegradeCell
    from ..bench.quality_clips import ShakeClip
    from ..bench.variants import Variant

DEFAULT_DATA = Path("../shared/data")
DEFAULT_SHAKE_TOOL = Path("../shared/tools/shake")
DEFAULT_DEGRADE_TOOL = Path("../shared/tools/degrade")
HELP = ("ours vs FFmpeg vid.stab/deshake, vidstab, vidgear and an LK baseline on real clips, known-shake "
        "clips made from them and degraded copies of those")
DESCRIPTION = ("Quality benchmark (quick_stream/bench/quality.py): every method scored by quick_stream.quality.metrics "
               "against the same input frames, on real clips (--real), known-shake clips made from them (--clip) and "
               "copies of those degraded as a noisier depth camera would record them (--degrade, --degrade-grid); on "
               "the known-shake clips also the share of the injected rotation ours removed (the shake tool's "
               "score_rotation.py); with degrade cells, a robustness table of ours against the best peer per clip "
               "and cell.")


def _variant(text: str) -> "Variant":
    from ..bench.variants import parse_variant

    return parse_variant(text)


def _shake_clip(text: str) -> "ShakeClip":
    from ..bench.quality_clips import ShakeClip

    return ShakeClip.parse(text)


def _real(text: str) -> str:
    from ..bench.quality_clips import check_name

    return check_name(text)


def _degrade(text: str) -> "DegradeCell":
    from ..bench.degrade_clips import parse_degrade

    return parse_degrade(text)


def _amplitudes(text: str) -> tuple[float, float, float]:
    from ..bench.shake_clips import parse_amplitudes

    return parse_amplitudes(text)


def add_arguments(q: argparse.ArgumentParser) -> None:
    q.add_argument("--data", type=Path, default=DEFAULT_DATA, metavar="DIR",
                   help=f"folder holding the real clips, TUM layout (default: {DEFAULT_DATA})")
    q.add_argument("--real", action="append", type=at.checked(_real, "real"), default=None, metavar="NAME",
                   help="a real clip: the folder NAME under --data, every frame; repeatable (default: "
                   "7scenes_redkitchen and tum_fr1_rpy, each skipped with a note when its folder is missing)")
    q.add_argument("--frames", type=at.positive_int, default=None,
                   help="use only the first N frames of every clip (default: all)")
    q.add_argument("--clip", dest="clips", action="append", type=at.checked(_shake_clip, "clip"), default=None,
                   metavar="[SRC:]SEED:FIRST-LAST",
                   help="a known-shake clip made from the real clip SRC (a folder under --data; default "
                   "7scenes_redkitchen): inject.py seed and inclusive source frame range; repeatable (default: "
                   "7:0-149 and 11:100-249, skipped with a note when 7scenes_redkitchen is missing)")
    q.add_argument("--no-shake", action="store_true", help="only the real clips, no known-shake clips")
    q.add_argument("--amplitude", type=at.checked(_amplitudes, "amplitude"), default=(0.6, 0.6, 0.8),
                   metavar="PITCH,YAW,ROLL", help="RMS shake in deg per axis (default: 0.6,0.6,0.8)")
    q.add_argument("--shake-tool", type=Path, default=DEFAULT_SHAKE_TOOL, metavar="DIR",
                   help=f"folder of the shake tool, inject.py and score_rotation.py (default: {DEFAULT_SHAKE_TOOL})")
    q.add_argument("--degrade", action="append", type=at.checked(_degrade, "degrade"), default=[],
                   metavar="NAME='--flag value ...'",
                   help="also a copy of every known-shake clip and of its reference made by degrade.py with these "
                   "flags (--stereo-k, --holes, --shift, --depth-lag, --blur, --gain-jitter, --jpeg; a flag not "
                   "given is OFF, not degrade.py's default), seeded with the clip's shake seed; every method runs "
                   "on it; repeatable (default: none)")
    q.add_argument("--degrade-grid", action="store_true",
                   help="add the standard degrade cells: clean (the clip itself), k006 (--stereo-k 0.006), k012 "
                   "(--stereo-k 0.012), lag1 (--depth-lag 1), blur1 (--blur 1), holes02 (--holes 0.2), shift42 "
                   "(--shift 4,2), all (those five at once, --stereo-k 0.012, with degrade.py's default "
                   "--gain-jitter 0.03 and --jpeg 75)")
    q.add_argument("--degrade-tool", type=Path, default=DEFAULT_DEGRADE_TOOL, metavar="DIR",
                   help=f"folder of the degrade tool, degrade.py (default: {DEFAULT_DEGRADE_TOOL})")
    q.add_argument("--work", type=at.output_dir("--work"), default="out/bench-quality", metavar="DIR",
                   help="cache of made clips (DIR/clips, reused), corrections, FFmpeg files "
                   "(default: out/bench-quality)")
    q.add_argument("--variant", dest="variants", action="append", type=at.checked(_variant, "variant"),
                   default=[], metavar="NAME='--flag value ...'",
                   help="also run ours with these stabilizer flags, those of quick-stream stabilize; repeatable "
                   "(default: none)")
    q.add_argument("--grid", action="store_true",
                   help="add the variants every group x both end modes, and the paper's path (se3, identity, "
                   "--lowpass-sigma 0)")
    q.add_argument("--no-baselines", action="store_true",
                   help="skip the peers (FFmpeg, vidstab, vidgear, LK moving average) and ours 'bordered' (ours leaving "
                        "black borders as those peers mostly do, run with them to compare like for like): ours and "
                        "the input only")
    q.add_argument("--latency-curve", nargs="?", const=_lookaheads(DEFAULT_LOOKAHEADS), default=None,
                   type=at.checked(_lookaheads, "latency-curve"), metavar="S,S,...",
                   help="also the quality-against-latency curve on the real and known-shake clips: ours at each "
                   "look-ahead (seconds; its keyframe interval that many frames) and the latency presets, against "
                   "each online peer set to look as many frames ahead; a table per clip and a plot WORK/"
                   "latency_curve.png (default look-aheads: " + DEFAULT_LOOKAHEADS + ")")
    add_json(q, "everything (settings, commands, versions, per-clip metrics, the robustness grid)")
    at.add_force(q)


DEFAULT_LOOKAHEADS = "0.1,0.2,0.333,0.5,1"


def _lookaheads(text: str) -> list[float]:
    vals = [float(v) for v in text.split(",") if v.strip()]
    if not vals or not all(0 < v <= 10 for v in vals):
        raise ValueError(f"expected look-aheads in seconds, each in (0, 10], comma-separated; got {text!r}")
    return vals


def _error(msg: str) -> int:
    print(f"quick-stream bench quality: {msg}", file=sys.stderr)
    return 2


def _used_twice(flag: str, names: list[str]) -> str:
    dup = sorted({n for n in names if names.count(n) > 1})
    return f"{flag}: name(s) used twice: {', '.join(dup)}" if dup else ""


def ours_variants(args: argparse.Namespace) -> list[Variant]:
    """Ours' variants to run: ``--variant``, ``--grid``'s, and with the peers the ``bordered`` one (ours
    leaving black borders as they mostly do: the like-for-like row for a peer that shows borders)."""
    from ..bench import variants

    out = list(args.variants) + (variants.grid_variants() if args.grid else [])
    if not args.no_baselines and variants.BORDERED not in {v.name for v in out}:
        out.append(variants.bordered_variant())
    return out


def run(args: argparse.Namespace) -> int:
    """The benchmark from parsed flags; exit 2 (a message naming the flag) before any work when one is wrong.

    A clip folder that is missing raises SourceError (its flag in the message; exit 2 by the caller).
    """
    from ..bench import degrade_clips, quality, quality_tables, variants
    from ..bench.quality_clips import select_sources
    from ..bench.shake_clips import check_tool

    variant_list = ours_variants(args)
    cells = (degrade_clips.grid_cells() if args.degrade_grid else []) + list(args.degrade)
    problem = (_used_twice("--variant", [v.name for v in variant_list])
               or _used_twice("--degrade", [c.name for c in cells]))
    if problem:
        return _error(problem)
    if args.no_shake and cells:
        return _error("--degrade/--degrade-grid degrade the known-shake clips: not with --no-shake")
    real, shakes, notes = select_sources(args.data, args.real, args.clips, args.no_shake)
    shakes = [c.with_amplitudes(args.amplitude) for c in shakes]
    try:
        if shakes:
            check_tool(args.shake_tool)
        if shakes and any(not c.is_clean for c in cells):
            degrade_clips.check_tool(args.degrade_tool)
    except FileNotFoundError as e:
        return _error(str(e))
    for note in notes:
        print(f"quick-stream bench quality: note: {note}", file=sys.stderr)
    cfg = quality.QualityConfig(data=args.data, frames=args.frames, real=real, clips=shakes,
                                shake_tool=args.shake_tool, degrade=cells, degrade_tool=args.degrade_tool,
                                work=Path(args.work), variants=variant_list, baselines=not args.no_baselines,
                                notes=notes, lookaheads=args.latency_curve or [])
    r = quality.run(cfg, quality.progress_to_stderr())
    print(quality_tables.format_tables(r), file=text_out(args))
    if args.json:
        write_json(args.json, r, default=quality_tables.json_default)
        if args.json != "-":
            print(f"wrote {args.json}")
    return 0

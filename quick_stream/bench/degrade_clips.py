"""Degraded copies of the known-shake clips for the quality benchmark, made with the external
``degrade`` tool (``--degrade-tool``, default ``../shared/tools/degrade``).

The tool's ``degrade.py IN OUT --seed S [flags]`` makes a TUM-layout clip look as a noisier,
less synchronised depth camera would record it, keeping the timestamps, ``shake.txt`` and the
ground truth, so a degraded known-shake clip is still scored by the shake tool. Its effects and
their defaults (every one on by default except the lag; 0 turns one off):

* ``--stereo-k K`` (0.003): depth noise sigma = K z^2 m;
* ``--holes F`` (0.08): invalid depth blobs covering F of the image, and depth edges;
* ``--shift DX,DY`` (2,1): depth shifted against colour, px;
* ``--depth-lag N`` (0): colour frame i gets the depth of frame i-N;
* ``--blur E`` (0.5): motion blur along the frame-to-frame shift, E = exposure / frame interval;
* ``--gain-jitter G`` (0.03): per-frame colour gain 1 +- G;
* ``--jpeg Q`` (75): colour re-encoded as JPEG at quality Q.

A **cell** is a name and the values of all seven effects. Its flags start from all effects
OFF (not from the tool's defaults), so a cell isolates the effects it names; the tool is
always run with all seven flags spelled out (:meth:`DegradeCell.argv`). ``clean`` is the
undegraded clip itself. The standard grid (``--degrade-grid``, :func:`grid_cells`): ``clean``,
``k006`` (stereo-k 0.006), ``k012`` (0.012), ``lag1`` (depth-lag 1), ``blur1`` (blur 1),
``holes02`` (holes 0.2), ``shift42`` (shift 4,2), and ``all``: those five effects at once at
their strongest grid values (stereo-k 0.012) plus the tool's default gain jitter (0.03) and
JPEG (75).

Each cell is applied to a known-shake clip and to its unshaken reference with the same seed
(the shake clip's seed), so ``score_rotation.py --reference`` still subtracts only what the
stabiliser does to the clip's own motion. Made copies are cached beside the shake clips: the
folder name spells every value and the seed, and the copy is reused when its
``bench-clip.json`` (written last) records the same argv, seed and source clip
(:func:`~quick_stream.bench.shake_clips.run_recorded`).
"""
from __future__ import annotations

import argparse
import json
import math
import re
import shlex
import sys
from dataclasses import dataclass, field
from pathlib import Path

from .shake_clips import RECORD, is_recorded, run_recorded

DEFAULT_TOOL = Path("../shared/tools/degrade")
TOOL_DEFAULTS = {"stereo_k": 0.003, "holes": 0.08, "shift": (2.0, 1.0), "depth_lag": 0, "blur": 0.5,
                 "gain_jitter": 0.03, "jpeg": 75}
OFF = {"stereo_k": 0.0, "holes": 0.0, "shift": (0.0, 0.0), "depth_lag": 0, "blur": 0.0, "gain_jitter": 0.0,
       "jpeg": 0}
CLEAN = "clean"
# short keys of the cached folder names, in the order of the flags
_SHORT = {"stereo_k": "k", "holes": "h", "shift": "sh", "depth_lag": "lag", "blur": "b", "gain_jitter": "g",
          "jpeg": "q"}


def _text(v: object) -> str:
    if isinstance(v, tuple):
        return ",".join(f"{x:g}" for x in v)
    return f"{v:g}" if isinstance(v, float) else str(v)


@dataclass(frozen=True)
class DegradeCell:
    """A named degradation: the seven effects' values (``OFF`` for those not given); ``clean`` has none."""

    name: str
    values: dict = field(default_factory=dict)  # every key of OFF; empty for clean

    @property
    def is_clean(self) -> bool:
        return not self.values

    def argv(self) -> list[str]:
        """The tool's flags, all seven spelled out (none left to the tool's defaults); none for clean."""
        out: list[str] = []
        for key in OFF if self.values else ():
            out += ["--" + key.replace("_", "-"), _text(self.values[key])]
        return out

    def folder_name(self, base: str, seed: int) -> str:
        """Cache folder of this cell applied to the clip folder ``base`` with ``seed``."""
        return base + "_deg_" + "_".join(f"{_SHORT[k]}{_text(self.values[k])}" for k in OFF) + f"_seed{seed}"


class _RaisingParser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # type: ignore[override]
        raise ValueError(message)


def _nonneg(kind: type) -> object:
    def parse(text: str) -> object:
        v = kind(text)
        if not 0 <= v < math.inf:
            raise ValueError
        return v
    parse.__name__ = f"{kind.__name__} >= 0"
    return parse


def _fraction(text: str) -> float:
    v = float(text)
    if not 0 <= v < 1:
        raise ValueError
    return v


def _jpeg(text: str) -> int:
    v = int(text)
    if not 0 <= v <= 100:
        raise ValueError
    return v


def _shift(text: str) -> tuple[float, float]:
    dx, dy = (float(x) for x in text.split(","))
    if not all(abs(x) < 1e3 for x in (dx, dy)):
        raise ValueError
    return dx, dy


_fraction.__name__, _jpeg.__name__, _shift.__name__ = "fraction in [0, 1)", "quality 0-100", "DX,DY"


def _flag_parser(name: str) -> argparse.ArgumentParser:
    """degrade.py's effect flags (not --seed, --frames, --force: the benchmark sets those)."""
    p = _RaisingParser(prog=name, add_help=False, allow_abbrev=False)
    for key, kind in (("stereo_k", _nonneg(float)), ("holes", _fraction), ("shift", _shift),
                      ("depth_lag", _nonneg(int)), ("blur", _nonneg(float)), ("gain_jitter", _fraction),
                      ("jpeg", _jpeg)):
        p.add_argument("--" + key.replace("_", "-"), dest=key, type=kind, default=OFF[key])
    return p


def cell(name: str, argv: list[str]) -> DegradeCell:
    """A cell from degrade.py flags (those not given: off); ValueError naming the cell when wrong."""
    try:
        values = vars(_flag_parser(name).parse_args(list(argv)))
    except ValueError as e:
        raise ValueError(f"degrade cell {name}: {e}") from None
    return DegradeCell(name, values)


def parse_degrade(text: str) -> DegradeCell:
    """``NAME='--flag value ...'`` (shell-quoted flags of degrade.py) -> DegradeCell."""
    name, sep, rest = text.partition("=")
    name = name.strip()
    if not sep or not name:
        raise ValueError(f"expected NAME='--flag value ...', got {text!r}")
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.+-]*", name) or name == CLEAN:
        raise ValueError(f"degrade cell name {name!r}: use letters, digits and _ . + - (and not '{CLEAN}')")
    try:
        argv = shlex.split(rest)
    except ValueError as e:
        raise ValueError(f"degrade cell {name}: {e}") from None
    return cell(name, argv)


def grid_cells() -> list[DegradeCell]:
    """The standard grid (module docstring): clean, one effect at a time, and all of them."""
    strongest = ["--stereo-k", "0.012", "--depth-lag", "1", "--blur", "1", "--holes", "0.2", "--shift", "4,2"]
    tool = ["--gain-jitter", _text(TOOL_DEFAULTS["gain_jitter"]), "--jpeg", _text(TOOL_DEFAULTS["jpeg"])]
    return [DegradeCell(CLEAN), cell("k006", ["--stereo-k", "0.006"]), cell("k012", ["--stereo-k", "0.012"]),
            cell("lag1", ["--depth-lag", "1"]), cell("blur1", ["--blur", "1"]), cell("holes02", ["--holes", "0.2"]),
            cell("shift42", ["--shift", "4,2"]), cell("all", strongest + tool)]


def check_tool(tool: Path) -> None:
    """FileNotFoundError naming the flag when the degrade tool folder has no degrade.py."""
    if not (Path(tool) / "degrade.py").is_file():
        raise FileNotFoundError(f"--degrade-tool {tool}: no degrade.py (give the degrade tool's folder)")


def _record(c: DegradeCell, seed: int, source: Path) -> dict:
    try:
        made_by = json.loads((Path(source) / RECORD).read_text())
    except (OSError, ValueError):
        made_by = None
    return {"degrade": c.argv(), "seed": seed, "source": str(Path(source).resolve()), "source_record": made_by}


def make_degraded(source: Path, c: DegradeCell, seed: int, cache: Path, tool: Path = DEFAULT_TOOL,
                  python: str = sys.executable) -> tuple[Path, list[str] | None]:
    """The copy of the clip ``source`` degraded by cell ``c`` with ``seed``, under ``cache``; made unless cached.

    Returns (folder, the command run or None when the cached copy was reused).
    """
    if c.is_clean:
        raise ValueError("the clean cell is the clip itself, nothing to make")
    folder = Path(cache) / c.folder_name(Path(source).name, seed)
    record = _record(c, seed, source)
    if is_recorded(folder, record):
        return folder, None
    check_tool(tool)
    cmd = [python, str(Path(tool) / "degrade.py"), str(source), str(folder), "--seed", str(seed), *c.argv(),
           "--force"]
    return folder, run_recorded(folder, record, cmd, "degrade tool")

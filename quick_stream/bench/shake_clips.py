"""Known-shake clips for the quality benchmark, made with the external ``shake`` tool, and its scorer.

The tool (a folder with ``inject.py`` and ``score_rotation.py``, given by path) adds a known,
purely rotational shake to a TUM-layout RGB-D clip: a rotation about the optical centre maps
the image exactly by a homography, so the shake is known to better than 0.05 deg. For every
shaken clip the same tool, seed and frame range with ``--pitch 0 --yaw 0 --roll 0`` makes its
unshaken reference: the same crop (so the same intrinsics and geometry) and the same
timestamps, with no shake.

Clips are cached: each lives in ``CACHE/<name>`` where the name spells every parameter, and is
reused when its ``bench-clip.json`` (written last, after the tool succeeded) records the same
parameters and source folder. An interrupted clip (no record) is made again.

Scoring the removal: the stabiliser's per-frame corrections go to a text file
(:func:`write_corrections`, ``timestamp qx qy qz qw`` per line, seconds and a Hamilton
quaternion, x y z w), read by ``score_rotation.py SHAKE.txt EST.txt [--reference REF.txt]
--json``; :func:`score_rotation` runs it and returns its JSON.
"""
from __future__ import annotations

import json
import math
import subprocess
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Iterable

import numpy as np
from scipy.spatial.transform import Rotation

from ..core.path.tilt import effective_rotation

DEFAULT_TOOL = Path("../shared/tools/shake")
DEFAULT_AMPLITUDES = (0.6, 0.6, 0.8)  # RMS deg: pitch, yaw, roll (the tool's defaults)
RECORD = "bench-clip.json"


@dataclass(frozen=True)
class ShakeSpec:
    """One shaken clip: seed and inclusive frame range of the source, shake RMS per axis (deg)."""

    seed: int
    first: int
    last: int
    pitch: float = DEFAULT_AMPLITUDES[0]
    yaw: float = DEFAULT_AMPLITUDES[1]
    roll: float = DEFAULT_AMPLITUDES[2]

    @classmethod
    def parse(cls, text: str, amplitudes: tuple[float, float, float] = DEFAULT_AMPLITUDES) -> "ShakeSpec":
        """``SEED:FIRST-LAST`` (e.g. ``7:0-149``); ValueError saying what is wrong."""
        seed_s, sep, rng = text.strip().partition(":")
        first_s, dash, last_s = rng.partition("-")
        try:
            if not sep or not dash:
                raise ValueError
            seed, first, last = int(seed_s), int(first_s), int(last_s)
        except ValueError:
            raise ValueError(f"expected SEED:FIRST-LAST (e.g. 7:0-149), got {text!r}") from None
        if first < 0 or last < first:
            raise ValueError(f"frame range must satisfy 0 <= FIRST <= LAST, got {text!r}")
        return cls(seed, first, last, *amplitudes)

    @property
    def frames(self) -> str:
        return f"{self.first}-{self.last}"

    def reference(self) -> "ShakeSpec":
        """The same seed and frames with no shake (same crop, same timestamps)."""
        return ShakeSpec(self.seed, self.first, self.last, 0.0, 0.0, 0.0)

    def folder_name(self, source: Path) -> str:
        return (f"{Path(source).name}_s{self.seed}_f{self.frames}"
                f"_p{self.pitch:g}_y{self.yaw:g}_r{self.roll:g}")

    def label(self) -> str:
        return f"seed {self.seed}, frames {self.frames}, shake {self.pitch:g}/{self.yaw:g}/{self.roll:g} deg"

    def inject_args(self) -> list[str]:
        return ["--seed", str(self.seed), "--frames", self.frames,
                "--pitch", repr(self.pitch), "--yaw", repr(self.yaw), "--roll", repr(self.roll)]


def parse_amplitudes(text: str) -> tuple[float, float, float]:
    """``PITCH,YAW,ROLL`` RMS in degrees (three finite numbers >= 0); ValueError otherwise."""
    try:
        vals = tuple(float(x) for x in text.split(","))
    except ValueError:
        vals = ()
    if len(vals) != 3 or not all(math.isfinite(v) and v >= 0 for v in vals):
        raise ValueError(f"expected PITCH,YAW,ROLL (three numbers >= 0, deg), got {text!r}")
    return vals[0], vals[1], vals[2]


def check_tool(tool: Path) -> None:
    """FileNotFoundError naming what is missing from the shake tool folder."""
    for name in ("inject.py", "score_rotation.py"):
        if not (Path(tool) / name).is_file():
            raise FileNotFoundError(f"shake tool {tool}: no {name} (give the tool's folder with --shake-tool)")


def _record(spec: ShakeSpec, source: Path) -> dict:
    return {"spec": asdict(spec), "source": str(Path(source).resolve())}


def is_recorded(folder: Path, record: dict) -> bool:
    """Whether ``folder`` holds a finished clip made with the parameters ``record`` spells."""
    try:
        return json.loads((Path(folder) / RECORD).read_text()) == record
    except (OSError, ValueError):
        return False


def is_cached(folder: Path, spec: ShakeSpec, source: Path) -> bool:
    return is_recorded(folder, _record(spec, source))


def run_recorded(folder: Path, record: dict, cmd: list[str], what: str) -> list[str]:
    """Make ``folder`` with ``cmd`` (a tool run with ``--force``), then write ``record`` in it, last.

    Any earlier record goes first, so a run that fails or is interrupted leaves no record and the
    clip is made again next time. RuntimeError naming ``what`` and the command when the tool fails.
    """
    Path(folder).parent.mkdir(parents=True, exist_ok=True)
    (Path(folder) / RECORD).unlink(missing_ok=True)
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"{what} failed (rc {r.returncode}): {' '.join(cmd)}\n{r.stderr.strip()[-1500:]}")
    (Path(folder) / RECORD).write_text(json.dumps(record, indent=1))
    return cmd


def make_clip(source: Path, spec: ShakeSpec, cache: Path, tool: Path = DEFAULT_TOOL,
              python: str = sys.executable) -> tuple[Path, list[str] | None]:
    """The clip folder for ``spec`` under ``cache``, made by ``inject.py`` unless cached.

    Returns (folder, the command run or None when the cached clip was reused).
    """
    folder = Path(cache) / spec.folder_name(source)
    record = _record(spec, source)
    if is_recorded(folder, record):
        return folder, None
    check_tool(tool)
    cmd = [python, str(Path(tool) / "inject.py"), str(source), str(folder), *spec.inject_args(), "--force"]
    return folder, run_recorded(folder, record, cmd, "shake tool")


def rotation_part(g: np.ndarray) -> np.ndarray:
    """The rotation a 4x4 (or 3x3) correction renders at the image centre (:func:`.tilt.effective_rotation`,
    docs/method.md 4.5): for one the tilt cap turned in part into an image shift, the whole turn, whose image
    motion at the centre the shift renders; otherwise its linear part projected onto SO(3) (exact for SE(3);
    for SIM(3) it drops the scale)."""
    return effective_rotation(np.asarray(g, float))


def seconds_text(timestamp_ns: int) -> str:
    """Exact decimal seconds of an integer nanosecond timestamp."""
    ns = int(timestamp_ns)
    sign = "-" if ns < 0 else ""
    ns = abs(ns)
    return f"{sign}{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}"


def write_corrections(path: Path, rows: Iterable[tuple[int, np.ndarray]]) -> int:
    """Write ``timestamp qx qy qz qw`` per (timestamp_ns, correction matrix); returns the line count.

    The correction g_s is the pose of the virtual (stabilised) camera relative to the real one,
    X_input = g_s X_stab, so its rotation is score_rotation's C_i (``--kind correction``).
    """
    lines = ["# stabiliser corrections: C_i = rotation of the virtual camera relative to the input camera",
             "# (X_input = C_i X_stab, OpenCV camera axes); Hamilton quaternion",
             "# timestamp qx qy qz qw"]
    n = 0
    for ts_ns, g in rows:
        q = Rotation.from_matrix(rotation_part(g)).as_quat()
        lines.append(f"{seconds_text(ts_ns)} {q[0]:.12f} {q[1]:.12f} {q[2]:.12f} {q[3]:.12f}")
        n += 1
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text("\n".join(lines) + "\n")
    return n


def read_corrections(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps in s, (N, 4) quaternions x y z w) of a file :func:`write_corrections` wrote."""
    ts, qs = [], []
    for line in Path(path).read_text().splitlines():
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        p = s.split()
        ts.append(float(p[0]))
        qs.append([float(x) for x in p[1:5]])
    return np.array(ts), np.array(qs).reshape(-1, 4)


def score_command(tool: Path, shake: Path, estimate: Path, reference: Path | None = None,
                  python: str = sys.executable) -> list[str]:
    cmd = [python, str(Path(tool) / "score_rotation.py"), str(shake), str(estimate)]
    if reference is not None:
        cmd += ["--reference", str(reference)]
    return cmd + ["--json"]


def score_rotation(tool: Path, shake: Path, estimate: Path, reference: Path | None = None,
                   python: str = sys.executable) -> dict:
    """Run ``score_rotation.py`` (kind correction) and return its JSON, plus the command as ``command``."""
    cmd = score_command(tool, shake, estimate, reference, python)
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"score_rotation failed (rc {r.returncode}): {' '.join(cmd)}\n{r.stderr.strip()[-1500:]}")
    out = json.loads(r.stdout)
    out["command"] = cmd
    return out

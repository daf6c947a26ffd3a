"""Where the injected shake that survives stabilization comes from: an ablation on known-shake clips.

For each known-shake clip (and its unshaken reference, :mod:`.shake_clips`) the share of the
injected high-frequency rotation removed, per axis, is scored (``score_rotation.py``, with and
without ``--reference``) for:

* ``as shipped``: the default settings, corrections from the motion stage (the path);
* ``oracle motion``: the same planner fed the reference clip's estimated motions with the
  known shake composed in exactly (camera motion ``S_t^-1 M_t S_{t+1}``): what is left is the
  path's doing, the difference to ``as shipped`` is motion-estimation noise;
* ``rendered``: the rotation the warp actually rendered (each frame's mesh, as a homography
  H between input and output vertices, is the rotation K^-1 H^-1 K of a rotation-only
  correction, projected onto SO(3)): the difference to ``as shipped`` is the warp's. Framing
  zooms about the image centre, which rotates nothing, so it cannot leave rotation;
* single changes to the default: no LK refinement of the flow, no look-ahead, no border fill, no crop budget,
  the EP path of the previous default, and the paper's own path.

``quick-stream bench rotation`` prints one table per clip.
"""
from __future__ import annotations

import copy
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from ..core.lie import get_group
from ..core.motion import MotionEstimate
from ..core.motion.chain import split_over
from ..core.stabilizer import Stabilizer, StabilizerParams
from ..core.flow_stage import FlowStage
from ..core.stages import MotionStage
from ..io.sources.tum import TumSource
from .quality_clips import source_folder
from .variants import parse_settings
from .shake_clips import DEFAULT_TOOL, ShakeSpec, make_clip, score_rotation, write_corrections

DEFAULT_CLIPS = ("7:0-149", "11:100-249")
SINGLE_CHANGES = {
    "no LK refinement": [],  # set on the flow parameters below
    "no look-ahead": ["--lookahead", "0"],
    "no border fill": ["--fill-frames", "0"],
    "no crop budget": ["--max-zoom", "0"],
    "EP path (previous default)": ["--path", "ep", "--max-zoom", "0"],
    "paper path": ["--path", "ep", "--end", "identity", "--lowpass-sigma", "0", "--max-zoom", "0"],
}


@dataclass
class Run:
    """One clip's frames, flows and motions under one set of flow parameters."""

    stamps: list[int]
    flows: list


def _flows(folder: Path, params: StabilizerParams) -> Run:
    fs = FlowStage(params.flow, params.continuity)
    stamps, flows = [], []
    for fr in TumSource(folder):
        stamps.append(fr.timestamp_ns)
        flows += fs.push(fr)
    flows += fs.finish()
    return Run(stamps, flows)


def _plan(run: Run, params: StabilizerParams, motions: list[MotionEstimate] | None = None) -> list[np.ndarray]:
    """Corrections of every frame from the motion stage (``motions`` replace the estimated ones)."""
    stage = MotionStage(params.motion, params.planner, params.warp)
    out: dict[int, np.ndarray] = {}

    def take(batches) -> None:
        for b in batches:
            for c in b:
                out[c.seq] = c.matrix

    take([stage.start(run.flows[0].seq)])
    for i, f in enumerate(run.flows):
        if motions is None:
            take(stage.push(f)[1])
        else:
            for part in split_over(motions[i], f.over):  # a flow that reached over frames: one motion each
                take([stage.planner.push(part, stage.frame_model(f) if part.seq_next == f.seq_next else None)])
    take(stage.finish())
    return [out[s] for s in sorted(out)]


def _motions(run: Run, params: StabilizerParams) -> list[MotionEstimate]:
    stage = MotionStage(params.motion, params.planner, params.warp)
    return [stage.estimator.estimate(f) for f in run.flows]


def read_shake(path: Path) -> np.ndarray:
    """The injected rotations S_i (N, 3, 3) of a ``shake.txt``."""
    from scipy.spatial.transform import Rotation
    q = [ln.split()[1:5] for ln in Path(path).read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    return Rotation.from_quat(np.array(q, float)).as_matrix()


def oracle_motions(reference: list[MotionEstimate], shake: np.ndarray, group: str) -> list[MotionEstimate]:
    """The reference clip's motions with the known shake composed in: S_t^-1 M_t S_{t+1}."""
    g = get_group(group)
    S = np.tile(np.eye(4), (len(shake), 1, 1))
    S[:, :3, :3] = shake
    out = []
    for m in reference:
        o = copy.copy(m)
        o.matrix = np.linalg.inv(S[m.seq]) @ m.matrix @ S[m.seq_next]
        o.twist, o.zeta_bar = g.log(o.matrix), g.log(np.linalg.inv(o.matrix))
        out.append(o)
    return out


def rendered_rotations(folder: Path, params: StabilizerParams) -> list[tuple[int, np.ndarray]]:
    """(timestamp, rotation the warp rendered) per frame: from each mesh's vertex homography."""
    st = Stabilizer(params)
    out = []
    K = next(iter(TumSource(folder, count=1))).intrinsics.K

    def take(batch) -> None:
        for sf in batch:
            m = sf.mesh
            H, _ = cv2.findHomography(m.src.reshape(-1, 2), m.dst.reshape(-1, 2), 0)
            C = np.linalg.inv(K) @ np.linalg.inv(H) @ K
            R4 = np.eye(4)
            R4[:3, :3] = C / np.cbrt(np.linalg.det(C))
            out.append((sf.timestamp_ns, R4))

    for fr in TumSource(folder):
        take(st.push(fr))
    take(st.finish())
    return out


def run_clip(src: Path, spec: ShakeSpec, cache: Path, tool: Path, settings: list[str],
             progress: Callable[[str], None] | None = None) -> dict:
    """``progress``: told each step (making the clips, their flows, each row scored)."""
    say = progress or (lambda _msg: None)
    say(f"clip {spec.seed}:{spec.first}-{spec.last}: making the shaken and reference clips")
    shaken, _ = make_clip(src, spec, cache, tool)
    ref, _ = make_clip(src, spec.reference(), cache, tool)
    base = parse_settings(settings).params
    say(f"{shaken.name}: scene flow of both clips")
    runs = {k: (_flows(shaken, base), _flows(ref, base)) for k in ("lk",)}
    no_lk = copy.deepcopy(base)
    no_lk.flow.refine = "none"
    say(f"{shaken.name}: scene flow of both clips without LK refinement")
    runs["none"] = (_flows(shaken, no_lk), _flows(ref, no_lk))
    rows: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="qs_rot_") as tmp:
        tmp_p = Path(tmp)

        def score(name: str, est: list[tuple[int, np.ndarray]], refc: list[tuple[int, np.ndarray]]) -> None:
            say(f"{shaken.name}: scored {name}")
            e, r = tmp_p / "est.txt", tmp_p / "ref.txt"
            write_corrections(e, est)
            write_corrections(r, refc)
            with_ref = score_rotation(tool, shaken / "shake.txt", e, r)
            rows[name] = {"removed_with_reference": with_ref["removed_fraction"],
                          "removed": score_rotation(tool, shaken / "shake.txt", e)["removed_fraction"],
                          "residual_deg": with_ref["residual_hp_rms_deg"],
                          "injected_deg": with_ref["injected_hp_rms_deg"]}

        s_run, r_run = runs["lk"]
        ref_corr = list(zip(r_run.stamps, _plan(r_run, base)))
        score("as shipped", list(zip(s_run.stamps, _plan(s_run, base))), ref_corr)
        oracle = oracle_motions(_motions(r_run, base), read_shake(shaken / "shake.txt"), base.motion.group)
        score("oracle motion", list(zip(s_run.stamps, _plan(s_run, base, oracle))), ref_corr)
        score("rendered", rendered_rotations(shaken, base), rendered_rotations(ref, base))
        for name, extra in SINGLE_CHANGES.items():
            p = no_lk if name == "no LK refinement" else parse_settings(settings + extra).params
            s2, r2 = runs["none"] if name == "no LK refinement" else runs["lk"]
            score(name, list(zip(s2.stamps, _plan(s2, p))), list(zip(r2.stamps, _plan(r2, p))))
    return {"clip": shaken.name, "rows": rows}


def run(data: Path, clips: list[ShakeSpec], cache: Path, tool: Path = DEFAULT_TOOL,
        settings: list[str] | None = None, progress: Callable[[str], None] | None = None) -> dict:
    cv2.setNumThreads(1)
    src = source_folder(data)
    return {"settings": settings or [],
            "clips": [run_clip(src, s, cache, tool, settings or [], progress) for s in clips]}


def format_table(r: dict) -> str:
    lines = []
    for c in r["clips"]:
        lines.append(f"{c['clip']}: injected high-frequency rotation removed (%), pitch / yaw / roll / total")
        lines.append(f"{'':28s} {'with --reference':>27s}   {'without':>25s}   residual deg (with ref)")
        for name, row in c["rows"].items():
            a = " ".join(f"{100 * x:6.1f}" for x in row["removed_with_reference"])
            b = " ".join(f"{100 * x:6.1f}" for x in row["removed"])
            d = " ".join(f"{x:.3f}" for x in row["residual_deg"])
            lines.append(f"{name:28s} {a}   {b}   {d}")
    return "\n".join(lines)


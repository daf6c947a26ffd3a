"""The pipeline's estimates on the wire: ``flow``, ``motion`` and ``correction`` messages
(docs/wire-format.md), encoded and decoded; :mod:`.messages` dispatches to them."""
from __future__ import annotations

from typing import Any

import numpy as np

from ...core.motion import KINDS as MOTION_KINDS, MotionEstimate
from ...core.path.planner import CORRECTION_MOTIONS, Correction
from ...core.release_tags import Tag
from ...core.sceneflow import SceneFlowResult
from . import ranges
from .codec import MAX_SEQ_LIST, Reader, WireError, encode_array, float_list, pack, seq_list
from .fields import Decoded, intrinsics_fields, read_intrinsics, text
from .flowpack import compact_fields, decode_compact

GROUP_DIMS = {"se3": 6, "sim3": 7, "sa3": 11, "ga3": 12}
MAX_FLOW_POINTS = 10_000_000


# --- flow ---------------------------------------------------------------------------------------

_FLOW_ARRAYS = (("points", 3), ("displacements", 3), ("weights", None), ("pixels", 2), ("pixels_next", 2))


def encode_flow(flow: SceneFlowResult, stream: str, shed: Any = ()) -> bytes:
    """A SceneFlowResult as a ``flow`` message: the compact layout of version 2 when it gives every
    array back bit for bit (the scene flow's own results: :mod:`.flowpack`), else version 1's five
    float32 arrays. ``shed``: the frames the flow stage shed since its previous flow (all before
    ``seq_next``; the field is left out when there are none)."""
    compact = compact_fields(flow)
    f: dict[str, Any] = {"seq_next": int(flow.seq_next)}
    if (named := seq_list("shed", shed, max(int(flow.seq), int(flow.seq_next)), stream, flow.seq)) is not None:
        f["shed"] = named
    if compact is None:
        for name, _ in _FLOW_ARRAYS:
            f[name] = encode_array(getattr(flow, name), "<f4")
    else:
        f.update(compact)
    f["intrinsics"] = intrinsics_fields(flow.intrinsics)
    f["intrinsics_next"] = intrinsics_fields(flow.intrinsics_next)
    f["counts"] = {str(k): int(v) for k, v in flow.counts.items()}
    f["problem"] = text("problem", flow.problem)
    if flow.over:
        f["over"] = over_list(flow, stream)
    return pack(f, "flow", stream, flow.seq, version=1 if compact is None else 2)


def _decode_flow(r: Reader) -> Decoded:
    K0, K1 = read_intrinsics(r, "intrinsics"), read_intrinsics(r, "intrinsics_next")
    if r.version >= 2:
        arrays = decode_compact(r, MAX_FLOW_POINTS, K0, K1)
    else:
        arrays = {}
        n = None
        for name, cols in _FLOW_ARRAYS:
            a = r.array(name, "<f4", 1 if cols is None else 2, () if cols is None else (cols,),
                        finite=True, max_elems=3 * MAX_FLOW_POINTS)
            if n is None:
                n = a.shape[0]
            elif a.shape[0] != n:
                raise r.error(name, f"{a.shape[0]} rows but points has {n}")
            arrays[name] = a.astype(np.float64)
    counts_r = r.map("counts")
    counts = {}
    for key in counts_r.d:
        counts[key] = counts_r.int(key)
    seq_next = r.int("seq_next", min=0)
    flow = SceneFlowResult(
        r.seq, seq_next, arrays["points"], arrays["displacements"], arrays["weights"],
        arrays["pixels"], arrays["pixels_next"], K0, K1, counts, r.str("problem"), read_over(r, seq_next),
    )
    return Decoded("flow", flow, r.stream, r.seq, version=r.version, shed=r.seqs("shed", max(r.seq, seq_next)))


def over_list(flow: SceneFlowResult, stream: str) -> list[int]:
    """A flow's ``over`` for the wire: increasing frame seqs strictly between its ``seq`` and ``seq_next``."""
    out = [int(x) for x in flow.over]
    if not _between(out, int(flow.seq), int(flow.seq_next)):
        raise WireError(f"expected increasing frame seqs strictly between {flow.seq} and {flow.seq_next}, got "
                        f"{out[:5]}", field="over", stream=stream, seq=flow.seq)
    return out


def read_over(r: Reader, seq_next: int) -> tuple[int, ...]:
    """A flow's ``over`` (() when absent), checked as :func:`over_list` writes it."""
    over = r.seqs("over", max(r.seq, seq_next))
    if not _between(list(over), r.seq, seq_next):
        raise r.error("over", f"expected increasing frame seqs strictly between {r.seq} and {seq_next}, got "
                              f"{list(over[:5])!r}")
    return over


def _between(seqs: list[int], lo: int, hi: int) -> bool:
    return len(seqs) <= MAX_SEQ_LIST and all(lo < a < b for a, b in zip(seqs, seqs[1:] + [hi]))


# --- motion -------------------------------------------------------------------------------------

def encode_motion(m: MotionEstimate, stream: str) -> bytes:
    """A MotionEstimate as a ``motion`` message (matrix 16 float64 row-major; rms_px may be NaN)."""
    dim = GROUP_DIMS.get(m.group)
    if dim is None:
        raise WireError(f"unknown group {m.group!r}", field="group", stream=stream, seq=m.seq)
    f = {
        "seq_next": int(m.seq_next), "group": m.group, "estimator": text("estimator", m.estimator),
        "matrix": float_list("matrix", m.matrix, 16), "twist": float_list("twist", m.twist, dim),
        "zeta_bar": None if m.zeta_bar is None else float_list("zeta_bar", m.zeta_bar, dim),
        "valid": bool(m.valid), "reason": text("reason", m.reason), "n_points": int(m.n_points),
        "inlier_ratio": float(m.inlier_ratio), "rms_px": float(m.rms_px),
        "kind": _kind("kind", m.kind, MOTION_KINDS, stream, m.seq),
        "covariance": None if m.covariance is None else float_list("covariance", m.covariance, dim * dim),
    }
    return pack(f, "motion", stream, m.seq)


def _kind(name: str, value: str, allowed: tuple[str, ...], stream: str, seq: int) -> str:
    if value not in allowed:
        raise WireError(f"{name} must be one of {', '.join(allowed)}, got {value!r}", field=name, stream=stream,
                        seq=seq)
    return value


def motion_transform(r: Reader) -> tuple[int, np.ndarray]:
    """(seq_next, 4x4 matrix) of a motion message's Reader, those fields checked as :func:`decode` checks
    them: what a reader of a message checked whole before (a recorder's views) needs, without the rest."""
    group = r.str("group")
    if group not in GROUP_DIMS:
        raise r.error("group", f"unknown group {group!r} (known: {', '.join(GROUP_DIMS)})")
    return r.int("seq_next", min=0), matrix_field(r, group)


def matrix_field(r: Reader, group: str | None = None) -> np.ndarray:
    """The 4x4 ``matrix`` field of a correction's (or, with its ``group``, a motion's) Reader, checked as
    :func:`decode` checks it: what a reader of a correction checked whole before needs of it."""
    return ranges.transform(r, "matrix", r.floats("matrix", 16).reshape(4, 4), group)


def _decode_motion(r: Reader) -> Decoded:
    group = r.str("group")
    dim = GROUP_DIMS.get(group)
    if dim is None:
        raise r.error("group", f"unknown group {group!r} (known: {', '.join(GROUP_DIMS)})")
    zeta = r.floats("zeta_bar", dim, optional=True)
    kind = r.str("kind", optional=True) or "fit"  # optional (added within v1): a motion without it was a fit
    if kind not in MOTION_KINDS:
        raise r.error("kind", f"expected one of {', '.join(MOTION_KINDS)}, got {kind!r}")
    cov = r.floats("covariance", dim * dim, optional=True)
    inliers = r.float("inlier_ratio")
    if not 0.0 <= inliers <= 1.0:
        raise r.error("inlier_ratio", f"must be in [0, 1], got {inliers:g}")
    m = MotionEstimate(
        r.seq, r.int("seq_next", min=0), group, r.str("estimator"),
        matrix_field(r, group), r.floats("twist", dim), r.bool("valid"), r.str("reason"),
        r.int("n_points", min=0),
        inliers, r.float("rms_px", finite=False), zeta,
        kind=kind, covariance=None if cov is None else cov.reshape(dim, dim),
    )
    return Decoded("motion", m, r.stream, r.seq)


# --- correction ---------------------------------------------------------------------------------

def encode_correction(c: Correction, stream: str, tag: Tag | tuple[int, int, int] | None = None) -> bytes:
    """A Correction as a ``correction`` message, with the framing zoom planned with the path (``c.zoom``)
    and its release ``tag`` = (release id, index in it, release size[, closed by]): the planner's release it
    belongs to (:class:`~quick_stream.core.release_tags.Tag`)."""
    zoom = c.zoom
    if zoom is not None and not (np.isfinite(zoom) and zoom > 0):
        raise WireError(f"zoom must be finite and > 0, got {zoom}", field="zoom", stream=stream, seq=c.seq)
    if tag is not None and not (len(tag) in (3, 4) and tag[0] >= 0 and 0 <= tag[1] < tag[2]):
        raise WireError(f"the release tag (field batch) must be (release >= 0, 0 <= index < size, size), got {tag}",
                        field="batch", stream=stream, seq=c.seq)
    closed_by = None if tag is None else Tag(*tag).closed_by
    f = {"matrix": float_list("matrix", c.matrix, 16), "segment": int(c.segment), "keyframe": bool(c.keyframe),
         "valid": bool(c.valid), "reason": text("reason", c.reason), "zoom": None if zoom is None else float(zoom),
         "batch": None if tag is None else [int(x) for x in tag[:3]],  # the tag's wire field
         "closed_by": None if closed_by is None else int(closed_by),
         "camera": None if c.camera is None else float_list("camera", c.camera, 16), "chain": int(c.chain),
         "motion": _kind("motion", c.motion, CORRECTION_MOTIONS, stream, c.seq)}
    if (named := seq_list("shed", c.shed, c.seq, stream, c.seq)) is not None:
        f["shed"] = named
    return pack(f, "correction", stream, c.seq)


def _decode_correction(r: Reader) -> Decoded:
    camera = r.floats("camera", 16, optional=True)
    camera = None if camera is None else ranges.transform(r, "camera", camera.reshape(4, 4))
    chain = r.int("chain", optional=True)
    motion = r.str("motion", optional=True) or "fit"  # optional (added within v1)
    if motion not in CORRECTION_MOTIONS:
        raise r.error("motion", f"expected one of {', '.join(CORRECTION_MOTIONS)}, got {motion!r}")
    c = Correction(r.seq, matrix_field(r), r.int("segment"),
                   r.bool("keyframe"), r.bool("valid"), r.str("reason"),
                   ranges.zoom(r, "zoom", r.float("zoom", positive=True, optional=True)), camera,
                   -1 if chain is None else chain, motion, r.seqs("shed", r.seq))
    tag, closed_by = r.get("batch", optional=True), r.int("closed_by", optional=True)  # the release tag
    if tag is not None:
        if (not isinstance(tag, list) or len(tag) != 3 or not all(type(x) is int for x in tag)
                or not (tag[0] >= 0 and 0 <= tag[1] < tag[2])):
            raise r.error("batch", f"expected [release >= 0, 0 <= index < size, size], got {tag!r}")
        tag = Tag(*tag, closed_by)
    return Decoded("correction", c, r.stream, r.seq, tag=tag)

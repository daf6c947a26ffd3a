"""Re-run one stage from a recording's logged inputs and compare with its logged outputs.

The services add only transport to the library (:mod:`quick_stream.core.stages`,
:mod:`quick_stream.core.release`), so a stage re-run from what the recorder logged must reproduce
what it logged, and it runs the service's own objects. ``flow``: each logged flow (seq ->
seq_next) from exactly the two logged frames it names (the service may have dropped frames
between). ``motion``: the logged flows in order through one
:class:`~quick_stream.core.stages.MotionDriver`, as the motion service runs it (``end``: finish
and restart); motions and release-tagged corrections, the forwarded ``end`` included, compared
in order. Both compare bytes. ``render``: the logged corrections through one
:class:`~quick_stream.core.release.RenderDriver`, as the render service runs it, fed the logged
frames each release needs (orphans as the service renders them; ``end``: the stream's finish),
each frame encoded as its logged message was and compared decoded (seq, t_ns, image, zoom, flags;
the bytes carry wall-clock latency stamps). ``end`` messages split a channel into stream runs,
paired in order across channels. Bit-exact results need OpenCV run as the services run it
(``cv2.setNumThreads(1)``).
"""
from __future__ import annotations

import os
from collections import defaultdict, deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..core.release import RenderDriver
from ..core.release_tags import Tag
from ..core.path.planner import Correction
from ..core.render_stage import StabilizedFrame
from ..core.sceneflow import SceneFlow
from ..core.params import StabilizerParams
from ..core.stages import MotionDriver
from ..core.settings import settings_digest
from ..io.recording import RecordingError, read_messages
from ..io.settings_file import recording_settings
from ..io.stabilizer_flags import default_settings
from ..io.sources import SourceError
from ..io.sources.mcap_replay import recorded_streams
from ..stream import keys
from ..stream.wire import StabilizedImage, WireError, decode
from ..stream.wire.codec import unpack
from ..stream.wire.messages import encode_correction, encode_end, encode_flow, encode_motion, encode_stabilized

STAGES = ("flow", "motion", "render")
INPUTS = {"flow": ("frame",), "motion": ("flow",), "render": ("frame", "correction")}
OUTPUTS = {"flow": ("flow",), "motion": ("motion", "correction"), "render": ("stabilized",)}


class RerunError(ValueError):
    """The stage cannot be re-run from this recording; the message names the file and the problem."""


@dataclass
class Mismatch:
    """One logged output not reproduced: the ``fields`` that differ, or ``missing`` (not
    reproduced), ``extra`` (reproduced, never logged), ``decode`` or ``input`` (bad message)."""

    topic: str
    seq: int | None
    fields: tuple[str, ...]
    detail: str = ""

    def __str__(self) -> str:
        return (f"{self.topic} seq {'?' if self.seq is None else self.seq}: {', '.join(self.fields)}"
                + (f" ({self.detail})" if self.detail else ""))


@dataclass
class TopicResult:
    """One output channel: outputs logged, reproduced identically, and made but never logged."""

    topic: str
    logged: int = 0
    identical: int = 0
    extra: int = 0


@dataclass
class RerunResult:
    """What :func:`rerun_stage` found: inputs read, per output channel counts, mismatches, notes."""

    path: str
    stage: str
    stream: str
    inputs: dict[str, int] = field(default_factory=dict)
    outputs: list[TopicResult] = field(default_factory=list)
    mismatches: list[Mismatch] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.mismatches and all(t.identical == t.logged and not t.extra for t in self.outputs)

    @property
    def logged(self) -> int:
        return sum(t.logged for t in self.outputs)

    @property
    def identical(self) -> int:
        return sum(t.identical for t in self.outputs)


@dataclass
class _Msg:
    type: str | None  # None: the envelope does not decode
    seq: int | None
    data: bytes


def _header(data: bytes) -> _Msg:
    try:
        r = unpack(data)
        return _Msg(r.type, r.seq, data)
    except WireError:
        return _Msg(None, None, data)


def _runs(msgs: list[_Msg], mtype: str) -> list[tuple[list[_Msg], _Msg | None]]:
    """A channel's ``mtype`` messages (undecodable ones kept, to be reported) split at its
    ``end`` messages into stream runs: (the run's messages, its end message or None)."""
    out: list[tuple[list[_Msg], _Msg | None]] = []
    cur: list[_Msg] = []
    for m in msgs:
        if m.type == "end":
            out.append((cur, m))
            cur = []
        elif m.type in (mtype, None):
            cur.append(m)
    if cur or not out:
        out.append((cur, None))
    return out


def _nth(runs: list[tuple[list[_Msg], bool]], i: int) -> list[_Msg]:
    """Run ``i``'s messages; none when the channel has fewer runs."""
    return runs[i][0] if i < len(runs) else []


def resolve_stream(path: str | os.PathLike, stream: str | None) -> str:
    """``stream`` checked, or the recording's only stream; RerunError naming the choices otherwise."""
    if stream is not None:
        try:
            return keys.check_stream(stream)
        except ValueError as e:
            raise RerunError(str(e)) from None
    try:
        streams = sorted(recorded_streams(path, stage=None))
    except SourceError as e:
        raise RerunError(str(e)) from None
    if len(streams) == 1:
        return streams[0]
    if not streams:
        raise RerunError(f"{path}: no quick-stream channels ({keys.PREFIX}/<stream>/<stage>)")
    raise RerunError(f"{path}: several streams ({', '.join(streams)}); choose one with --stream")


def _differing(a: Any, b: Any, prefix: str = "", depth: int = 2) -> list[str]:
    """Dotted names of the (nested) map fields where two unpacked messages differ."""
    if not (isinstance(a, dict) and isinstance(b, dict)) or depth == 0:
        return [] if a == b else [prefix.rstrip(".") or "bytes"]
    out = []
    for k in sorted(set(a) | set(b), key=str):
        if k not in a or k not in b:
            out.append(f"{prefix}{k}")
        elif a[k] != b[k]:
            out.extend(_differing(a[k], b[k], f"{prefix}{k}.", depth - 1))
    return out


def _compare_bytes(t: TopicResult, got: bytes, logged: _Msg, res: RerunResult) -> None:
    if got == logged.data:
        t.identical += 1
        return
    try:
        diff = tuple(_differing(unpack(got).d, unpack(logged.data).d)) or ("encoding",)
        res.mismatches.append(Mismatch(t.topic, logged.seq, diff))
    except WireError as e:
        res.mismatches.append(Mismatch(t.topic, logged.seq, ("decode",), str(e)))


def _compare_sequence(t: TopicResult, got: list[bytes], logged: list[_Msg], res: RerunResult) -> None:
    """Reproduced and logged messages of one channel compared in order."""
    t.logged += len(logged)
    for i in range(max(len(got), len(logged))):
        if i >= len(got):
            res.mismatches.append(Mismatch(t.topic, logged[i].seq, ("missing",), f"message {i} not reproduced"))
        elif i >= len(logged):
            t.extra += 1
            res.mismatches.append(Mismatch(t.topic, _header(got[i]).seq, ("extra",), f"message {i} never logged"))
        else:
            _compare_bytes(t, got[i], logged[i], res)


def _rerun_flow(ch: dict[str, list[_Msg]], stream: str, params: StabilizerParams, res: RerunResult) -> None:
    t = TopicResult(keys.key(stream, "flow"))
    res.outputs.append(t)
    frame_runs = _runs(ch["frame"], "frame")
    sf = SceneFlow(params.flow)
    for i, (flows, _) in enumerate(_runs(ch["flow"], "flow")):
        frames = {m.seq: m.data for m in reversed(_nth(frame_runs, i)) if m.type == "frame"}
        for m in flows:
            t.logged += 1
            try:
                logged = decode(m.data).obj
            except WireError as e:
                res.mismatches.append(Mismatch(t.topic, m.seq, ("decode",), str(e)))
                continue
            lost = [s for s in (logged.seq, logged.seq_next) if s not in frames]
            try:
                pair = [decode(frames[s], color="luma").obj for s in (logged.seq, logged.seq_next)] if not lost else []
            except WireError as e:
                lost = [str(e)]
            if lost:
                res.mismatches.append(Mismatch(t.topic, m.seq, ("input",), f"input frame(s) not usable: {lost}"))
                continue
            _compare_bytes(t, encode_flow(sf.compute(*pair), stream), m, res)


def _tagged(corrections: list[tuple[Correction, Tag]], stream: str) -> list[bytes]:
    return [encode_correction(c, stream, tag=tag) for c, tag in corrections]


def _rerun_motion(ch: dict[str, list[_Msg]], stream: str, params: StabilizerParams, res: RerunResult) -> None:
    driver = MotionDriver(params.motion, params.planner, params.warp)
    motions: list[bytes] = []
    corrections: list[bytes] = []
    for m in ch["flow"]:
        try:
            msg = decode(m.data)
        except WireError:
            continue  # the service logs and skips it too
        if msg.type == "end":
            corrections.extend(_tagged(driver.finish(), stream))
            corrections.append(encode_end(msg.obj, stream))
            driver.restart()
        elif msg.type == "flow" and (out := driver.push(msg.obj, msg.shed)) is not None:
            motions.extend(encode_motion(x, stream) for x in out[0])
            corrections.extend(_tagged(out[1], stream))
    if driver.refused:
        res.notes.append(f"{driver.refused} flows refused (stale or duplicate), as the service refuses them")
    for name, got in (("motion", motions), ("correction", corrections)):
        t = TopicResult(keys.key(stream, name))
        res.outputs.append(t)
        _compare_sequence(t, got, ch[name], res)


def _render_run(driver: RenderDriver, frames: list[_Msg], corrections: list[_Msg],
                ended: _Msg | None) -> list[StabilizedFrame]:
    """One stream run through the render service's driver, frames fed as its releases need them
    (every frame of a release there: each renders as soon as it is complete, as in the service)."""
    held = deque((m.seq, m.data) for m in frames if m.type == "frame")
    out: list[StabilizedFrame] = []

    def feed(upto: int | None) -> None:
        while held and (upto is None or held[0][0] <= upto):
            seq, data = held.popleft()
            driver.add_frame(seq, lambda d=data: decode(d).obj)  # refused (out of order, duplicate) as by the service

    for m in corrections:
        try:
            msg = decode(m.data)
        except WireError:
            continue
        driver.add_correction(msg.obj, msg.tag)
        for rel in driver.due(force=True):
            feed(max(c.seq for c in rel.corrections))
            out.extend(r.frame for r in driver.render(rel))
    if ended is not None:
        feed(None)
        try:
            marker = decode(ended.data).obj  # the frames it names as shed are let go, as by the service
        except WireError:
            marker = None
        driver.end(marker)
        for _, group in driver.finish():
            out.extend(r.frame for r in group)
        driver.restart()
    return out


def _compare_image(t: TopicResult, sf: StabilizedFrame, m: _Msg, stream: str, quality: int,
                   res: RerunResult) -> None:
    """A reproduced frame against its logged message, decoded, encoded as that message was."""
    try:
        logged = decode(m.data)
    except WireError as e:
        res.mismatches.append(Mismatch(t.topic, m.seq, ("decode",), str(e)))
        return
    want, img = logged.obj, StabilizedImage(sf.seq, sf.timestamp_ns, sf.image, sf.zoom, sf.flags)
    got = decode(encode_stabilized(img, stream, color=logged.encoding, quality=quality)).obj
    diff = tuple(name for name, same in (
        ("image", got.image.shape == want.image.shape and np.array_equal(got.image, want.image)),
        ("t_ns", got.timestamp_ns == want.timestamp_ns), ("zoom", got.zoom == want.zoom),
        ("flags", list(got.flags) == list(want.flags))) if not same)
    if diff:
        res.mismatches.append(Mismatch(t.topic, m.seq, diff))
    else:
        t.identical += 1


def _rerun_render(ch: dict[str, list[_Msg]], stream: str, params: StabilizerParams, res: RerunResult,
                  quality: int, max_frames: int) -> None:
    t = TopicResult(keys.key(stream, "stabilized"))
    res.outputs.append(t)
    frame_runs, logged_runs = _runs(ch["frame"], "frame"), _runs(ch["stabilized"], "stabilized")
    driver = RenderDriver(params.warp, params.framing, max_frames=max_frames)
    for i, (corrections, ended) in enumerate(_runs(ch["correction"], "correction")):
        made = _render_run(driver, _nth(frame_runs, i), corrections, ended)
        by_seq: dict[int, deque[StabilizedFrame]] = defaultdict(deque)
        for sf in made:
            by_seq[sf.seq].append(sf)
        for m in _nth(logged_runs, i):
            t.logged += 1
            if m.seq is None or not by_seq[m.seq]:
                res.mismatches.append(Mismatch(t.topic, m.seq, ("missing",), "not reproduced"))
            else:
                _compare_image(t, by_seq[m.seq].popleft(), m, stream, quality, res)
        for seq, left in sorted(by_seq.items()):
            t.extra += len(left)
            res.mismatches.extend(Mismatch(t.topic, seq, ("extra",), "rendered but never logged") for _ in left)
    st = driver.stats()
    totals = {"orphans": st["orphans"], "missing": st["missing"], "dropped": st["dropped"], "bad frames": st["bad_frames"]}
    if any(totals.values()):
        res.notes.append("render stage: " + ", ".join(f"{v} {k}" for k, v in totals.items() if v))


def _settings_notes(stage: str, params: StabilizerParams, recorded: StabilizerParams | None,
                    stats: list[_Msg]) -> list[str]:
    """What to say about the settings: the recording holds none, they are not the recording's, or the
    stage's service said (its stats' ``settings`` digest) that it ran with others."""
    notes = []
    mine = settings_digest(params)
    if recorded is None:
        notes.append("the recording holds no settings record: re-ran with the defaults and the flags given")
    elif settings_digest(recorded) != mine:
        notes.append(f"re-ran with settings {mine}, not the recording's {settings_digest(recorded)} "
                     "(--settings or flags given)")
    ran: set[str] = set()
    for m in stats:
        try:
            d = decode(m.data)
        except WireError:
            continue
        if d.type == "stats" and d.obj.service == stage and isinstance(d.obj.values.get("settings"), str):
            ran.add(d.obj.values["settings"])
    if ran - {mine}:
        notes.append(f"the {stage} service ran with settings {', '.join(sorted(ran))}; re-ran with {mine}")
    return notes


def rerun_stage(path: str | os.PathLike, stage: str, stream: str | None = None,
                params: StabilizerParams | None = None, *, quality: int = 90, max_frames: int = 150) -> RerunResult:
    """Re-run ``stage`` (flow, motion or render) of ``stream`` from the recording at ``path``.

    ``stream`` None: the recording's only stream. ``params``: the settings to re-run with, by
    default the recording's own (its settings record; :mod:`quick_stream.io.settings_file`), else
    the defaults. The notes say when they are not what the stage's service ran with. ``quality``
    (JPEG) and ``max_frames`` are the render service's ``--quality`` and ``--max-frames``. Raises
    :class:`RerunError` when the recording is missing or unreadable or has no logged inputs or
    outputs of the stage.
    """
    if stage not in STAGES:
        raise RerunError(f"stage must be one of {', '.join(STAGES)}, got {stage!r}")
    path = Path(path)
    if not path.is_file():
        raise RerunError(f"{path}: {'not a regular file' if path.exists() else 'no such file'}")
    names = INPUTS[stage] + tuple(n for n in OUTPUTS[stage] if n not in INPUTS[stage]) + ("stats",)
    try:
        recorded = recording_settings(path)
        if params is None:
            params = recorded or default_settings()
        stream = resolve_stream(path, stream)
        topics = {keys.key(stream, n): n for n in names}
        ch: dict[str, list[_Msg]] = {n: [] for n in names}
        for topic, _, data in read_messages(path, topics=list(topics)):
            ch[topics[topic]].append(_header(bytes(data)))
    except RecordingError as e:
        raise RerunError(str(e)) from None
    for kind, group in (("inputs", INPUTS[stage]), ("outputs", OUTPUTS[stage])):
        for n in group:
            if not any(m.type == n for m in ch[n]):
                raise RerunError(f"{path}: no logged {kind} for the {stage} stage: no {n!r} messages "
                                 f"on {keys.key(stream, n)}")
    res = RerunResult(str(path), stage, stream, {keys.key(stream, n): len(ch[n]) for n in INPUTS[stage]})
    res.notes += _settings_notes(stage, params, recorded, ch["stats"])
    if stage == "flow":
        _rerun_flow(ch, stream, params, res)
    elif stage == "motion":
        _rerun_motion(ch, stream, params, res)
    else:
        _rerun_render(ch, stream, params, res, quality, max_frames)
    return res

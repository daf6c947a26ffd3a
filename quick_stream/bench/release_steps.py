"""Where the first frame of each release spends its time, read from the pipeline bench's recording.

The renderer frames a planner release as a whole, so the first frame of a release is the one that
waits longest beyond its segment (``bench pipeline``'s *processing, first of batch*). This splits
that wait into the stages it crosses, from the times the recorder received each message (its
log times: one clock for all, taken on arrival at a recorder that runs at a lower priority, so each
step is as the recorder saw it, a few ms late under load):

* *flow*: the frame that closed the release (the correction's ``closed_by``) -> the flow of the pair
  it ends;
* *motion and path*: that flow -> its motion (the motion service solves the closed segment's path
  before it publishes);
* *correction*: that motion -> the release's first correction;
* *render*: the release's first correction -> its first stabilized frame (the warps and border
  estimates of that frame and the ``fill_lookahead`` frames after it, docs/method.md (14a), then the
  frame's render and JPEG).

Releases without ``closed_by`` (the end of a stream), or missing any of the messages, are left out.
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterable

import numpy as np

from ..io.recording import read_messages
from ..stream import keys
from ..stream.wire import WireError
from ..stream.wire.codec import unpack

STEPS = ("flow", "motion and path", "correction", "render")
STAGES = ("frame", "flow", "motion", "correction", "stabilized")


def step_times(messages: Iterable[tuple[str, int, bytes]], stream: str = "cam0",
               from_seq: int = 0) -> dict[str, list[float]]:
    """Per step of :data:`STEPS`, its ms for each release whose first frame is at or after ``from_seq``:
    ``messages`` are (topic, log_time_ns, wire bytes) as :func:`~quick_stream.io.recording.read_messages`
    yields them."""
    arrived: dict[str, dict[int, int]] = {s: {} for s in STAGES}  # stage -> seq (the pair's newest) -> ns
    firsts: list[tuple[int, int, int]] = []  # (first seq, closed_by, ns) of each release's first correction
    topics = {keys.key(stream, s): s for s in STAGES}
    for topic, t_ns, data in messages:
        stage = topics.get(topic)
        if stage is None:
            continue
        try:
            r = unpack(data)
            if r.type != stage:  # an end marker, or a message of another type on the key
                continue
            seq = r.int("seq_next") if stage in ("flow", "motion") else r.seq
        except WireError:  # a malformed message has no time to give
            continue
        if stage == "correction":
            batch, closed_by = r.d.get("batch"), r.d.get("closed_by")
            if isinstance(batch, list) and len(batch) == 3 and batch[1] == 0 and type(closed_by) is int:
                firsts.append((seq, closed_by, t_ns))
        else:
            arrived[stage].setdefault(seq, t_ns)
    out: dict[str, list[float]] = {s: [] for s in STEPS}
    for first, closed_by, t_corr in firsts:
        t = [arrived["frame"].get(closed_by), arrived["flow"].get(closed_by), arrived["motion"].get(closed_by),
             t_corr, arrived["stabilized"].get(first)]
        if first < from_seq or None in t:
            continue
        for step, a, b in zip(STEPS, t, t[1:]):
            out[step].append((b - a) / 1e6)
    return out


def release_steps(recording: str | Path, stream: str = "cam0", from_seq: int = 0) -> dict[str, dict[str, float]]:
    """:func:`step_times` of a recording, as p50/p90/max ms and the number of releases per step."""
    got = step_times(read_messages(recording, [keys.key(stream, s) for s in STAGES]), stream, from_seq)
    return {step: {"p50": round(float(np.percentile(v, 50)), 1), "p90": round(float(np.percentile(v, 90)), 1),
                   "max": round(float(np.max(v)), 1), "n": len(v)} for step, v in got.items() if v}

"""The clips of ``quick-stream bench quality``: real clips, known-shake clips made from any of them,
and degraded copies of those (:mod:`.degrade_clips`).

* Real clips: folders (TUM layout) under ``--data`` named by ``--real`` (default
  ``7scenes_redkitchen`` and ``tum_fr1_rpy``), every frame.
* Known-shake clips: ``[SRC:]SEED:FIRST-LAST`` (:class:`ShakeClip`; SRC a folder under
  ``--data``, default ``7scenes_redkitchen``), a shaken clip and its unshaken reference made
  by the shake tool (:mod:`.shake_clips`) and cached under ``WORK/clips`` with the same folder
  names whatever the source (the name starts with the source folder's).
* Degraded copies: every degrade cell applied to every known-shake clip and to its reference,
  with the clip's seed, cached beside them. The ``clean`` cell is the known-shake clip itself.

A clip folder missing under ``--data`` is skipped with a note when it is one of the defaults,
and is an error naming the flag when it was given (:func:`select_sources`).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

from ..core.frame import BadFrame
from ..io.sources import SourceError
from ..io.sources.tum import TumSource
from .degrade_clips import CLEAN, DegradeCell, make_degraded
from .shake_clips import ShakeSpec, make_clip

REAL_CLIP = "7scenes_redkitchen"  # the known-shake clips' default source
DEFAULT_REAL = ("7scenes_redkitchen", "tum_fr1_rpy")
DEFAULT_CLIPS = ("7:0-149", "11:100-249")

Progress = Callable[[str], None]


def check_name(name: str) -> str:
    """A clip folder's name (no path, not empty, not . or ..); ValueError otherwise."""
    if not name or "/" in name or "\\" in name or name in (".", ".."):
        raise ValueError(f"expected a folder name under --data, got {name!r}")
    return name


@dataclass(frozen=True)
class ShakeClip:
    """A known-shake clip: the real clip it is made from (a folder under --data) and the shake."""

    source: str
    shake: ShakeSpec

    @classmethod
    def parse(cls, text: str, amplitudes: tuple[float, float, float] | None = None) -> "ShakeClip":
        """``[SRC:]SEED:FIRST-LAST`` (e.g. ``tum_fr1_rpy:3:0-149``, ``7:0-149``); ValueError if wrong."""
        head, sep, tail = text.strip().rpartition(":")
        src, sep2, seed = head.rpartition(":")
        if not sep or not sep2:  # SEED:FIRST-LAST alone
            src = REAL_CLIP
        else:
            try:
                check_name(src)
            except ValueError:
                raise ValueError(f"expected [SRC:]SEED:FIRST-LAST with SRC a folder name, got {text!r}") from None
            text = f"{seed}:{tail}"
        try:
            spec = ShakeSpec.parse(text) if amplitudes is None else ShakeSpec.parse(text, amplitudes)
        except ValueError as e:
            raise ValueError(str(e).replace("expected SEED", "expected [SRC:]SEED")) from None
        return cls(src, spec)

    def with_amplitudes(self, amplitudes: tuple[float, float, float]) -> "ShakeClip":
        pitch, yaw, roll = amplitudes
        return replace(self, shake=replace(self.shake, pitch=pitch, yaw=yaw, roll=roll))

    @property
    def label(self) -> str:
        """``SRC:SEED:FIRST-LAST``, as the flag takes it."""
        return f"{self.source}:{self.shake.seed}:{self.shake.frames}"


def default_shake_clips() -> list[ShakeClip]:
    return [ShakeClip.parse(c) for c in DEFAULT_CLIPS]


@dataclass
class Clip:
    name: str
    folder: Path
    spec: ShakeSpec | None = None  # shaken clips only
    reference: Path | None = None  # the unshaken reference clip's folder
    made: dict = field(default_factory=dict)  # "shaken"/"reference" -> the tool's command, or "cached"
    source: str = ""  # the real clip (folder under --data) it was made from; its own name for a real clip
    label: str = ""  # the known-shake clip as --clip spells it (SRC:SEED:FIRST-LAST)
    cell: DegradeCell | None = None  # known-shake clips: the degrade cell (clean: the clip itself)


def source_folder(data: Path, name: str = REAL_CLIP, flag: str = "--data") -> Path:
    """``DATA/NAME``; SourceError naming ``flag`` when it is not a folder."""
    folder = Path(data) / name
    if not folder.is_dir():
        raise SourceError(f"{flag}: TUM folder not found: {folder}")
    return folder


def select_sources(data: Path, real: list[str] | None, clips: list[ShakeClip] | None,
                   no_shake: bool = False) -> tuple[list[str], list[ShakeClip], list[str]]:
    """(real clip names, known-shake clips, notes) to run; None means the defaults.

    A default whose source folder is missing is left out with a note; one that was given is a
    SourceError naming its flag.
    """
    notes: list[str] = []
    names = list(DEFAULT_REAL) if real is None else list(real)
    kept = []
    for name in names:
        if (Path(data) / name).is_dir():
            kept.append(name)
        elif real is None:
            notes.append(f"default real clip {name} skipped: no folder {Path(data) / name}")
        else:
            source_folder(data, name, f"--real {name}")
    shakes = [] if no_shake else (default_shake_clips() if clips is None else list(clips))
    kept_shakes = []
    for c in shakes:
        if (Path(data) / c.source).is_dir():
            kept_shakes.append(c)
        elif clips is None:
            notes.append(f"default known-shake clip {c.label} skipped: no folder {Path(data) / c.source}")
        else:
            source_folder(data, c.source, f"--clip {c.label}")
    if not kept and not kept_shakes:
        raise SourceError(f"--data {data}: none of the clips to run is there ({', '.join(names)})")
    return kept, kept_shakes, notes


def prepare_clips(data: Path, real: list[str], shakes: list[ShakeClip], cells: list[DegradeCell], work: Path,
                  shake_tool: Path, degrade_tool: Path, progress: Progress | None = None) -> list[Clip]:
    """The real clips, then per known-shake clip: itself (cell ``clean``) and its degraded copies,
    each with its reference (made, or taken from the cache)."""
    cache = Path(work) / "clips"
    clips = [Clip(name, source_folder(data, name), source=name) for name in real]
    for sc in shakes:
        src = source_folder(data, sc.source)
        made, folders = {}, {}
        for kind, s in (("shaken", sc.shake), ("reference", sc.shake.reference())):
            if progress:
                progress(f"clip {s.folder_name(src)}")
            folders[kind], cmd = make_clip(src, s, cache, shake_tool)
            made[kind] = "cached" if cmd is None else cmd
        clean = Clip(folders["shaken"].name, folders["shaken"], sc.shake, folders["reference"], made, sc.source,
                     sc.label, DegradeCell(CLEAN))
        clips.append(clean)
        for cell in cells:
            if cell.is_clean:
                continue
            dmade, dfolders = {}, {}
            for kind in ("shaken", "reference"):
                if progress:
                    progress(f"clip {cell.folder_name(folders[kind].name, sc.shake.seed)}")
                dfolders[kind], cmd = make_degraded(folders[kind], cell, sc.shake.seed, cache, degrade_tool)
                dmade[kind] = "cached" if cmd is None else cmd
            clips.append(Clip(dfolders["shaken"].name, dfolders["shaken"], sc.shake, dfolders["reference"],
                              {"shake": made, "degrade": dmade}, sc.source, sc.label, cell))
    return clips


def load_frames(folder: Path, frames: int | None) -> tuple[list[int], list[np.ndarray], list[int], float]:
    """(seqs, BGR images, timestamps ns, fps) of the readable frames of a TUM clip (first ``frames``)."""
    src = TumSource(folder, count=frames)
    seqs, images, stamps = [], [], []
    for fr in src:
        if isinstance(fr, BadFrame):
            continue
        seqs.append(fr.seq)
        images.append(fr.color)
        stamps.append(fr.timestamp_ns)
    return seqs, images, stamps, src.fps

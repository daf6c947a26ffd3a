"""RGB-D frames from a folder in the TUM RGB-D layout.

The folder holds ``rgb.txt`` and ``depth.txt`` (``timestamp filename`` lines,
``#`` comments), the images they name, an optional ``groundtruth.txt``
(``timestamp tx ty tz qx qy qz qw``, camera-to-world) and, in quick-stream's
test data, ``intrinsics.json`` (fx, fy, cx, cy, width, height, depth_scale,
optionally ``"approximate": true``).

Each rgb entry is paired with the nearest unused depth entry within ``max_dt``
seconds (greedy by smallest time difference, like TUM's ``associate.py``); rgb
entries left without a partner are counted, logged and skipped at open time.
The associated pairs keep rgb.txt order; a frame's ``seq`` is its position in
that full association list, so ``start`` shifts which frames are delivered but
not their numbering.

Images are read only when their frame is delivered. A frame that cannot be
delivered (missing/unreadable image, wrong depth size or type, depth with no
valid pixel, timestamp not after every earlier one) becomes a :class:`BadFrame`
whose error names the file and the problem; it is logged at WARNING and
iteration continues.
"""
from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Mapping

import cv2
import numpy as np

from ...core.frame import BadFrame, FrameError, Intrinsics, RGBDFrame
from ...stream.wire.pixels import jpeg_size
from .base import FrameOrGap, SourceError
from .trajectory import TrajectoryError, poses_at, read_tum_trajectory

log = logging.getLogger("quick_stream.io.sources.tum")

_INTRINSIC_KEYS = ("fx", "fy", "cx", "cy", "width", "height")
_FLOAT_OPTIONS = ("depth_scale", "fx", "fy", "cx", "cy", "max_dt", "fps")
_INT_OPTIONS = ("width", "height", "start", "count")


@dataclass(frozen=True)
class TumEntry:
    """One associated rgb/depth pair (paths as written in the index files)."""

    rgb_t: float
    rgb_file: str
    depth_file: str
    pose: np.ndarray | None = None
    out_of_order: str = ""  # non-empty: why this entry's timestamp is rejected


def parse_file_list(path: Path) -> list[tuple[float, str, int]]:
    """Parse a TUM ``timestamp filename`` list -> [(timestamp_s, filename, line_no)]."""
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as e:
        raise SourceError(f"cannot read {path}: {e.strerror or e}") from None
    out = []
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split(None, 1)
        try:
            t = float(parts[0])
        except ValueError:
            t = math.nan
        if len(parts) < 2 or not math.isfinite(t) or t < 0:
            raise SourceError(
                f"{path}:{lineno}: expected 'timestamp filename' with a finite "
                f"non-negative timestamp, got {line[:80]!r}"
            )
        out.append((t, parts[1].strip(), lineno))
    return out


def associate(rgb_ts: list[float], depth_ts: list[float], max_dt: float) -> dict[int, int]:
    """Greedy nearest-timestamp matching -> {rgb index: depth index}.

    Candidate pairs with ``|dt| <= max_dt`` are taken in order of increasing
    ``|dt|``, each rgb and each depth entry at most once (as TUM's associate.py).
    """
    d = np.asarray(depth_ts, dtype=float)
    order = np.argsort(d, kind="stable")
    ds = d[order]
    cands = []
    for i, t in enumerate(rgb_ts):
        lo = int(np.searchsorted(ds, t - max_dt - 1e-12, side="left"))
        hi = int(np.searchsorted(ds, t + max_dt + 1e-12, side="right"))
        for k in range(lo, hi):
            dt = abs(ds[k] - t)
            if dt <= max_dt + 1e-12:
                cands.append((dt, i, int(order[k])))
    cands.sort()
    match: dict[int, int] = {}
    used: set[int] = set()
    for _, i, j in cands:
        if i not in match and j not in used:
            match[i] = j
            used.add(j)
    return match


class TumSource:
    """A TUM-layout RGB-D folder as a lazily read :class:`~.base.Source`.

    ``depth_scale`` (raw units per metre) and ``intrinsics`` (an
    :class:`Intrinsics`, or a mapping overriding some of fx, fy, cx, cy, width,
    height) override ``intrinsics.json``. Width/height missing from both are read
    from the first colour image. ``start``/``count`` select a window of the
    associated frames; ``fps`` defaults to 1 / median rgb timestamp spacing.
    """

    def __init__(
        self,
        path: str | Path,
        depth_scale: float | None = None,
        intrinsics: Intrinsics | Mapping[str, float] | None = None,
        max_dt: float = 0.02,
        start: int = 0,
        count: int | None = None,
        fps: float | None = None,
    ) -> None:
        if not (math.isfinite(max_dt) and max_dt >= 0):
            raise ValueError(f"max_dt must be a finite number >= 0, got {max_dt}")
        if start < 0:
            raise ValueError(f"start must be >= 0, got {start}")
        if count is not None and count < 0:
            raise ValueError(f"count must be >= 0, got {count}")
        if fps is not None and not (math.isfinite(fps) and fps > 0):
            raise ValueError(f"fps must be a finite number > 0, got {fps}")
        if depth_scale is not None and not (math.isfinite(depth_scale) and depth_scale > 0):
            raise ValueError(f"depth_scale must be a finite number > 0, got {depth_scale}")
        self.path = Path(path)
        self.name = f"tum:{path}"
        self.max_dt = float(max_dt)
        if self.path.exists() and not self.path.is_dir():
            raise SourceError(f"tum: takes a folder in TUM layout (rgb.txt, depth.txt and the images they name), "
                              f"and {self.path} is a file (a recording: mcap:FILE)")
        if not self.path.is_dir():
            raise SourceError(f"TUM folder not found: {self.path}")
        for fname in ("rgb.txt", "depth.txt"):
            if not (self.path / fname).is_file():
                raise SourceError(f"TUM folder {self.path} has no {fname} ({self.path / fname})")
        rgb = parse_file_list(self.path / "rgb.txt")
        depth = parse_file_list(self.path / "depth.txt")
        if not rgb:
            raise SourceError(f"{self.path / 'rgb.txt'} lists no images")

        match = associate([r[0] for r in rgb], [d[0] for d in depth], self.max_dt)
        unmatched = [r for i, r in enumerate(rgb) if i not in match]
        self.unmatched_rgb: list[tuple[float, str]] = [(t, f) for t, f, _ in unmatched]
        if unmatched:
            log.warning(
                "%s: %d of %d rgb images have no depth image within %.4g s and are skipped "
                "(first: %s at line %d)", self.path / "rgb.txt", len(unmatched), len(rgb),
                self.max_dt, unmatched[0][1], unmatched[0][2])
        if not match:
            raise SourceError(
                f"{self.path}: no rgb image in rgb.txt has a depth image in depth.txt "
                f"within max_dt={self.max_dt} s")

        self.depth_scale, self.intrinsics, self.intrinsics_approximate = self._load_calibration(
            depth_scale, intrinsics, rgb[min(match)][1])

        pairs = [(rgb[i], depth[match[i]]) for i in sorted(match)]
        gt_file = self.path / "groundtruth.txt"
        poses: list[np.ndarray | None] = [None] * len(pairs)
        if gt_file.is_file():
            try:
                gt_ts, gt_poses = read_tum_trajectory(gt_file)
            except (OSError, TrajectoryError) as e:
                raise SourceError(f"cannot read ground truth {gt_file}: {e}") from None
            poses = poses_at(gt_ts, gt_poses, [r[0] for r, _ in pairs], self.max_dt)

        entries: list[TumEntry] = []
        latest = -math.inf
        for (r, d), pose in zip(pairs, poses):
            bad = ""
            if r[0] <= latest:
                bad = (f"{self.path / 'rgb.txt'}:{r[2]}: timestamp {r[0]:.6f} of {r[1]} is not "
                       f"after the previous frame's ({latest:.6f}); timestamps out of order")
            latest = max(latest, r[0])
            entries.append(TumEntry(r[0], r[1], d[1], pose, bad))
        self.entries = entries  # full association list; seq = index into it

        if start > len(entries):
            raise ValueError(f"start={start} but {self.path} has only {len(entries)} frames")
        stop = len(entries) if count is None else min(len(entries), start + count)
        self.start, self.stop = start, stop

        if fps is None:
            ts = np.array([e.rgb_t for e in entries])
            dts = np.diff(ts)
            dts = dts[dts > 0]
            fps = 1.0 / float(np.median(dts)) if len(dts) else 30.0
        self.fps = float(fps)
        self.has_ground_truth = any(e.pose is not None for e in entries[start:stop])

    # -- opening -----------------------------------------------------------------
    def _load_calibration(
        self, depth_scale, intrinsics, first_rgb: str
    ) -> tuple[float, Intrinsics, bool]:
        jfile = self.path / "intrinsics.json"
        data: dict = {}
        if jfile.is_file():
            try:
                data = json.loads(jfile.read_text(encoding="utf-8"))
                if not isinstance(data, dict):
                    raise ValueError("top level is not an object")
            except (OSError, ValueError) as e:
                raise SourceError(f"cannot read {jfile}: {e}") from None
        vals = {k: data[k] for k in (*_INTRINSIC_KEYS, "depth_scale") if data.get(k) is not None}
        approximate = bool(data.get("approximate", False))
        if isinstance(intrinsics, Intrinsics):
            vals.update({k: getattr(intrinsics, k) for k in _INTRINSIC_KEYS})
            approximate = False
        elif intrinsics is not None:
            unknown = set(intrinsics) - set(_INTRINSIC_KEYS)
            if unknown:
                raise ValueError(f"unknown intrinsics keys {sorted(unknown)}; use {_INTRINSIC_KEYS}")
            vals.update({k: v for k, v in intrinsics.items() if v is not None})
        if depth_scale is not None:
            vals["depth_scale"] = depth_scale
        if ("width" not in vals or "height" not in vals) and all(k in vals for k in ("fx", "fy", "cx", "cy")):
            size = image_header_size(self.path / first_rgb)  # image size is not calibration: from the data
            if size is not None:
                vals.setdefault("width", size[0])
                vals.setdefault("height", size[1])
        missing = [k for k in (*_INTRINSIC_KEYS, "depth_scale") if k not in vals]
        if missing:
            raise SourceError(
                f"TUM folder {self.path}: missing calibration {', '.join(missing)} (give them in "
                f"{jfile.name} or as source options)")
        try:
            K = Intrinsics(float(vals["fx"]), float(vals["fy"]), float(vals["cx"]),
                           float(vals["cy"]), int(vals["width"]), int(vals["height"]))
            K.validate()
            scale = float(vals["depth_scale"])
        except (TypeError, ValueError) as e:
            raise SourceError(f"TUM folder {self.path}: bad calibration: {e}") from None
        if not (math.isfinite(scale) and scale > 0):
            raise SourceError(f"TUM folder {self.path}: depth_scale must be > 0, got {scale}")
        if approximate:
            log.info("%s: intrinsics are marked approximate", jfile)
        return scale, K, approximate

    @classmethod
    def from_spec(cls, path: str, options: Mapping[str, str]) -> "TumSource":
        """Open from a spec path (``tum:`` prefix optional) and string options.

        Options: depth_scale, fx, fy, cx, cy, width, height, max_dt, fps (numbers),
        start, count (integers). An unknown option or bad value raises ValueError
        naming it.
        """
        if path.startswith("tum:"):
            path = path[4:]
        kw: dict = {}
        K: dict = {}
        for key, raw in options.items():
            if key in _FLOAT_OPTIONS:
                try:
                    val = float(raw)
                except (TypeError, ValueError):
                    raise ValueError(f"tum source option {key}={raw!r} is not a number") from None
                if not math.isfinite(val):
                    raise ValueError(f"tum source option {key}={raw!r} is not finite")
            elif key in _INT_OPTIONS:
                try:
                    val = int(raw)
                except (TypeError, ValueError):
                    raise ValueError(f"tum source option {key}={raw!r} is not an integer") from None
            else:
                known = ", ".join(sorted(_FLOAT_OPTIONS + _INT_OPTIONS))
                raise ValueError(f"tum source: unknown option {key!r} (known: {known})")
            (K if key in _INTRINSIC_KEYS else kw)[key] = val
        try:
            return cls(path, intrinsics=K or None, **kw)
        except ValueError as e:
            raise ValueError(f"tum source option: {e}") from None

    # -- access ------------------------------------------------------------------
    def __len__(self) -> int:
        return self.stop - self.start

    def __iter__(self) -> Iterator[FrameOrGap]:
        for seq in range(self.start, self.stop):
            yield self._read(seq)

    def frame(self, i: int) -> FrameOrGap:
        """The i-th frame this source delivers (0 <= i < len; negative counts from the end)."""
        n = len(self)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"{self.name}: frame index {i} out of range (0..{n - 1})")
        return self._read(self.start + i)

    def __repr__(self) -> str:
        return (f"TumSource({str(self.path)!r}, frames={len(self)}, fps={self.fps:.3g}, "
                f"depth_scale={self.depth_scale:g}, gt={self.has_ground_truth})")

    def _read(self, seq: int) -> FrameOrGap:
        e = self.entries[seq]
        ts_ns = int(round(e.rgb_t * 1e9))
        origin = f"{e.rgb_file} + {e.depth_file}"
        try:
            if e.out_of_order:
                raise FrameError(e.out_of_order)
            color = self._read_color(self.path / e.rgb_file)
            depth = self._read_depth(self.path / e.depth_file, color.shape)
            frame = RGBDFrame(color, depth, self.intrinsics, ts_ns, seq,
                              pose=None if e.pose is None else e.pose.copy(), origin=origin)
            try:
                return frame.validate()
            except FrameError as err:
                raise FrameError(f"{self.path / e.rgb_file} + {self.path / e.depth_file}: {err}") from None
        except (FrameError, cv2.error, OSError) as err:
            msg = str(err) if isinstance(err, FrameError) else f"{origin}: {type(err).__name__}: {err}"
            log.warning("%s: frame %d: %s", self.name, seq, msg)
            return BadFrame(seq, ts_ns, origin, msg)

    def _check_header(self, p: Path, what: str) -> None:
        """Refuse an image whose header declares another size than the intrinsics' before decoding
        it (a 760 KiB PNG can declare 20000x20000: 1.6 GB decoded)."""
        size = image_header_size(p)
        W, H = self.intrinsics.width, self.intrinsics.height
        if size is not None and size != (W, H):
            raise FrameError(f"{p}: {what} is {size[0]}x{size[1]} (from its header; not decoded), "
                             f"intrinsics are for {W}x{H}")

    def _read_image(self, p: Path, what: str) -> np.ndarray:
        """The decoded image file (any depth and channels); FrameError when it is missing, declares
        another size than the intrinsics' or does not decode."""
        if not p.is_file():
            raise FrameError(f"{p}: {what} not found")
        self._check_header(p, what)
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise FrameError(f"{p}: cannot decode {what}")
        return img

    def _read_color(self, p: Path) -> np.ndarray:
        img = self._read_image(p, "colour image")
        if img.dtype == np.uint16:  # 16-bit colour: keep the high byte, as IMREAD_COLOR would
            img = (img >> 8).astype(np.uint8)
        if img.dtype != np.uint8:
            raise FrameError(f"{p}: colour image must be 8-bit, got dtype {img.dtype}")
        if img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 1):
            img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        elif img.ndim == 3 and img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
        if img.ndim != 3 or img.shape[2] != 3:
            raise FrameError(f"{p}: colour image has unsupported shape {img.shape}")
        W, H = self.intrinsics.width, self.intrinsics.height
        if (img.shape[1], img.shape[0]) != (W, H):
            raise FrameError(f"{p}: colour image is {img.shape[1]}x{img.shape[0]}, "
                             f"intrinsics are for {W}x{H}")
        return img

    def _read_depth(self, p: Path, color_shape: tuple[int, ...]) -> np.ndarray:
        raw = self._read_image(p, "depth image")
        if raw.ndim != 2:
            raise FrameError(f"{p}: depth image must be single-channel, got shape {raw.shape}")
        if raw.shape != color_shape[:2]:
            raise FrameError(f"{p}: depth image is {raw.shape[1]}x{raw.shape[0]} but the colour "
                             f"image is {color_shape[1]}x{color_shape[0]}")
        if raw.dtype == np.uint16:
            depth = raw.astype(np.float32) / np.float32(self.depth_scale)
        elif raw.dtype in (np.float32, np.float64):  # float depth is already in metres
            depth = raw.astype(np.float32, copy=False)
        else:
            raise FrameError(f"{p}: depth must be 16-bit (raw units) or float (metres), "
                             f"got dtype {raw.dtype}")
        with np.errstate(invalid="ignore"):
            if not np.any(np.isfinite(depth) & (depth > 0)):
                raise FrameError(f"{p}: depth has no valid pixel (all zero or invalid)")
        return depth


def image_header_size(p: Path) -> tuple[int, int] | None:
    """(width, height) a PNG or JPEG file declares in its header, without decoding it; None if
    the file is neither (or unreadable: the decoder then says why)."""
    try:
        with open(p, "rb") as f:
            head = f.read(24)
            if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
                return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
            if head[:2] == b"\xff\xd8":
                f.seek(0)
                return jpeg_size(f.read(1 << 22))  # the SOF comes before the image data
    except OSError:
        return None
    return None

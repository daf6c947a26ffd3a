"""The source interface: a lazily iterated stream of RGB-D frames."""
from __future__ import annotations

import logging
import signal
import threading
from typing import Iterator, Protocol, runtime_checkable

from ...core.frame import BadFrame, Intrinsics, RGBDFrame

FrameOrGap = RGBDFrame | BadFrame

log = logging.getLogger(__name__)


class SourceError(RuntimeError):
    """A source cannot be opened at all (missing folder, unreadable index, bad options)."""


@runtime_checkable
class Source(Protocol):
    """What every source provides.

    Iterating yields frames one at a time in capture order and never loads a whole
    clip into memory. A frame that cannot be delivered is yielded as a
    :class:`~quick_stream.core.frame.BadFrame` carrying the reason, and iteration goes on.
    """

    name: str
    intrinsics: Intrinsics  # nominal intrinsics of the stream (frames carry their own)
    fps: float
    has_ground_truth: bool
    depth_scale: float  # raw depth units per metre the frames were quantized to (the wire keeps it)

    def __len__(self) -> int: ...  # number of frames the source will yield (or will try to)

    def __iter__(self) -> Iterator[FrameOrGap]: ...


@runtime_checkable
class LiveSource(Source, Protocol):
    """A live device: ``open()`` connects now (raising if there is no device), so a camera that is not
    there fails before the stream starts; ``stop`` (a threading.Event, set by the process when it is asked
    to stop) makes reconnection retries give up at once. (A file source's stop is its last frame.)"""

    stop: threading.Event | None

    def open(self) -> None: ...


@runtime_checkable
class ReplaySource(Source, Protocol):
    """A recording: each frame with the message bytes it was recorded as, so a replay can send them
    exactly (``pixels=False``: images and depth left undecoded, their compressed streams unchecked, every
    other field still checked; the receivers check the pixels)."""

    def iter_with_messages(self, pixels: bool = True) -> Iterator[tuple[FrameOrGap, bytes]]: ...


def open_live(source: Source, spec: str) -> int | None:
    """A live device (a source with ``open()``): there, or a clear error before the stream. Returns
    an exit code to stop with (0: stopped while opening; 2: it cannot be opened, not restarted by the
    supervisor), None to go on. SIGTERM while it opens ends its retries at once."""
    if not isinstance(source, LiveSource):
        return None
    stopping = threading.Event()
    source.stop = stopping
    prev = signal.signal(signal.SIGTERM, lambda *_: stopping.set())
    try:
        source.open()
    except Exception as e:  # noqa: BLE001 - NoDevice, depthai's errors: the camera cannot be used
        if stopping.is_set():
            log.info("stopped while opening %s", spec)
            return 0
        log.error("source %s cannot be opened: %s", spec, e)
        return 2  # a configuration problem: the supervisor does not restart it
    finally:
        signal.signal(signal.SIGTERM, prev)
    return 0 if stopping.is_set() else None

"""The source interface: a lazily iterated stream of RGB-D frames."""
from __future__ import annotations

from typing import Iterator, Protocol, runtime_checkable

from ...core.frame import BadFrame, Intrinsics, RGBDFrame

FrameOrGap = RGBDFrame | BadFrame


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

    # Optional, for live devices: ``open()`` connects now (raising if there is no device) so a
    # camera that is not there fails before the stream starts, and ``stop`` (a threading.Event)
    # makes retries give up at once when the process is asked to stop.

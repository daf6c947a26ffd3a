"""The C heap of a quick-stream process (glibc): keep frame-sized buffers for reuse, hand the rest back.

Light on purpose (no zenoh, no OpenCV): the CLI calls :func:`keep_freed_buffers` before it knows
which command runs, and every service does in :func:`~quick_stream.stream.process.service_main`.
"""
from __future__ import annotations

from typing import Callable


def _libc(name: str) -> Callable[..., int] | None:
    try:
        import ctypes

        return getattr(ctypes.CDLL("libc.so.6"), name)
    except (OSError, AttributeError):
        return None  # not glibc: nothing to do


_MALLOC_TRIM = _libc("malloc_trim")
_MALLOPT = _libc("mallopt")
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters
HEAP_BELOW = 32 << 20  # bytes: allocations below come from the heap (glibc's largest mmap threshold on 64-bit)
KEEP_FREED = 128 << 20  # bytes: freed memory the heap keeps at its top before it gives it back by itself


def keep_freed_buffers() -> bool:
    """Have glibc serve every allocation under ``HEAP_BELOW`` from its heap and keep up to ``KEEP_FREED``
    freed at its top (``mallopt``), so the images, depth maps and flow fields each frame allocates
    (0.3-2.5 MB each) reuse the memory the last frame's freed. By default glibc maps some of them
    afresh and unmaps them when freed, and the kernel faults in and zeroes their pages again: in
    ``stabilize`` about 250 page faults and 0.25-0.65 ms of kernel time a frame (7-Scenes), in the flow
    service about 330 faults a frame, 3 % of a core. A service still hands freed memory back every
    ``TRIM_EVERY`` stats (:func:`trim_heap`). False when not applied (not glibc)."""
    if _MALLOPT is None:
        return False
    return bool(_MALLOPT(M_MMAP_THRESHOLD, HEAP_BELOW)) and bool(_MALLOPT(M_TRIM_THRESHOLD, KEEP_FREED))


def trim_heap() -> None:
    """Hand freed heap pages back to the OS (glibc ``malloc_trim``). Frames and messages of many
    sizes, allocated in zenoh's threads and freed in the service's, leave free memory spread over
    several malloc arenas; without this the resident size of a long run creeps up by several
    percent (10-minute soak, docs/reliability.md). A few milliseconds, every ``TRIM_EVERY`` stats."""
    if _MALLOC_TRIM is not None:
        _MALLOC_TRIM(0)

"""Read a source ahead in a worker thread: the next frames decode while the stabilizer works.

A frame source spends its time in image decoding (``cv2.imread``, ``cv2.imdecode``) and numpy,
which release the GIL, so on a second core reading overlaps the stabilizer's own work
(``quick-stream stabilize``: the wall time drops towards the compute time). At most ``depth``
frames wait; the order is the source's; an exception of the source is raised where the frame
it failed on would have come; closing early (or leaving the loop) stops the worker.
"""
from __future__ import annotations

import queue
import threading
from collections.abc import Iterable, Iterator
from typing import Generic, TypeVar

T = TypeVar("T")
_END = object()


class Prefetch(Generic[T]):
    """Iterate ``items`` through a worker thread holding at most ``depth`` of them ahead."""

    def __init__(self, items: Iterable[T], depth: int = 4) -> None:
        if depth < 1:
            raise ValueError(f"prefetch depth must be >= 1, got {depth}")
        self._q: queue.Queue = queue.Queue(depth)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(iter(items),), name="prefetch", daemon=True)
        self._thread.start()

    def _put(self, item: object) -> bool:
        """Queue ``item`` unless stopped first; whether it was queued."""
        while not self._stop.is_set():
            try:
                self._q.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def _run(self, it: Iterator[T]) -> None:
        try:
            for item in it:
                if not self._put(item):
                    return
        except BaseException as e:  # noqa: BLE001 - raised in the consumer, in order
            self._put(_Raised(e))
            return
        self._put(_END)

    def __iter__(self) -> Iterator[T]:
        try:
            while (item := self._q.get()) is not _END:
                if isinstance(item, _Raised):
                    raise item.error
                yield item
        finally:
            self.close()

    def close(self) -> None:
        """Stop the worker (it finishes the item it is reading) and wait for it."""
        self._stop.set()
        self._thread.join()


class _Raised:
    def __init__(self, error: BaseException) -> None:
        self.error = error

"""Progress on stderr for the commands that run longer than a few seconds.

``Progress(prefix)`` is called with a message per item (or phase) and shows at most one a
second, plus any message passed with ``force=True`` (a phase starts) and the last one: on a
terminal as one line rewritten in place, elsewhere (a log, a pipe) as lines. ``heartbeat``
covers work with no items to count: after ``after_s`` it says, once a second, how long it has
been working. Standard output stays for the results.
"""
from __future__ import annotations

import sys
import threading
import time
from contextlib import contextmanager
from typing import Iterator, TextIO


class Progress:
    """Throttled progress messages ``<prefix>: [  12.3 s] <message>`` on ``stream`` (stderr)."""

    def __init__(self, prefix: str, enabled: bool = True, every_s: float = 1.0, stream: TextIO | None = None) -> None:
        self.prefix, self.enabled, self.every_s = prefix, enabled, every_s
        self.stream = stream or sys.stderr
        self.t0 = time.monotonic()
        self._last_shown = -float("inf")
        self._pending: str | None = None  # the newest message not shown yet (shown by close)
        self._open_line = False  # a terminal line written with \r, not yet ended
        self._lock = threading.Lock()

    def _tty(self) -> bool:
        try:
            return self.stream.isatty()
        except (AttributeError, ValueError):
            return False

    def __call__(self, message: str, force: bool = False) -> None:
        if not self.enabled:
            return
        with self._lock:
            now = time.monotonic()
            if not force and now - self._last_shown < self.every_s:
                self._pending = message
                return
            self._show(message, now)

    def _show(self, message: str, now: float) -> None:
        self._pending = None
        self._last_shown = now
        line = f"{self.prefix}: [{now - self.t0:7.1f} s] {message}"
        try:
            if self._tty():
                self.stream.write(f"\r{line}\x1b[K")
                self._open_line = True
            else:
                self.stream.write(line + "\n")
            self.stream.flush()
        except (OSError, ValueError):  # stderr closed (a pipe's reader went away): progress is not worth dying for
            self.enabled = False

    def close(self) -> None:
        """Show the last message held back, and end a terminal's rewritten line."""
        if not self.enabled:
            return
        with self._lock:
            if self._pending is not None:
                self._show(self._pending, time.monotonic())
            if self._open_line:
                try:
                    self.stream.write("\n")
                    self.stream.flush()
                except (OSError, ValueError):
                    pass
                self._open_line = False

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@contextmanager
def heartbeat(prefix: str, what: str, after_s: float = 2.0, every_s: float = 1.0,
              stream: TextIO | None = None) -> Iterator[Progress]:
    """While the body runs: after ``after_s`` seconds, ``<prefix>: [  t s] <what>`` once a second."""
    progress = Progress(prefix, every_s=every_s, stream=stream)
    stop = threading.Event()

    def beat() -> None:
        if stop.wait(after_s):
            return
        while not stop.is_set():
            progress(what, force=True)
            stop.wait(every_s)

    thread = threading.Thread(target=beat, name="progress-heartbeat", daemon=True)
    thread.start()
    try:
        yield progress
    finally:
        stop.set()
        thread.join()
        progress.close()

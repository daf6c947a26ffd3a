"""Where the stage drivers report: the service's logger, or nowhere (the in-process stabilizer)."""
from __future__ import annotations

import logging

_QUIET = logging.getLogger("quick_stream.quiet")  # a driver given no logger says nothing
_QUIET.addHandler(logging.NullHandler())
_QUIET.propagate = False


def log_or_quiet(log: logging.Logger | None) -> logging.Logger:
    """``log``, or a logger that drops every record when it is None."""
    return _QUIET if log is None else log

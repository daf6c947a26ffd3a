"""The real render service with every rendered frame slowed down (backpressure tests).

``python -m tests.tools.slow_render --slow-ms MS [render flags]`` runs
:func:`quick_stream.services.render.main` with the render flags, unchanged, except that the
:class:`~quick_stream.core.render_stage.RenderStage` its driver makes
(:class:`~quick_stream.core.release.RenderDriver`; wrapped by :func:`slowed`) spends ``MS``
milliseconds more on every frame it renders. A bad ``--slow-ms`` exits 2 naming it, as a
service's flags do. The launcher starts it in place of ``quick_stream.services.render`` wherever a
test needs a slow stage (tests/integration/test_backpressure.py).
"""
from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Iterator

from quick_stream.core import release
from quick_stream.services import render
from quick_stream.stream import argtypes as at


def slowed(stage_class: type, slow_ms: float) -> type:
    """A subclass of the render stage whose batches and final flush yield each frame ``slow_ms`` later."""

    class SlowRenderStage(stage_class):
        def iter_release(self, *a, **k) -> Iterator:
            for sf in super().iter_release(*a, **k):
                time.sleep(slow_ms / 1e3)
                yield sf

        def flush(self, *a, **k) -> list:
            out = []
            for sf in super().flush(*a, **k):
                time.sleep(slow_ms / 1e3)
                out.append(sf)
            return out

    return SlowRenderStage


def main(argv: list[str] | None = None) -> int:
    """``--slow-ms MS`` (default 0) is this tool's; every other flag goes to the render service's ``main``."""
    p = argparse.ArgumentParser(prog="python -m tests.tools.slow_render", add_help=False)
    p.add_argument("--slow-ms", type=at.nonneg_float, default=0.0,
                   help="spend this much longer on every rendered frame")
    known, rest = p.parse_known_args(sys.argv[1:] if argv is None else argv)
    real = release.RenderStage
    if known.slow_ms > 0:
        release.RenderStage = slowed(real, known.slow_ms)  # what the render driver makes each stream's stage of
    try:
        return render.main(rest)
    finally:
        release.RenderStage = real  # in-process callers (tests) get the real stage back


if __name__ == "__main__":
    sys.exit(main())

"""The real render service under a file-size limit (a full disk, reproducibly).

``python -m tests.tools.fsize_render --fsize BYTES [render flags]`` sets this process's
``RLIMIT_FSIZE`` (as ``prlimit --fsize`` does; Python ignores SIGXFSZ, so a write past the limit
fails with EFBIG, as one on a full disk fails with ENOSPC) and runs
:func:`quick_stream.services.render.main` with the render flags, unchanged. The launcher starts it
in place of ``quick_stream.services.render`` (tests/integration/test_render_write_failure.py).
"""
from __future__ import annotations

import argparse
import resource
import sys

from quick_stream.services import render
from quick_stream.stream import argtypes as at


def main(argv: list[str] | None = None) -> int:
    """``--fsize BYTES`` is this tool's; every other flag goes to the render service's ``main``."""
    p = argparse.ArgumentParser(prog="python -m tests.tools.fsize_render", add_help=False)
    p.add_argument("--fsize", type=at.positive_int, required=True, help="no file may grow past this many bytes")
    known, rest = p.parse_known_args(sys.argv[1:] if argv is None else argv)
    resource.setrlimit(resource.RLIMIT_FSIZE, (known.fsize, known.fsize))
    return render.main(rest)


if __name__ == "__main__":
    sys.exit(main())

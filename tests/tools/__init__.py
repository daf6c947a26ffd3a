"""Test tools, not part of the product: fault injection, fuzz drivers and a slowed render (they
need the ``test`` extra). Each runs from the repo root as ``python -m tests.tools.NAME``:

* ``faults``: SIGKILL services of a running ``quick-stream up`` mid-stream, measure recovery;
* ``fuzz`` (``--engine hypothesis``: ``fuzz_hypothesis``; ``--target mcap``: ``fuzz_mcap``):
  malformed wire messages and damaged recordings against the decoders and readers;
* ``slow_viewer``: a slow foreign subscriber beside a live pipeline;
* ``flood``: a foreign publisher flooding the frame key, against the pipeline's own capacity;
* ``slow_render``: the render service with every frame slowed (backpressure tests);
* ``fsize_render``: the render service under a file-size limit (a full disk, reproducibly);
* ``netns_probe``: a zenoh session inside a network namespace (tests/integration/test_netns.py).
"""
from __future__ import annotations

import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def repo_env(env: dict[str, str] | None = None) -> dict[str, str]:
    """``env`` (default: this process's) with the repo root first on PYTHONPATH, so a child process
    started anywhere can run ``python -m tests.tools.NAME``."""
    env = dict(os.environ if env is None else env)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [env.get("PYTHONPATH")])])
    return env

"""The C heap keeps frame-sized buffers for the next frame (``stream.heap``), and still hands them back
on ``trim_heap``. Each case runs in a fresh interpreter: ``mallopt`` is process-wide."""
from __future__ import annotations

import json
import subprocess
import sys

# A "frame" allocates four 2 MB buffers, writes them and frees them: 8 MB freed at the heap's top,
# beyond what glibc keeps there by default (twice its adaptive mmap threshold, here 4 MB), so every
# frame faults its 8 MB in again (2048 pages of 4 kB).
FRAMES = """
import json, resource, sys
import numpy as np
from quick_stream.stream.heap import keep_freed_buffers, trim_heap
kept = keep_freed_buffers() if sys.argv[1] == "keep" else None
def frame():
    bufs = [np.ones(2 << 20, np.uint8) for _ in range(4)]
    return sum(int(b[::4096].sum()) for b in bufs)
def rss_kb():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4
for _ in range(3):
    frame()
f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(20):
    frame()
faults = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0) / 20
before = rss_kb()
trim_heap()
print(json.dumps({"kept": kept, "faults": faults, "trimmed_kb": before - rss_kb()}))
"""


def frames(mode: str) -> dict:
    out = subprocess.run([sys.executable, "-c", FRAMES, mode], capture_output=True, text=True, timeout=120, check=True)
    return json.loads(out.stdout)


def test_freed_frame_buffers_are_reused_without_page_faults_and_trimmed_on_demand():
    default, keep = frames("default"), frames("keep")
    assert keep["kept"] is True  # glibc (the machines this runs on)
    assert default["faults"] > 1000  # each frame's 8 MB faulted in again
    assert keep["faults"] < 50  # reused from the heap
    assert keep["trimmed_kb"] > 6000  # and handed back to the OS when the service trims

"""quick-stream: online QuICK 3D video stabilization for RGB-D cameras.

Layers, each importing only its own or lower ones (docs/architecture.md,
"Modules and layers"; tests/unit/test_layers.py checks it):

* ``core``: every algorithm (frames, Lie groups, scene flow, motion, path,
  rendering) and the stages that chain them; pure, no zenoh, files or CLI;
* ``stream``: the wire format, keys, zenoh transport, a service's runtime, the
  launcher and the flags every service shares;
* ``io``: sources, sinks, MCAP recordings, the Foxglove view, plots;
* ``quality``: metrics and evaluation against ground truth, stage re-runs;
* ``bench``: the benchmarks that print numbers;
* ``cli``: the ``quick-stream`` command, one module per sub-command.

The processes (``quick_stream.services``, the repo's ``services/`` folder)
import only core, stream and io, and add transport around them.

Threading: every stage runs on one core (a service per stage). The linear
algebra here is on tiny matrices (3x3 .. 12x12, a few thousand rows), where
OpenBLAS's thread pool costs far more than it saves (measured: SA(3) log 20 ms
instead of 0.7 ms with a busy second core), so BLAS/OpenMP pools default to one
thread unless the environment says otherwise. This must run before numpy loads.
"""
import os as _os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")

__version__ = "0.1.0"

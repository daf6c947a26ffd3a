"""quick-stream: online QuICK 3D video stabilization for RGB-D cameras.

The library holds every algorithm (scene flow, Lie groups, motion, path,
rendering), the wire format and the transport/logging helpers; the processes in
``services/`` only add transport around it.

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

"""Names the dead-code scan cannot see used: read by vulture, never imported.

The scan (``tests/unit/test_dead_code.py``)::

    vulture quick_stream services tests tests/tools/vulture_whitelist.py --min-confidence 60

Only true false positives belong here, each with the reason the scan cannot see its use: names
called by a library (a file protocol, depthai, pytest) or read through ``__dict__``. Code that
nothing uses is deleted, not listed.
"""
# ruff: noqa: B018, F821 - bare attribute references are how vulture whitelists name things

# io/recording.py: BoundedFile is a file object for mcap's readers, which call seekable()
_.seekable

# core/path/planner.py: SegmentInfo records are written whole to report.json (``s.__dict__`` in
# cli/stabilize_cmd.py); these fields are read by whoever reads the report
_.start_seq
_.solve_ms
_.budget_margin_px

# bench/peers.py: the OpenCV 5 shim assigned into vidstab's module, which calls it
_.cv2_estimateRigidTransform

# tests: pytest fixtures (autouse, or requested by a test's parameter name) and hooks pytest calls by name
pytest_configure
one_thread
no_work

# tests/unit/test_oak_source.py: depthai calls a HostNode's process() for each message
_.process

# tests/unit/test_oak_source.py: mock reads side_effect when the stand-in node's method is called
_.side_effect

# core/__init__.py, core/render/__init__.py: a module's __getattr__ is called by Python for a name the
# module does not hold (the package's names load their module on first use)
__getattr__

"""The streaming processes (capture, flow, motion, render, recorder), one thin module each.

This folder installs as ``quick_stream.services`` (pyproject.toml maps it into the package):
run one with ``python -m quick_stream.services.flow`` or its console script ``quick-stream-flow``.
Each service subscribes, calls the library (core, stream, io only), publishes and logs; no
algorithm lives here.
"""

"""The streaming processes (capture, flow, motion, render, recorder), one thin module each.

This folder installs as ``quick_stream.services`` (pyproject.toml maps it into the package):
run one with ``python -m quick_stream.services.flow`` or its console script ``quick-stream-flow``.
Each is a parser, one library stage wired to the runtime's service loop and a handler per
message type (docs/architecture.md, "The service loop"): it imports core, stream and io only, and
no algorithm or policy lives here.
"""

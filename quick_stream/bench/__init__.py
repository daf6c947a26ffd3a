"""Benchmarks that print numbers (``quick-stream bench NAME``); targets are checked here, not in timed tests.

The fault-injection and fuzz drivers are test tools (``python -m tests.tools.faults`` etc.), not here.
"""

"""Benchmarks that print numbers (``quick-stream bench NAME``); targets are checked here, not in timed tests."""

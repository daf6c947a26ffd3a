"""Streaming: the wire format, key expressions, zenoh transport, a service's runtime, the launcher
(``quick-stream up``'s supervisor) and the flags every service shares (argtypes, stabilizer flags).

Imports only :mod:`quick_stream.core` below it.
"""

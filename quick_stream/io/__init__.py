"""Files and devices: frame sources (synthetic, TUM folders, MCAP replay, OAK cameras), MP4/PNG
sinks, MCAP recordings, the Foxglove view of a stream and path plots.

Imports only :mod:`quick_stream.core` and :mod:`quick_stream.stream` below it.
"""

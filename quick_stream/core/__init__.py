"""The stabilizer itself: frames, Lie groups, scene flow, motion, path, rendering and the stages
that chain them (in-process: :class:`~quick_stream.core.stabilizer.Stabilizer`).

Pure computation: nothing here opens a zenoh session, reads or writes a file, or parses a command
line (tests/unit/test_layers.py checks that core imports no other layer, nor zenoh, mcap or argparse).
"""

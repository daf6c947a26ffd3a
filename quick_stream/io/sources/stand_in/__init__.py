"""Stand-in devices for a source checkout: test rigs, not part of the installed product.

:mod:`.oak_fake` is a scripted OAK camera (depthai's message API over synthetic frames, with faults
scripted by frame index) for the tests and for demos without hardware. Like ``quick_stream.bench``,
this package is left out of the wheel (pyproject.toml's package list): an editable install of a
checkout (``pip install -e .``) has it, an installed product does not, and a ``depthai:...,fake=``
spec then says so.
"""

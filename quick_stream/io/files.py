"""Whole files written so that a failed write leaves no cut-off file behind."""
from __future__ import annotations

import os
from pathlib import Path


def write_file(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` as a whole: into ``<path>.part``, renamed to ``path`` once every byte
    is written (a file already at ``path`` stays as it was until then). A write that fails (a full
    disk, a file-size limit) removes the part and raises :class:`OSError` whose ``filename`` is ``path``."""
    path = Path(path)
    part = path.with_name(path.name + ".part")
    try:
        with part.open("wb") as f:
            f.write(data)
        os.replace(part, path)
    except OSError as e:
        try:
            part.unlink(missing_ok=True)
        except OSError:
            pass  # none was made (its folder is not there)
        raise OSError(e.errno, e.strerror or str(e), str(path)) from None

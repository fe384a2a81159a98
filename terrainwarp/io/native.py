"""Native libraries that print to the process's stderr (file descriptor 2) by themselves: Warp's
initialisation on a machine without a GPU, libpng on a corrupt PNG. Their lines duplicate (or contradict)
the one-line errors terrainwarp raises, so they are silenced while such a call runs, and only then."""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator

__all__ = ["native_stderr_silenced"]


@contextlib.contextmanager
def native_stderr_silenced() -> Iterator[None]:
    """Point file descriptor 2 at the null device while the block runs, then restore it.

    Python's own ``sys.stderr`` is flushed first, so nothing written before the block is lost. Where the
    descriptors cannot be juggled (an unusual embedding), the block runs with stderr as it is."""
    try:
        saved = os.dup(2)
    except OSError:
        yield
        return
    try:
        null = os.open(os.devnull, os.O_WRONLY)
    except OSError:
        os.close(saved)
        yield
        return
    with contextlib.suppress(Exception):
        sys.stderr.flush()
    os.dup2(null, 2)
    try:
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(null)

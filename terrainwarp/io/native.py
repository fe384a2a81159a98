"""Native libraries that print to the process's stderr (file descriptor 2) by themselves: libpng on a corrupt
PNG, Warp's start on a machine without a GPU. Their lines duplicate (or contradict) the one-line errors
terrainwarp raises, so they are silenced while such a call runs, and only then
(:func:`native_stderr_silenced`, which lives with the device code that starts Warp)."""

from __future__ import annotations

from ..kernels.device import native_stderr_silenced

__all__ = ["native_stderr_silenced"]

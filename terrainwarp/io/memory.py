"""The size guard: how many bytes a heightmap needs, against what this machine has available.

A heightmap too large for memory is refused up front, with the estimate and the available memory in the
message, before anything is allocated or decoded (fBm noise, an image or a GeoTIFF whose header declares
its size): not Warp's allocation error, a MemoryError or ``std::bad_alloc`` minutes later.
"""

from __future__ import annotations

import os
from pathlib import Path

try:
    import resource
except ImportError:  # pragma: no cover - not on Windows
    resource = None

__all__ = ["BYTES_PER_SAMPLE", "available_bytes", "check_heightmap_fits", "format_bytes"]

# Peak bytes per sample while a heightmap is made: the float32 heights themselves (4 B) plus what making
# them costs on the way. Measured peaks over the process's resident size, 4000 x 4000 samples: fBm 13 B
# (Warp's output, the scaled copy, the checks' masks), a 16-bit PNG with max_height 15 B (the decoded
# pixels, float64 scaling, float32 heights), an int16 GeoTIFF 21 B (raw band, float64 decoding, no-data
# mask, float32 heights). 24 B covers each with a little room.
BYTES_PER_SAMPLE = 24
BIGGER = "terrains larger than memory need the tiled, streamed (out-of-core) path"


def available_bytes() -> int | None:
    """Memory this process can still use, in bytes: MemAvailable from /proc/meminfo (Linux), else the free
    physical pages (``os.sysconf``); lowered to what a cgroup (v2) memory limit leaves, and to what an
    address-space limit (``ulimit -v``) leaves. None when the machine does not say (then nothing is refused)."""
    avail = _proc_bytes("/proc/meminfo", "MemAvailable")
    if avail is None:
        try:
            avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError, AttributeError):
            avail = None
    try:  # a container's limit, when it is lower than what the host has free
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit != "max":
            used = int(Path("/sys/fs/cgroup/memory.current").read_text().strip())
            left = max(int(limit) - used, 0)
            avail = left if avail is None else min(avail, left)
    except (OSError, ValueError):
        pass
    left = _address_space_left()
    if left is not None:
        avail = left if avail is None else min(avail, left)
    return avail


def _address_space_left() -> int | None:
    """What an address-space limit (``ulimit -v``, RLIMIT_AS) leaves this process: the limit less its virtual
    size (VmSize in /proc/self/status); None without a limit. Past it an allocation fails with MemoryError
    (or std::bad_alloc in native code) however much the machine has free."""
    try:
        soft = resource.getrlimit(resource.RLIMIT_AS)[0]
    except (AttributeError, OSError, ValueError):  # no resource limits here
        return None
    if soft == resource.RLIM_INFINITY:
        return None
    return max(int(soft) - (_proc_bytes("/proc/self/status", "VmSize") or 0), 0)


def _proc_bytes(path: str, key: str) -> int | None:
    """A ``key:  N kB`` line of a /proc file, in bytes; None when there is no such file or line."""
    try:
        for line in Path(path).read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def format_bytes(n: float) -> str:
    """``8.0 TB``, ``21.3 GB``, ``512 B`` (powers of 1000)."""
    for unit in ("B", "kB", "MB", "GB", "TB", "PB"):
        if abs(n) < 1000.0 or unit == "PB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000.0
    raise AssertionError("unreachable")


def check_heightmap_fits(name: str, rows: int, cols: int, *, what: str = "heightmap", hint: str = "") -> int:
    """Refuse a ``rows`` x ``cols`` heightmap that would not fit in the available memory.

    Args:
        name: the argument to blame in the message (``rows``, ``path``, ``window``, ...).
        rows, cols: the heightmap's size in samples.
        what: how the message calls the thing (``"heightmap"``, ``"raster dem.tif read as a heightmap"``).
        hint: what else the user can do, added to the message.

    Returns:
        The estimate in bytes (``rows * cols * BYTES_PER_SAMPLE``).

    Raises:
        ValueError: ``"<name>: a R x C <what> needs about X; this machine has Y available (...)"``.
    """
    need = int(rows) * int(cols) * BYTES_PER_SAMPLE
    avail = available_bytes()
    if avail is not None and need > avail:
        extra = f"; {hint}" if hint else ""
        raise ValueError(f"{name}: a {int(rows)} x {int(cols)} {what} needs about {format_bytes(need)}; this "
                         f"machine has {format_bytes(avail)} available ({BIGGER}{extra})")
    return need

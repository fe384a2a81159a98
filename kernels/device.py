"""Warp started quietly, and the block size a launch uses: what every launch helper needs before it runs.

:func:`start` initialises Warp once, the way terrainwarp wants it for its own work: Warp's greeting is held back
(its log level raised for that call only, then set back), and on a machine with no CUDA driver Warp's native
warning "Could not find or load the NVIDIA CUDA driver" is not printed (file descriptor 2 points at the null
device for that call only). A machine with a driver starts exactly as Warp starts it. Nothing else changes: Warp's
settings are as they were found. A program that asks for a CUDA device on a machine without one gets a
``ValueError`` naming the argument and the missing GPU (:func:`terrainwarp.kernels.checks.check_device`), not the
warning.

:func:`launch_block_dim` is the block size ``wp.launch`` resolves when given none (1 on the CPU, the module's own on
CUDA), so a module is built once, for the variant its launches run.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import sys
import threading
from collections.abc import Iterator

import warp as wp

__all__ = ["cuda_driver_present", "device_named", "is_quiet", "launch_block_dim", "native_stderr_silenced", "quietly",
           "set_quiet", "start", "started"]

_lock = threading.Lock()
_state = {"started": False, "quiet": True}

# where the NVIDIA driver's library lives on each system Warp's CUDA build runs on (macOS has none)
_DRIVER_LIBRARIES = {"linux": ("libcuda.so.1", "libcuda.so"), "win32": ("nvcuda.dll",)}


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


def cuda_driver_present() -> bool:
    """True when the NVIDIA driver's library loads on this machine (what Warp's CUDA start needs)."""
    for name in _DRIVER_LIBRARIES.get(sys.platform, ()):
        try:
            ctypes.CDLL(name)
        except OSError:
            continue
        return True
    return False


@contextlib.contextmanager
def quietly() -> Iterator[None]:
    """Hold back Warp's INFO lines ("Module ... load on device 'cpu' took ...") while the block runs, unless
    terrainwarp was configured verbose (``terrainwarp.configure(quiet=False)``); Warp's log level is set back
    after. Warnings and errors still show."""
    if not _state["quiet"] or wp.config.log_level >= wp.LOG_WARNING:
        yield
        return
    level = wp.config.log_level
    wp.config.log_level = wp.LOG_WARNING
    try:
        yield
    finally:
        wp.config.log_level = level


def set_quiet(on: bool) -> None:
    """Whether :func:`start` and :func:`quietly` hold Warp's own lines back (the default) or let them show."""
    _state["quiet"] = bool(on)


def is_quiet() -> bool:
    """True when terrainwarp holds Warp's own lines back (the default)."""
    return _state["quiet"]


def started() -> bool:
    """True once :func:`start` has run in this process."""
    return _state["started"]


def start() -> None:
    """Initialise Warp once (``wp.init``; nothing when it already runs), quietly as the module docstring says."""
    if _state["started"]:
        return
    with _lock:
        if _state["started"]:
            return
        silence = _state["quiet"] and not cuda_driver_present()
        with quietly(), native_stderr_silenced() if silence else contextlib.nullcontext():
            wp.init()
        _state["started"] = True


_DEVICES: dict[str, wp.Device] = {}  # a full device name ("cpu", "cuda:0") names that device for good


def device_named(device: str | wp.Device | None) -> wp.Device:
    """``wp.get_device(device)``, Warp started first (:func:`start`); a full name is looked up once per process
    (``"cuda"`` and None name whichever device is current, and are looked up every time)."""
    dev = _DEVICES.get(device) if isinstance(device, str) else None
    if dev is not None:
        return dev
    start()
    dev = wp.get_device(device)
    if isinstance(device, str) and device != "cuda":
        _DEVICES[device] = dev
    return dev


def launch_block_dim(device: wp.Device) -> int | None:
    """The block size ``wp.launch`` uses on ``device`` when given none: 1 on the CPU; None (the module's own,
    256 by default) on CUDA. A module loaded for another block size would be built a second time."""
    return 1 if device.is_cpu else None

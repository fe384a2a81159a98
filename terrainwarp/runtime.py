"""What terrainwarp may change in the process that runs it, and only when asked: :func:`configure`.

``import terrainwarp`` changes nothing process-wide: not Warp's settings, not file descriptor 2, not the
allocator, and it registers no fork handler. When terrainwarp starts Warp and loads its own kernel modules it
does so quietly, whatever Warp's log level (see :mod:`terrainwarp.kernels.device`): Warp's greeting and its
per-module "load took ... ms" lines are held back, Warp's warning about a missing CUDA driver is not printed on
a machine that has none, and Warp's log level is as it was after. Each setting below is made by
:func:`configure`, which the ``terrainwarp`` command calls on start (:func:`configure_from_env`) and an
application calls if it wants them:

* ``quiet``: True (the default): terrainwarp's own Warp start and module loads print nothing; False: they
  print Warp's lines as Warp's log level allows (the ``TERRAINWARP_VERBOSE`` environment variable of the
  command). Warp's log level itself is never changed.
* ``keep_memory``: freed frame-sized memory stays mapped for the next frame (glibc ``mallopt``, see
  :func:`terrainwarp.kernels.parallel.keep_frame_memory`); ``False`` sets glibc's initial thresholds back.
* ``threads``: CPU threads a kernel launch is split across (:func:`terrainwarp.kernels.parallel.set_threads`).

The first kernel launch in a process where the kernel cache lacks some module compiles them all first, with a
progress line each (:mod:`terrainwarp.warmup`).
"""

from __future__ import annotations

import os
import threading
from typing import NamedTuple

from .kernels import device, parallel
from .kernels.checks import check_bool

__all__ = ["Configuration", "configure", "configure_from_env", "configuration", "VERBOSE_ENV", "KEEP_MEMORY_ENV"]

VERBOSE_ENV = "TERRAINWARP_VERBOSE"  # set (non-empty): the command leaves Warp's messages on
KEEP_MEMORY_ENV = "TERRAINWARP_KEEP_MEMORY"  # 0/false/no/off: the command leaves glibc's allocator alone


class Configuration(NamedTuple):
    """What is in force in this process: ``quiet`` (terrainwarp's Warp lines held back: True unless configured
    otherwise), ``keep_memory`` (None: never set, the process's own), ``threads`` (the launch split now)."""

    quiet: bool
    keep_memory: bool | None
    threads: int


_lock = threading.Lock()
_set: dict = {"keep_memory": None}
_KEEP_THREADS = object()


def configuration() -> Configuration:
    """The settings :func:`configure` has made so far."""
    return Configuration(device.is_quiet(), _set["keep_memory"], parallel.threads())


def configure(*, quiet: bool | None = None, keep_memory: bool | None = None,
              threads: int | None | object = _KEEP_THREADS) -> Configuration:
    """Apply process-wide settings, each only when given (None, or ``threads`` left out: unchanged).

    Args:
        quiet: True: terrainwarp's own Warp start and module loads print nothing (the default); False: they
            print what Warp's log level lets through. Warp's log level is not changed either way.
        keep_memory: True: freed frame memory stays mapped (glibc only); False: glibc's initial thresholds.
        threads: threads per kernel launch; None: the default (``TERRAINWARP_THREADS`` or the usable cores).

    Returns:
        The :class:`Configuration` now in force.

    Raises:
        TypeError: a setting of the wrong type (named).
    """
    if quiet is not None:
        check_bool("quiet", quiet)
    if keep_memory is not None:
        check_bool("keep_memory", keep_memory)
    with _lock:
        if quiet is not None:
            device.set_quiet(bool(quiet))
        if keep_memory is not None:
            parallel.keep_frame_memory(bool(keep_memory))
            _set["keep_memory"] = bool(keep_memory)
    if threads is not _KEEP_THREADS:
        parallel.set_threads(threads)
    return configuration()


def configure_from_env() -> Configuration:
    """The ``terrainwarp`` command's settings: quiet unless ``TERRAINWARP_VERBOSE`` is set, freed memory kept
    unless ``TERRAINWARP_KEEP_MEMORY`` is 0/false/no/off."""
    quiet = os.environ.get(VERBOSE_ENV, "") == ""
    keep = os.environ.get(KEEP_MEMORY_ENV, "1").strip().lower() not in ("0", "false", "no", "off")
    return configure(quiet=quiet, keep_memory=keep)

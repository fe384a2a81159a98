"""What terrainwarp may change in the process that runs it, and only when asked: :func:`configure`.

``import terrainwarp`` changes nothing process-wide: not Warp's log level, not file descriptor 2, not the
allocator, and it registers no fork handler. Each of these is a setting of :func:`configure`, which the
``terrainwarp`` command calls on start (:func:`configure_from_env`) and an application calls if it wants them:

* ``quiet``: Warp's log level to WARNING (no greeting, no per-module "load took ... ms" lines), and Warp
  initialised now with its native library's stderr silenced while it starts (on a machine without a GPU it
  prints "Could not find or load the NVIDIA CUDA driver" itself, on file descriptor 2). ``False`` sets the log
  level back to what it was before ``configure`` first changed it.
* ``keep_memory``: freed frame-sized memory stays mapped for the next frame (glibc ``mallopt``, see
  :func:`terrainwarp.kernels.parallel.keep_frame_memory`); ``False`` sets glibc's initial thresholds back.
* ``threads``: CPU threads a kernel launch is split across (:func:`terrainwarp.kernels.parallel.set_threads`).

Warp still initialises itself on first use when nothing configured it, as it does for any program that uses it.
"""

from __future__ import annotations

import os
import threading
from typing import NamedTuple

import warp as wp

from .io.native import native_stderr_silenced, say_first_compile
from .kernels import parallel
from .kernels.checks import check_bool

__all__ = ["Configuration", "configure", "configure_from_env", "configuration", "VERBOSE_ENV", "KEEP_MEMORY_ENV"]

VERBOSE_ENV = "TERRAINWARP_VERBOSE"  # set (non-empty): the command leaves Warp's messages on
KEEP_MEMORY_ENV = "TERRAINWARP_KEEP_MEMORY"  # 0/false/no/off: the command leaves glibc's allocator alone


class Configuration(NamedTuple):
    """What :func:`configure` has set in this process: ``quiet`` and ``keep_memory`` (None: never set, the
    process's own), ``threads`` (the launch split now)."""

    quiet: bool | None
    keep_memory: bool | None
    threads: int


_lock = threading.Lock()
_set: dict = {"quiet": None, "keep_memory": None, "log_level": None, "initialised": False}
_KEEP_THREADS = object()


def configuration() -> Configuration:
    """The settings :func:`configure` has made so far."""
    return Configuration(_set["quiet"], _set["keep_memory"], parallel.threads())


def configure(*, quiet: bool | None = None, keep_memory: bool | None = None,
              threads: int | None | object = _KEEP_THREADS) -> Configuration:
    """Apply process-wide settings, each only when given (None, or ``threads`` left out: unchanged).

    Args:
        quiet: True: Warp's log level WARNING, and Warp initialised with the native stderr silenced during its
            start; False: Warp's log level as it was before.
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
            _quiet(bool(quiet))
        if keep_memory is not None:
            parallel.keep_frame_memory(bool(keep_memory))
            _set["keep_memory"] = bool(keep_memory)
    if threads is not _KEEP_THREADS:
        parallel.set_threads(threads)
    return configuration()


def _quiet(on: bool) -> None:
    if on:
        if _set["log_level"] is None:
            _set["log_level"] = wp.config.log_level
        wp.config.log_level = wp.LOG_WARNING
        if not _set["initialised"]:  # wp.init() does nothing once Warp runs; the fd juggling is for its start only
            with native_stderr_silenced():
                wp.init()
            _set["initialised"] = True
    elif _set["log_level"] is not None:
        wp.config.log_level = _set["log_level"]
    _set["quiet"] = on


def configure_from_env() -> Configuration:
    """The ``terrainwarp`` command's settings: quiet unless ``TERRAINWARP_VERBOSE`` is set, freed memory kept
    unless ``TERRAINWARP_KEEP_MEMORY`` is 0/false/no/off; and, on a terminal, one line when the kernels are
    about to be compiled for the first time."""
    quiet = os.environ.get(VERBOSE_ENV, "") == ""
    keep = os.environ.get(KEEP_MEMORY_ENV, "1").strip().lower() not in ("0", "false", "no", "off")
    got = configure(quiet=quiet, keep_memory=keep)
    say_first_compile(wp.config.kernel_cache_dir)
    return got

"""Native libraries that print to the process's stderr (file descriptor 2) by themselves: Warp's
initialisation on a machine without a GPU, libpng on a corrupt PNG. Their lines duplicate (or contradict)
the one-line errors terrainwarp raises, so they are silenced while such a call runs, and only then. And the
one word said about Warp's compiler: the first run compiles the kernels (see :func:`first_compile_note`)."""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from typing import TextIO

__all__ = ["KERNEL_MODULE_PREFIX", "first_compile_note", "native_stderr_silenced", "say_first_compile"]

# Warp names a compiled module's cache folder "wp_" + the module's name + "_" + its hash.
KERNEL_MODULE_PREFIX = "wp_terrainwarp.kernels."


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


def first_compile_note(kernel_cache_dir: str | os.PathLike | None) -> str | None:
    """The one line to print when Warp's kernel cache holds no compiled terrainwarp kernel yet (missing,
    empty, or only other programs' kernels): the first run then compiles every kernel module, which takes
    about a minute on a CPU, and would otherwise be silent. None when the kernels are cached."""
    if kernel_cache_dir is None:
        return None
    try:
        with os.scandir(kernel_cache_dir) as entries:
            if any(e.name.startswith(KERNEL_MODULE_PREFIX) for e in entries):
                return None
    except OSError:  # missing or unreadable: Warp will compile (and try to cache) on first use
        pass
    return (f"terrainwarp: compiling Warp kernels on first use; they are cached in {os.fspath(kernel_cache_dir)} "
            "(about a minute, once)")


def say_first_compile(kernel_cache_dir: str | os.PathLike | None, stream: TextIO | None = None) -> bool:
    """Print :func:`first_compile_note` on ``stream`` (default ``sys.stderr``) when it is a terminal: the
    note is for a person waiting, and a program reading stderr through a pipe (the CLI's callers and
    tests, which expect exactly one line on an error) gets only what it asked for. True when printed."""
    stream = sys.stderr if stream is None else stream
    note = first_compile_note(kernel_cache_dir)
    try:
        tty = stream is not None and stream.isatty()
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        tty = False
    if note is None or not tty:
        return False
    print(note, file=stream, flush=True)
    return True

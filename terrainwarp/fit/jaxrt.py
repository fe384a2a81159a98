"""JAX for the fit, set up where a fit starts (never at import): the persistent compilation cache in the user's
cache folder, and the relaxed models' programs compiled once per shape.

**The cache** (:func:`use_cache`): ``$XDG_CACHE_HOME/terrainwarp/jax`` (by default ``~/.cache/terrainwarp/jax``,
beside Warp's kernel cache ``~/.cache/warp``), or the folder the environment variable ``TERRAINWARP_JAX_CACHE``
names; ``TERRAINWARP_JAX_CACHE=off`` (or ``0``, ``false``, ``no``, ``none``) leaves JAX without one, and a cache
folder the application gave JAX itself (``jax_compilation_cache_dir``) is left as it is. Every program is kept,
however fast it compiled, so a second fit in a fresh process compiles nothing. JAX writes an entry in place, not
through a temporary name; so before a process first uses the folder, each entry not yet seen whole is checked
(it must decompress whole: zlib carries a checksum) and one that does not, older than a minute (a writer killed
half way, not one still writing), is removed, to be compiled and written again (JAX itself would warn and compile
it on every use, never writing it again). Entries seen whole are listed in ``verified.txt`` (written through a
temporary name) and not read again.

**Programs** (:func:`compiled`): a traceable function jitted, lowered and compiled for its arguments' shapes once
per process, charged to the running fit's ``compile`` part, with the progress bar saying so
(:mod:`terrainwarp.fit.timings`). With the cache folder on, the traced program is kept there as well
(``exports/``: ``jax.export``, serialised, a checksum first, written through a temporary name; its key holds the
source of the modules that trace it), so a new process neither traces nor compiles: it reads the program and JAX's
cache gives its compiled code.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.util
import os
import threading
import time
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from .timings import part, say

__all__ = ["CACHE_ENV", "cache_dir", "use_cache", "compiled", "compiled_count", "check_entries"]

CACHE_ENV = "TERRAINWARP_JAX_CACHE"
_OFF = ("0", "off", "false", "no", "none")
_SETTLE_S = 60.0  # an entry younger than this may still be being written by another process
_MANIFEST = "verified.txt"

_EXPORT_VERSION = 1  # the layout of an exported program's file
_TRACED = ("terrainwarp.fit.optimise", "terrainwarp.fit.relaxed", "terrainwarp.fit.relaxed_cdlod",
           "terrainwarp.fit.relaxed_continuous", "terrainwarp.fit.relaxed_tree", "terrainwarp.lod.policies")
_lock = threading.Lock()
_state: dict[str, Any] = {"done": False, "dir": None}
_programs: dict = {}


def cache_dir() -> Path | None:
    """The folder the fit's compiled programs are kept in (None: turned off by ``TERRAINWARP_JAX_CACHE``)."""
    env = os.environ.get(CACHE_ENV, "").strip()
    if env.lower() in _OFF:
        return None
    if env:
        return Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME", "").strip() or str(Path.home() / ".cache")
    return Path(base) / "terrainwarp" / "jax"


def use_cache() -> Path | None:
    """Point JAX's persistent compilation cache at :func:`cache_dir` (once per process; a folder the application
    set already is kept). Returns the folder in use (None: none)."""
    import jax  # lazy: heavy optional dependency

    with _lock:
        if _state["done"]:
            return _state["dir"]
        own = jax.config.jax_compilation_cache_dir
        folder = Path(own) if own else cache_dir()
        if folder is not None and not own:
            try:
                folder.mkdir(parents=True, exist_ok=True)
                check_entries(folder)
            except OSError:
                folder = None  # a read-only home: no cache, the fit compiles as before
            if folder is not None:
                jax.config.update("jax_compilation_cache_dir", str(folder))
                jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        _state.update(done=True, dir=folder)
        return folder


def check_entries(folder: Path, now: float | None = None) -> tuple[int, int]:
    """Check the cache entries of ``folder`` not yet seen whole (see the module docstring): returns (entries
    checked, entries removed)."""
    now = time.time() if now is None else now
    seen = _read_manifest(folder / _MANIFEST)
    keep, checked, removed = {}, 0, 0
    for p in sorted(folder.glob("*-cache")):
        try:
            st = p.stat()
        except FileNotFoundError:
            continue
        tag = f"{st.st_size} {st.st_mtime_ns}"
        if seen.get(p.name) == tag:
            keep[p.name] = tag
            continue
        checked += 1
        if _whole(p):
            keep[p.name] = tag
        elif now - st.st_mtime > _SETTLE_S:
            p.unlink(missing_ok=True)
            removed += 1
    if keep != seen:
        tmp = folder / f".{_MANIFEST}.{os.getpid()}.tmp"
        tmp.write_text("".join(f"{k} {v}\n" for k, v in sorted(keep.items())))
        os.replace(tmp, folder / _MANIFEST)
    return checked, removed


def _read_manifest(path: Path) -> dict[str, str]:
    try:
        lines = path.read_text().splitlines()
    except (FileNotFoundError, UnicodeDecodeError):
        return {}
    out = {}
    for ln in lines:
        parts = ln.split(" ")
        if len(parts) == 3:
            out[parts[0]] = f"{parts[1]} {parts[2]}"
    return out


def _whole(path: Path) -> bool:
    """The entry decompresses whole (zlib: to its end, checksum included); a zstd entry is left to JAX."""
    data = path.read_bytes()
    if data[:4] == b"\x28\xb5\x2f\xfd":  # zstd (JAX with a zstd module): JAX checks it as it reads it
        return True
    d = zlib.decompressobj()
    try:
        d.decompress(data)
        d.flush()
    except zlib.error:
        return False
    return d.eof


def _signature(args: tuple) -> tuple:
    import jax  # lazy: heavy optional dependency

    leaves, tree = jax.tree_util.tree_flatten(args)
    return tree, tuple((np.shape(x), np.result_type(x).str) for x in leaves)


def compiled(fn: Callable, name: str, static: tuple, *args: Any):
    """``fn(*static, *args)`` (``fn`` traceable, ``static`` hashable) jitted, lowered and compiled for the shapes and
    dtypes of ``args``, once per process; call the result with ``args``. With the cache folder on, the traced
    program itself is kept there too (``jax.export``, serialised, checksummed, written through a temporary name,
    keyed by ``static``, the shapes, JAX's version and the source of the modules that trace it), so a new process
    reads it instead of tracing ``fn`` again, and JAX's cache gives its compiled code."""
    import jax  # lazy: heavy optional dependency

    key = (fn, static, _signature(args))
    prog = _programs.get(key)
    if prog is None:
        with part("compile"):
            say(f"compiling {name} (once per machine, then read from the cache)")
            folder = _state["dir"] if _state["done"] else None
            path = None if folder is None else folder / "exports" / f"{_export_key(fn, static, args)}.jaxexport"
            exported = _load_export(path) if path is not None else None
            if exported is None and path is not None:
                exported = _export(jax.jit(functools.partial(fn, *static)), args, path)
            target = jax.jit(exported.call) if exported is not None else jax.jit(functools.partial(fn, *static))
            prog = target.lower(*args).compile()
            say("")
        _programs[key] = prog
    return prog


def _export_key(fn: Callable, static: tuple, args: tuple) -> str:
    """What the traced program depends on: ``static``, the arguments' shapes, JAX's version, and the source of the
    modules of ``fn``, of ``static``'s types and of the relaxed models."""
    import jax  # lazy: heavy optional dependency

    h = hashlib.sha256(f"{static!r}|{_signature(args)!r}|{jax.__version__}|{_EXPORT_VERSION}".encode())
    mods = sorted({fn.__module__, *(type(x).__module__ for x in static), *_TRACED})
    for m in mods:
        spec = importlib.util.find_spec(m)
        if spec is not None and spec.origin and Path(spec.origin).is_file():
            h.update(Path(spec.origin).read_bytes())
    return h.hexdigest()[:32]


def _load_export(path: Path):
    """The exported program at ``path`` if it is whole (its checksum holds), else None (a bad file is removed)."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return None
    body = data[32:]
    if len(data) < 32 or hashlib.sha256(body).digest() != data[:32]:
        path.unlink(missing_ok=True)
        return None
    try:
        from jax import export  # lazy: heavy optional dependency

        return export.deserialize(bytearray(body))
    except Exception:  # noqa: BLE001 - an entry this JAX cannot read is made again
        path.unlink(missing_ok=True)
        return None


def _export(jitted, args: tuple, path: Path):
    """``jitted`` exported for ``args`` and written to ``path`` (checksum first, through a temporary name); None
    where JAX cannot serialise it here (the program is then traced in every process)."""
    try:
        from jax import export  # lazy: heavy optional dependency

        exported = export.export(jitted)(*args)
        body = bytes(exported.serialize())
    except ImportError:
        return None
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_bytes(hashlib.sha256(body).digest() + body)
    os.replace(tmp, path)
    return exported


def compiled_count() -> int:
    """The programs :func:`compiled` has made in this process."""
    return len(_programs)

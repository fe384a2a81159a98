"""The kernels compiled before the first frame: :func:`warmup`.

Warp compiles a kernel module the first time one of its kernels is launched, and keeps the object in its kernel
cache (``warp.config.kernel_cache_dir``; the ``WARP_CACHE_PATH`` environment variable moves it), where every
later process finds it. :func:`warmup` compiles every terrainwarp kernel module that is not in the cache yet, one
line per module as each finishes::

    compiling kernels, first run only: 7/20 raster

It runs in ``make setup`` (so ``make demo`` and ``make test`` on a fresh clone), in ``terrainwarp warmup`` and before
the work of ``report``, ``fit`` and ``stability``. A library user who never ran any of them sees the same lines
anyway: before a kernel module missing from the cache is first loaded, its line is printed and Warp compiles it in
this process (only the modules the program uses, as it first needs them; the first line says how many are missing
and that ``terrainwarp warmup`` compiles them all at once). Nothing is printed when the module is cached.

:func:`warmup`'s modules compile in worker processes, one per usable core (Warp's code generation parses Python with
``ast``, which CPython 3.11 does not allow on two threads at once). The workers use this process's kernel cache
and Warp's compile settings (``warp.config.cpu_compiler_flags``: Warp's default builds for this machine's CPU,
``-march=native``), so the objects they leave are the ones this process then loads. Several processes starting
at once (sweep workers) compile once: a lock file in the cache folder lets one compile while the others wait.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import os
import pkgutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import NamedTuple

import warp as wp

try:
    import fcntl  # POSIX: the cache folder's lock
except ImportError:  # pragma: no cover (Windows: no lock; Warp's renames still keep the cache whole)
    fcntl = None

from . import kernels
from .kernels import parallel
from .kernels.checks import check_device, check_int, check_optional
from .kernels.device import launch_block_dim, quietly

__all__ = ["LINE", "WarmupResult", "kernel_modules", "pending", "warmup"]

#: The progress line, one per module compiled.
LINE = "compiling kernels, first run only: {done}/{total} {name}"
LOCK_NAME = "terrainwarp-warmup.lock"  # in the kernel cache folder
# Warp settings that decide a module's hash (and so its cache entry): a worker takes this process's values
_SETTINGS = ("mode", "optimization_level", "cpu_compiler_flags", "max_unroll", "enable_backward", "lineinfo",
             "verify_fp", "enable_mathdx_gemm", "enable_mathdx_solver", "enable_mathdx_fft")
_SETTINGS_ENV = "TERRAINWARP_WARMUP_SETTINGS"


class WarmupResult(NamedTuple):
    """What :func:`warmup` did: the modules it compiled and those already cached (short names, e.g.
    ``"raster"``), its wall seconds, the worker processes it ran (0: compiled in this process) and the cache."""

    compiled: tuple[str, ...]
    cached: tuple[str, ...]
    seconds: float
    workers: int
    cache_dir: str


# ------------------------------------------------------------------------------------------------
# which modules, and which are not compiled yet
# ------------------------------------------------------------------------------------------------
def kernel_modules() -> dict[str, wp.Module]:
    """Every Warp module of ``terrainwarp.kernels`` that holds a kernel, by short name, largest source first
    (compiled first, so the workers finish together)."""
    found = {}
    for info in pkgutil.iter_modules(kernels.__path__):
        py = importlib.import_module(f"{kernels.__name__}.{info.name}")
        ks = [k for k in vars(py).values() if isinstance(k, wp.Kernel) and k.module.name == py.__name__]
        if ks:
            found[info.name] = (ks[0].module, Path(py.__file__).stat().st_size)
    return {n: m for n, (m, _) in sorted(found.items(), key=lambda kv: (-kv[1][1], kv[0]))}


def _binary(module: wp.Module, dev: wp.Device) -> Path:
    """Where Warp keeps ``module``'s compiled object for ``dev`` and the block size its launches use."""
    bd = launch_block_dim(dev)
    folder = Path(wp.config.kernel_cache_dir) / module.get_module_identifier(block_dim=bd)
    name = getattr(module, "_get_compile_output_name", None)
    if name is None:  # another Warp: the module's folder, which Warp renames into place when it is whole
        return folder
    return folder / name(dev, block_dim=bd if bd is not None else module.options["block_dim"])


def pending(device: str | wp.Device = "cpu") -> list[str]:
    """The kernel modules not compiled yet for ``device`` in Warp's kernel cache (short names)."""
    dev = check_device("device", device)
    return [n for n, m in kernel_modules().items() if not _binary(m, dev).exists()]


# ------------------------------------------------------------------------------------------------
# warmup
# ------------------------------------------------------------------------------------------------
def warmup(device: str | wp.Device = "cpu", *, workers: int | None = None,
           progress: Callable[[str], None] | bool = True) -> WarmupResult:
    """Compile every terrainwarp kernel module missing from Warp's kernel cache for ``device``.

    Args:
        device: the Warp device to compile for ("cpu", "cuda:0", ...).
        workers: worker processes (None: one per usable core, at most one per module; 0: in this process).
        progress: True: one line per module on stderr (:data:`LINE`); False: nothing; or a function given each
            line.

    Returns:
        A :class:`WarmupResult`.

    Raises:
        ValueError: a device Warp does not see (named). Warp's own error when a module fails to compile.
    """
    dev = check_device("device", device)
    workers = check_optional(check_int, "workers", workers, 0)
    say = _sayer(progress)
    t0 = time.perf_counter()
    mods = kernel_modules()
    with _cache_lock():
        todo = [n for n, m in mods.items() if not _binary(m, dev).exists()]
        n_workers = _worker_count(workers, len(todo))
        if todo:
            how = {0: "in this process", 1: "1 worker process"}.get(n_workers, f"{n_workers} worker processes")
            say(LINE.format(done=0, total=len(todo), name=f"(once per machine: {how}, cached in "
                                                            f"{wp.config.kernel_cache_dir})"))
        done = _compile_in_workers(todo, dev, n_workers, say) if n_workers else []
        left = [n for n in todo if n not in done or not _binary(mods[n], dev).exists()]
        for name in left:  # in this process: asked for, a worker failed, or its object did not match ours
            _compile_here(mods[name], dev)
            done.append(name)
            say(LINE.format(done=len(done), total=len(todo), name=name))
    cached = tuple(n for n in mods if n not in todo)
    return WarmupResult(tuple(todo), cached, time.perf_counter() - t0, n_workers, str(wp.config.kernel_cache_dir))


def _sayer(progress: Callable[[str], None] | bool) -> Callable[[str], None]:
    if callable(progress):
        return progress
    return _say if progress else (lambda line: None)


def _worker_count(workers: int | None, n: int) -> int:
    if workers is None:  # a worker costs an import (~1 s): not for a module or two, nor on one core
        cores = parallel.default_threads()
        workers = cores if n > 2 and cores > 1 else 0
    return min(workers, n)


def _compile_here(module: wp.Module, dev: wp.Device) -> None:
    with quietly():
        module.load(dev, block_dim=launch_block_dim(dev))


@contextlib.contextmanager
def _cache_lock() -> Iterator[None]:
    """Hold the warmup lock of the kernel cache folder (where ``fcntl`` exists and the folder is writable)."""
    if fcntl is None:
        yield
        return
    try:
        os.makedirs(wp.config.kernel_cache_dir, exist_ok=True)
        fd = os.open(os.path.join(wp.config.kernel_cache_dir, LOCK_NAME), os.O_RDWR | os.O_CREAT, 0o666)
    except OSError:
        yield
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock


# ------------------------------------------------------------------------------------------------
# worker processes
# ------------------------------------------------------------------------------------------------
def _worker_env() -> dict[str, str] | None:
    """The environment of a worker: this process's cache and compile settings; None where a worker could not
    reach this cache (a ``kernel_cache_dir`` set by hand after Warp started, not ending in Warp's version)."""
    cache = Path(wp.config.kernel_cache_dir)
    if cache.name != wp.config.version:
        return None
    settings = {k: getattr(wp.config, k) for k in _SETTINGS if hasattr(wp.config, k)}
    try:
        text = json.dumps(settings)
    except TypeError:
        return None
    return {**os.environ, "WARP_CACHE_PATH": str(cache.parent), _SETTINGS_ENV: text}


def _compile_in_workers(todo: list[str], dev: wp.Device, n: int, say: Callable[[str], None]) -> list[str]:
    """Compile ``todo`` in ``n`` worker processes, each taking the next module as it finishes one; the names
    compiled, in the order they finished (a worker that fails leaves its modules to the caller)."""
    env = _worker_env()
    if env is None:
        return []
    queue, done, lock = list(todo), [], threading.Lock()

    def run() -> None:
        code = "from terrainwarp.warmup import _worker; _worker()"
        try:
            p = subprocess.Popen([sys.executable, "-c", code, str(dev)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                 stderr=subprocess.DEVNULL, text=True, env=env)
        except OSError:  # no interpreter to start (an embedding): the caller compiles what is left
            return
        with p:
            while True:
                with lock:
                    name = queue.pop(0) if queue else None
                if name is None:
                    break
                try:
                    p.stdin.write(name + "\n")
                    p.stdin.flush()
                    reply = p.stdout.readline().split()
                except (OSError, ValueError):  # the worker died: what it held is left to the caller
                    break
                if reply[:2] != ["ok", name]:
                    break
                with lock:
                    done.append(name)
                    say(LINE.format(done=len(done), total=len(todo), name=name))
            with contextlib.suppress(OSError):
                p.stdin.close()

    threads = [threading.Thread(target=run, daemon=True) for _ in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return done


def _worker() -> None:
    """A worker process: compile the modules named on stdin, one a line, answering ``ok NAME`` for each."""
    for k, v in json.loads(os.environ.get(_SETTINGS_ENV, "{}")).items():
        setattr(wp.config, k, v)
    dev = check_device("device", sys.argv[1])
    mods = kernel_modules()
    for line in sys.stdin:
        name = line.strip()
        try:
            _compile_here(mods[name], dev)
        except Exception as e:  # the parent compiles it itself and raises Warp's error there
            print(f"error {name} {type(e).__name__}", flush=True)
            continue
        print(f"ok {name}", flush=True)


_lazy: dict = {}  # per device: the modules missing when the first one was met, and how many were compiled since


def _first_use(module: wp.Module, dev: wp.Device) -> None:
    """Before a kernel module's first load in this process: when the kernel cache lacks it, the progress line
    (Warp then compiles it, in this process). The first such line says how many modules are missing and that
    ``terrainwarp warmup`` compiles them all at once; nothing is printed when the module is cached."""
    try:
        if _binary(module, dev).exists():
            return
        state = _lazy.get(dev.alias)
        if state is None:
            state = _lazy[dev.alias] = {"total": max(len(pending(dev)), 1), "done": 0}
            _say(LINE.format(done=0, total=state["total"], name="(each as it is first needed; 'terrainwarp warmup' "
                                                                 "compiles them all at once, in parallel)"))
    except Exception:  # the check must never stop a launch: the module compiles on load as Warp does
        return
    state["done"] += 1
    _say(LINE.format(done=min(state["done"], state["total"]), total=state["total"],
                     name=module.name.rpartition(".")[2]))


def _say(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


parallel.on_first_load(_first_use)

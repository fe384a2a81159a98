"""The one parallel-launch helper: a kernel's index range split across CPU threads.

Warp's CPU backend runs a launch on the calling thread, one index after another. Its launches release
the GIL (the kernel is called through ctypes), so Python threads that each launch one contiguous chunk
of the outermost index range run on as many cores. :func:`launch` does that on the CPU and launches
once on CUDA:

- A kernel launched through it takes ``offset: int`` as its first parameter (the outermost index of its
  first item; ``i = wp.tid() + offset``, or ``i, j = wp.tid(); i += offset``). With ``parts=True`` it
  takes ``part: int`` second: this chunk's index in ``[0, threads())``, for per-chunk partial sums
  (``out_stats[part, k]``) that the host adds up in a fixed order.
- Chunks are contiguous, in order, and write disjoint ranges. Warp's CPU atomics are plain
  read-modify-writes (the CPU backend has been single-threaded), so a kernel whose chunks may touch the
  same element uses the true atomics below (:func:`atomic_min_u64`, :func:`atomic_min_i32`,
  :func:`atomic_add_i32`), whose result does not depend on order; anything order-dependent gets a
  deterministic merge. Outputs are then bit-identical for any thread count.
- Thread count: ``TERRAINWARP_THREADS`` (environment), or :func:`set_threads`; by default the cores this
  process may use (``os.sched_getaffinity``). Sweep workers set 1 so they never oversubscribe.
- Modules are loaded (compiled) on the calling thread before any chunk starts.
"""

from __future__ import annotations

import ctypes
import math
import os
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager

import numpy as np
import warp as wp

from .checks import check_int
from .device import device_named, launch_block_dim, quietly
from .pool import host_layout

THREADS_ENV = "TERRAINWARP_THREADS"
MIN_ITEMS = 4096  # fewer items per chunk than this are not worth a thread hand-off (~20 us)

_lock = threading.Lock()
_state: dict = {"threads": None, "default": None, "min_items": None, "pool": None, "pool_size": 0, "pid": os.getpid()}


# ------------------------------------------------------------------------------------------------
# true atomics on the CPU (Warp's own are plain read-modify-writes there); CUDA's as on the GPU
# ------------------------------------------------------------------------------------------------


@wp.func_native("""
#if defined(__CUDA_ARCH__)
return (uint64_t)atomicMin((unsigned long long*)wp::address(a, i), (unsigned long long)v);
#else
uint64_t* p = wp::address(a, i);
uint64_t old = __atomic_load_n(p, __ATOMIC_RELAXED);
while (v < old && !__atomic_compare_exchange_n(p, &old, v, true, __ATOMIC_RELAXED, __ATOMIC_RELAXED)) {}
return old;
#endif
""")
def atomic_min_u64(a: wp.array(dtype=wp.uint64), i: int, v: wp.uint64) -> wp.uint64:
    """``a[i] = min(a[i], v)`` atomically; returns the old value."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
return atomicMin(wp::address(a, i, j), v);
#else
int32_t* p = wp::address(a, i, j);
int32_t old = __atomic_load_n(p, __ATOMIC_RELAXED);
while (v < old && !__atomic_compare_exchange_n(p, &old, v, true, __ATOMIC_RELAXED, __ATOMIC_RELAXED)) {}
return old;
#endif
""")
def atomic_min_i32(a: wp.array2d(dtype=wp.int32), i: int, j: int, v: int) -> int:
    """``a[i, j] = min(a[i, j], v)`` atomically; returns the old value."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
return atomicAdd(wp::address(a, i), v);
#else
return __atomic_fetch_add(wp::address(a, i), v, __ATOMIC_RELAXED);
#endif
""")
def atomic_add_i32(a: wp.array(dtype=wp.int32), i: int, v: int) -> int:
    """``a[i] += v`` atomically; returns the old value."""
    ...


# ------------------------------------------------------------------------------------------------
# thread count
# ------------------------------------------------------------------------------------------------


def default_threads() -> int:
    """``TERRAINWARP_THREADS`` when set, else the cores this process may use."""
    env = os.environ.get(THREADS_ENV, "").strip()
    if env:
        try:
            n = int(env)
        except ValueError:
            n = 0
        if n < 1:
            raise ValueError(f"{THREADS_ENV}: expected a positive integer, got {env!r}")
        return n
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def set_threads(n: int | None) -> None:
    """Set the number of CPU threads each kernel launch is split across (``None``: back to the default,
    ``TERRAINWARP_THREADS`` or the cores this process may use). Outputs do not depend on it."""
    if n is not None:
        n = check_int("n", n, 1)
    with _lock:
        _state["threads"] = n


def threads() -> int:
    """The number of CPU threads a launch is split across now (the default is worked out once)."""
    n = _state["threads"]
    if n is None:
        _same_process()
        n = _state["default"]
        if n is None:
            n = _state["default"] = default_threads()
    return n


def set_min_items(n: int | None) -> None:
    """Override every launch's ``min_items`` (``1``: split even the smallest launch as finely as the threads
    allow, as the determinism tests do; ``None``: each launch's own)."""
    if n is not None:
        n = check_int("n", n, 1)
    _state["min_items"] = n


def _same_process() -> None:
    """Forget the thread pool and the default thread count in a forked child (a sweep worker): it has none of
    its parent's pool threads, and maybe other cores. Checked on use; no fork handler is registered."""
    if _state["pid"] != os.getpid():
        _state.update(pool=None, pool_size=0, default=None, pid=os.getpid())


def started() -> None:
    """Start Warp's runtime on this thread, once (``wp.init()``; nothing once it runs). Call it before threads
    that launch kernels start together: Warp's start marks every kernel module modified, and a module being
    loaded on another thread at that moment fails (``KeyError`` in ``Module.load``)."""
    wp.init()


def _pool(n: int) -> ThreadPoolExecutor:
    with _lock:
        _same_process()
        if _state["pool"] is None or _state["pool_size"] < n:
            if _state["pool"] is not None:
                _state["pool"].shutdown(wait=False)
            _state["pool"] = ThreadPoolExecutor(max_workers=n, thread_name_prefix="terrainwarp")
            _state["pool_size"] = n
        return _state["pool"]


# ------------------------------------------------------------------------------------------------
# frame memory: freed frame-sized blocks stay mapped for the next frame
# ------------------------------------------------------------------------------------------------

# glibc mallopt parameters (malloc.h) and the values set: blocks up to 32 MiB (glibc's largest mmap threshold
# on 64-bit) come from the heap, and up to 1 GiB of freed heap stays mapped instead of going back to the kernel;
# glibc's initial values, set back by keep_frame_memory(False)
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
KEEP_TRIM_BYTES, KEEP_TOP_PAD_BYTES, KEEP_MMAP_BYTES = 1 << 30, 64 << 20, 32 << 20
GLIBC_TRIM_BYTES, GLIBC_TOP_PAD_BYTES, GLIBC_MMAP_BYTES = 128 << 10, 128 << 10, 128 << 10


def keep_frame_memory(enable: bool = True) -> bool:
    """Keep freed frame-sized memory mapped in this process (``enable``), so that the next frame's outputs land on
    pages already faulted in, as an engine's per-frame arena does; ``False`` sets glibc's initial thresholds back
    (its dynamic mmap threshold stays off once set). Process-wide: nothing calls it on import
    (``terrainwarp.configure(keep_memory=True)`` and the ``terrainwarp`` command do).

    A frame makes and drops some hundred MB of arrays (vertices, triangles, images). glibc's defaults give
    blocks above a moving threshold back to the kernel on ``free`` and trim the heap's top beyond 2x that
    threshold, so the next frame faults its memory in again: measured on the 1,048,577^2 out-of-core path
    at 1080p, 9-21 thousand page faults and 0.1-0.6 s of system time per later frame (first touch of a
    page costs 0.6-16 ms/MB on this VM, against 0.25 ms/MB for a page seen before); with this setting,
    a handful of faults and ~0 s. Peak memory does not grow: what is kept is what the previous frame held.

    glibc on Linux only (elsewhere nothing changes). Returns whether the allocator was set.
    """
    try:
        libc = ctypes.CDLL(None)
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (macOS, Windows, musl without mallopt)
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    mmap_b, trim_b, pad_b = ((KEEP_MMAP_BYTES, KEEP_TRIM_BYTES, KEEP_TOP_PAD_BYTES) if enable else
                             (GLIBC_MMAP_BYTES, GLIBC_TRIM_BYTES, GLIBC_TOP_PAD_BYTES))
    done = [mallopt(_M_MMAP_THRESHOLD, mmap_b), mallopt(_M_TRIM_THRESHOLD, trim_b), mallopt(_M_TOP_PAD, pad_b)]
    return all(d == 1 for d in done)


# ------------------------------------------------------------------------------------------------
# the kernel clock: how much of a call's wall time its launches took
# ------------------------------------------------------------------------------------------------
_clock = threading.local()
_load_lock = threading.RLock()
_loaded: set = set()
_hook: list = [None]


def _device(device: str | wp.Device | None) -> wp.Device:
    """``wp.get_device``, Warp started quietly first (:func:`.device.device_named`)."""
    return device_named(device)


def on_first_load(hook: Callable[[wp.Module, wp.Device], None] | None) -> None:
    """Call ``hook(module, device)`` before a kernel module is first loaded on a device in this process (None: no
    hook). :mod:`terrainwarp.warmup` sets it: a module that must be compiled first says so, with a progress line,
    instead of compiling in silence."""
    _hook[0] = hook


def load(kernel: wp.Kernel, device: str | wp.Device | None = None) -> None:
    """Build (or read from the kernel cache) and load ``kernel``'s module on ``device`` once per process, for the
    block size its launches use (:func:`.device.launch_block_dim`), under a lock: Warp's code generation parses
    Python sources with ``ast``, which CPython 3.11 does not allow from two threads at once (``SystemError: AST
    constructor recursion depth mismatch``), so the first frames of threads that start together must not build a
    module side by side. Warp's per-module INFO lines are held back (:func:`.device.quietly`). Every launch helper
    here calls it."""
    dev = _device(device)
    key = (kernel.module, dev.alias)
    if key in _loaded:
        return
    with _load_lock:
        if key not in _loaded:
            if _hook[0] is not None:
                _hook[0](kernel.module, dev)
            with quietly():
                kernel.module.load(dev, block_dim=launch_block_dim(dev))
            _loaded.add(key)


@contextmanager
def kernel_clock() -> Iterator[list[float]]:
    """Time the launches this thread makes inside the block: yields a one-element list whose value grows by
    the wall seconds of each launch (:func:`launch`, :func:`launch_one`, :func:`replay`, :func:`scan`: the
    kernel and Warp's packing of its arguments, every chunk's thread included). Clocks nest: an inner block's
    seconds count in the outer one too. What a caller spends outside them is host work: allocation, copies,
    numpy, Python."""
    outer = getattr(_clock, "acc", None)
    acc = [0.0]
    _clock.acc = acc
    try:
        yield acc
    finally:
        _clock.acc = outer
        if outer is not None:
            outer[0] += acc[0]


def _timed(run: Callable[[], object]) -> object:
    acc = getattr(_clock, "acc", None)
    if acc is None:
        return run()
    t0 = time.perf_counter()
    try:
        return run()
    finally:
        acc[0] += time.perf_counter() - t0


def launch_one(kernel: wp.Kernel, dim: int | Sequence[int], inputs: Sequence = (), outputs: Sequence = (),
               device: str | wp.Device | None = None) -> None:
    """``wp.launch`` on one thread (a launch too small or too serial to split), on the :func:`kernel_clock`."""
    load(kernel, device)
    _timed(lambda: wp.launch(kernel, dim=dim, inputs=list(inputs), outputs=list(outputs), device=device))


def record(kernel: wp.Kernel, dim: int | Sequence[int], inputs: Sequence = (), outputs: Sequence = (),
           device: str | wp.Device | None = None) -> wp.Launch:
    """A launch recorded once (``wp.launch(..., record_cmd=True)``, the module :func:`load`-ed first), to
    :func:`replay` per frame without packing its arguments again."""
    load(kernel, device)
    return wp.launch(kernel, dim=dim, inputs=list(inputs), outputs=list(outputs), device=device, record_cmd=True)


def replay(cmd: wp.Launch) -> None:
    """Replay a launch recorded with ``wp.launch(..., record_cmd=True)``, on the :func:`kernel_clock`."""
    _timed(cmd.launch)


def scan(values: wp.array, out: wp.array, inclusive: bool = False) -> None:
    """``wp.utils.array_scan`` (the prefix sum of count -> scan -> emit), on the :func:`kernel_clock`."""
    _timed(lambda: wp.utils.array_scan(values, out, inclusive=inclusive))


# ------------------------------------------------------------------------------------------------
# launch
# ------------------------------------------------------------------------------------------------


def view(a: np.ndarray, dtype: type, device: str | wp.Device | None = None) -> wp.array:
    """A Warp array of ``a`` (contiguous, the dtype's scalar type): on the CPU the same memory, not a copy. A
    heightmap-sized input (heights, a normal map) read by every frame is then never copied per frame."""
    dev = _device(device)
    scalar = wp.dtype_to_numpy(getattr(dtype, "_wp_scalar_type_", dtype))
    return wp.array(np.ascontiguousarray(a, scalar), dtype=dtype, device=dev, copy=not dev.is_cpu)


def empty(shape: int | Sequence[int], dtype: type, device: str | wp.Device | None = None) -> wp.array:
    """``wp.empty``, but on the CPU through numpy, whose large allocations ask for huge pages: the first
    touch of a frame-sized output (by a launch's threads) then costs 2-3x less page faulting."""
    dev = _device(device)
    if not dev.is_cpu:
        return wp.empty(shape, dtype=dtype, device=dev)
    a = np.empty(*host_layout(shape, dtype))
    return wp.array(a, dtype=dtype, device=dev, copy=False)



def chunks(n: int, items_per_row: int = 1, min_items: int = MIN_ITEMS, oversplit: int = 1) -> list[tuple[int, int]]:
    """The contiguous ``[start, stop)`` ranges of the outermost index (``n`` rows of ``items_per_row``)
    that a CPU launch hands to its threads: at most ``threads() * oversplit`` of them."""
    if n <= 0:
        return []
    min_items = _state["min_items"] or min_items
    k = min(threads() * max(oversplit, 1), n, max(1, (n * max(items_per_row, 1)) // max(min_items, 1)))
    step = math.ceil(n / k)
    return [(s, min(s + step, n)) for s in range(0, n, step)]


def max_parts(oversplit: int = 1) -> int:
    """Rows a ``parts=True`` launch may index (``part`` is below this)."""
    return threads() * max(oversplit, 1)


def launch(kernel: wp.Kernel, dim: int | Sequence[int], inputs: Sequence = (), outputs: Sequence = (),
           device: str | wp.Device | None = None, *, parts: bool = False, min_items: int = MIN_ITEMS,
           oversplit: int = 1) -> None:
    """Launch ``kernel`` over ``dim``, split along the outermost index across :func:`threads` CPU threads.

    Args:
        kernel: a Warp kernel whose first parameter is ``offset: int`` (and second ``part: int`` with
            ``parts=True``), then the ``inputs`` and ``outputs`` given here.
        dim: the whole launch (an int or a shape); chunks split ``dim[0]``.
        parts: pass each chunk its index (``part``, below :func:`max_parts`) as well as its offset.
        min_items: the fewest items (product of the chunk's shape) worth a thread of their own.
        oversplit: chunks per thread, taken in turn by whichever thread is free (for uneven work per
            item: patches of different sizes, triangles near and far).
    """
    shape = (int(dim),) if isinstance(dim, int | np.integer) else tuple(int(d) for d in dim)
    dev = _device(device)
    if shape[0] <= 0 or math.prod(shape) == 0:
        return
    load(kernel, dev)
    _timed(lambda: _split_launch(kernel, shape, inputs, outputs, dev, parts, min_items, oversplit))


def _split_launch(kernel: wp.Kernel, shape: tuple[int, ...], inputs: Sequence, outputs: Sequence, dev: wp.Device,
                  parts: bool, min_items: int, oversplit: int) -> None:
    head = (0, 0) if parts else (0,)
    if not dev.is_cpu or threads() == 1:
        wp.launch(kernel, dim=shape, inputs=[*head, *inputs], outputs=list(outputs), device=dev)
        return
    ranges = chunks(shape[0], math.prod(shape[1:]), min_items, oversplit)
    if len(ranges) == 1:
        wp.launch(kernel, dim=shape, inputs=[*head, *inputs], outputs=list(outputs), device=dev)
        return
    order = iter(range(len(ranges)))  # next() on it is atomic under the GIL

    def work() -> None:
        for k in order:
            s, e = ranges[k]
            wp.launch(kernel, dim=(e - s, *shape[1:]), inputs=[*((s, k) if parts else (s,)), *inputs],
                      outputs=list(outputs), device=dev)

    helpers = min(threads(), len(ranges)) - 1
    futures = [_pool(helpers).submit(work) for _ in range(helpers)]
    try:
        work()
    finally:
        for f in futures:
            f.result()

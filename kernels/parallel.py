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
import sys
import threading
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import warp as wp

THREADS_ENV = "TERRAINWARP_THREADS"
MIN_ITEMS = 4096  # fewer items per chunk than this are not worth a thread hand-off (~20 us)

_lock = threading.Lock()
_state: dict = {"threads": None, "default": None, "min_items": None, "pool": None, "pool_size": 0}


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
        if isinstance(n, bool) or not isinstance(n, int):
            raise TypeError(f"n: expected an integer or None, got {n!r}")
        if n < 1:
            raise ValueError(f"n: expected at least 1 thread, got {n}")
    with _lock:
        _state["threads"] = n


def threads() -> int:
    """The number of CPU threads a launch is split across now (the default is worked out once)."""
    n = _state["threads"]
    if n is None:
        n = _state["default"]
        if n is None:
            n = _state["default"] = default_threads()
    return n


def set_min_items(n: int | None) -> None:
    """Override every launch's ``min_items`` (``1``: split even the smallest launch as finely as the threads
    allow, as the determinism tests do; ``None``: each launch's own)."""
    if n is not None and (isinstance(n, bool) or not isinstance(n, int) or n < 1):
        raise ValueError(f"n: expected a positive integer or None, got {n!r}")
    _state["min_items"] = n


def _pool(n: int) -> ThreadPoolExecutor:
    with _lock:
        if _state["pool"] is None or _state["pool_size"] < n:
            if _state["pool"] is not None:
                _state["pool"].shutdown(wait=False)
            _state["pool"] = ThreadPoolExecutor(max_workers=n, thread_name_prefix="terrainwarp")
            _state["pool_size"] = n
        return _state["pool"]


def _forget_pool() -> None:  # a forked child (a sweep worker) has no pool threads, maybe other cores
    _state["pool"] = None
    _state["pool_size"] = 0
    _state["default"] = None


os.register_at_fork(after_in_child=_forget_pool)


# ------------------------------------------------------------------------------------------------
# frame memory: freed frame-sized blocks stay mapped for the next frame
# ------------------------------------------------------------------------------------------------

KEEP_MEMORY_ENV = "TERRAINWARP_KEEP_MEMORY"
# glibc mallopt parameters (malloc.h) and the values set: blocks up to 32 MiB (glibc's largest mmap threshold
# on 64-bit) come from the heap, and up to 1 GiB of freed heap stays mapped instead of going back to the kernel
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
KEEP_TRIM_BYTES, KEEP_TOP_PAD_BYTES, KEEP_MMAP_BYTES = 1 << 30, 64 << 20, 32 << 20


def keep_frame_memory(enable: bool | None = None) -> bool:
    """Keep freed frame-sized memory mapped in this process, so that the next frame's outputs land on pages
    already faulted in, as an engine's per-frame arena does. Called once when terrainwarp is imported.

    A frame makes and drops some hundred MB of arrays (vertices, triangles, images). glibc's defaults give
    blocks above a moving threshold back to the kernel on ``free`` and trim the heap's top beyond 2x that
    threshold, so the next frame faults its memory in again: measured on the 1,048,577^2 out-of-core path
    at 1080p, 9-21 thousand page faults and 0.1-0.6 s of system time per later frame (first touch of a
    page costs 0.6-16 ms/MB on this VM, against 0.25 ms/MB for a page seen before); with this setting,
    a handful of faults and ~0 s. Peak memory does not grow: what is kept is what the previous frame held.

    glibc on Linux only (elsewhere nothing changes). ``enable``: None reads ``TERRAINWARP_KEEP_MEMORY``
    (``0`` turns it off; default on). Returns whether the allocator was set. It is process-wide; an
    application that wants its freed memory back at once sets ``TERRAINWARP_KEEP_MEMORY=0``.
    """
    if enable is None:
        enable = os.environ.get(KEEP_MEMORY_ENV, "1").strip() not in ("0", "false", "no", "off")
    if not enable:
        return False
    try:
        libc = ctypes.CDLL(None)
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (macOS, Windows, musl without mallopt)
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    done = [mallopt(_M_MMAP_THRESHOLD, KEEP_MMAP_BYTES), mallopt(_M_TRIM_THRESHOLD, KEEP_TRIM_BYTES),
            mallopt(_M_TOP_PAD, KEEP_TOP_PAD_BYTES)]
    return all(d == 1 for d in done)


# ------------------------------------------------------------------------------------------------
# launch
# ------------------------------------------------------------------------------------------------


def view(a: np.ndarray, dtype: type, device: str | wp.Device | None = None) -> wp.array:
    """A Warp array of ``a`` (contiguous, the dtype's scalar type): on the CPU the same memory, not a copy. A
    heightmap-sized input (heights, a normal map) read by every frame is then never copied per frame."""
    dev = wp.get_device(device)
    scalar = wp.dtype_to_numpy(getattr(dtype, "_wp_scalar_type_", dtype))
    return wp.array(np.ascontiguousarray(a, scalar), dtype=dtype, device=dev, copy=not dev.is_cpu)


def empty(shape: int | Sequence[int], dtype: type, device: str | wp.Device | None = None) -> wp.array:
    """``wp.empty``, but on the CPU through numpy, whose large allocations ask for huge pages: the first
    touch of a frame-sized output (by a launch's threads) then costs 2-3x less page faulting."""
    dev = wp.get_device(device)
    if not dev.is_cpu:
        return wp.empty(shape, dtype=dtype, device=dev)
    a = np.empty(*host_layout(shape, dtype))
    return wp.array(a, dtype=dtype, device=dev, copy=False)


def host_layout(shape: int | Sequence[int], dtype: type) -> tuple[tuple[int, ...], np.dtype]:
    """The numpy (shape, dtype) of a Warp array of ``shape`` and ``dtype`` (a vector type adds its own axes)."""
    shape = (int(shape),) if isinstance(shape, int | np.integer) else tuple(int(d) for d in shape)
    scalar = getattr(dtype, "_wp_scalar_type_", dtype)
    return (*shape, *tuple(getattr(dtype, "_shape_", ()))), np.dtype(wp.dtype_to_numpy(scalar))



# ------------------------------------------------------------------------------------------------
# the frame-buffer pool: frame- and heightmap-sized outputs reused once nothing references them
# ------------------------------------------------------------------------------------------------
_POOL: dict[tuple, list[np.ndarray]] = {}
_POOL_LOCK = threading.Lock()


def _unreferenced() -> int:
    """sys.getrefcount of a list's item that nothing else references (the list's reference and the call's)."""
    kept = [np.empty(1)]
    return sys.getrefcount(kept[0])


_FREE_REFS = _unreferenced()


def _free(kept: list[np.ndarray]) -> list[int]:
    """Indices of the kept buffers nothing references any more (no view of one alive: its only references are
    the pool's list and the check's own)."""
    return [i for i in range(len(kept)) if sys.getrefcount(kept[i]) == _FREE_REFS]


def pooled(shape: tuple[int, ...], dtype: type, keep: int = 2, max_bytes: int = 64 << 20) -> np.ndarray:
    """An uninitialised host array for an output: a kept one of this (shape, dtype) that nothing references any
    more (no view of it alive: its only references are the pool's and the check's own), else a new one, kept
    when fewer than ``keep`` are and it is at most ``max_bytes``.

    Blocks above glibc's largest mmap threshold (32 MiB) go back to the kernel when freed, and on this kind of
    VM faulting fresh memory in costs 0.6-16 ms/MB (against ~0.25 ms/MB to write memory seen before): a frame's
    images, or a heightmap-sized error pass, would pay that on every frame. A caller that holds an output
    keeps it: only an array nobody holds is handed out again."""
    key = (tuple(int(d) for d in shape), np.dtype(dtype).str)
    with _POOL_LOCK:
        kept = _POOL.setdefault(key, [])
        free = _free(kept)
        if free:
            return kept[free[0]]
        a = np.empty(key[0], dtype)  # numpy's large allocations ask for huge pages (see empty)
        if len(kept) < keep and a.nbytes <= max_bytes:
            kept.append(a)
        return a


def pooled_rows(shape: tuple[int, ...], dtype: type, keep: int = 2) -> np.ndarray:
    """The first ``shape[0]`` rows of a kept buffer that nothing references any more and has at least that many
    rows (the smallest such), else of a new one with up to 1/64 more rows (at most 1.6% unused), kept in place
    of the smallest unreferenced one when ``keep`` are kept already. For outputs whose length changes from
    frame to frame (a tessellation's points and triangles): an exact-shape pool (:func:`pooled`) would never
    hit, and a frame of 134 M triangles writes 2.5 GB that would otherwise be faulted in again on every frame.
    The view holds its buffer: a caller that keeps the output keeps it from the pool."""
    n, rest = int(shape[0]), tuple(int(d) for d in shape[1:])
    key = ("rows", rest, np.dtype(dtype).str)
    with _POOL_LOCK:
        kept = _POOL.setdefault(key, [])
        free = _free(kept)
        fits = [i for i in free if kept[i].shape[0] >= n]
        if fits:
            return kept[min(fits, key=lambda i: kept[i].shape[0])][:n]
        grain = 1 << max(int(n).bit_length() - 7, 0)  # <= 1/64 more rows: a slowly growing frame still hits
        a = np.empty((-(-n // grain) * grain, *rest), dtype)
        if len(kept) < keep:
            kept.append(a)
        elif free:  # the kept buffers adapt to the frames: the smallest unreferenced one makes way
            kept[min(free, key=lambda i: kept[i].shape[0])] = a
        return a[:n]


def release_buffers() -> int:
    """Drop every kept buffer of the pool (those still held stay with their holders); returns the bytes the pool
    let go. For an application done with frames of a large heightmap: the error pass keeps one buffer of each
    heightmap-sized kind (up to 1 GiB each) for the next frame, the tessellator two of each of its outputs."""
    with _POOL_LOCK:
        n = sum(a.nbytes for kept in _POOL.values() for a in kept)
        _POOL.clear()
    return n


def pooled_array(shape: int | Sequence[int], dtype: type, device: str | wp.Device | None = None, *,
                 keep: int = 1, max_bytes: int = 1 << 30) -> wp.array:
    """:func:`empty` from the frame-buffer pool (:func:`pooled`) on the CPU; ``wp.empty`` on CUDA. For outputs
    as large as the heightmap that a frame makes and drops (an error pass's maps): one kept per shape."""
    dev = wp.get_device(device)
    if not dev.is_cpu:
        return wp.empty(shape, dtype=dtype, device=dev)
    a = pooled(*host_layout(shape, dtype), keep, max_bytes)
    return wp.array(a, dtype=dtype, device=dev, copy=False)


def pooled_rows_array(n: int, dtype: type, device: str | wp.Device | None = None, *, keep: int = 2) -> wp.array:
    """:func:`empty` of ``n`` items from :func:`pooled_rows` on the CPU; ``wp.empty`` on CUDA."""
    dev = wp.get_device(device)
    if not dev.is_cpu:
        return wp.empty(n, dtype=dtype, device=dev)
    a = pooled_rows(*host_layout(n, dtype), keep)
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
    dev = wp.get_device(device)
    if shape[0] <= 0 or math.prod(shape) == 0:
        return
    head = (0, 0) if parts else (0,)
    if not dev.is_cpu or threads() == 1:
        wp.launch(kernel, dim=shape, inputs=[*head, *inputs], outputs=list(outputs), device=dev)
        return
    ranges = chunks(shape[0], math.prod(shape[1:]), min_items, oversplit)
    if len(ranges) == 1:
        wp.launch(kernel, dim=shape, inputs=[*head, *inputs], outputs=list(outputs), device=dev)
        return
    kernel.module.load(dev)  # compile / load once, here, before any thread launches it
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

"""The frame-buffer pool: frame- and heightmap-sized buffers leased to their users and given back.

Freshly allocated frame-sized memory costs page faults on its first write (0.6-16 ms/MB on this kind of VM,
against ~0.25 ms/MB to write memory seen before), and blocks above glibc's largest mmap threshold (32 MiB) go
back to the kernel when freed: a frame's images, its tessellation or a heightmap-sized error pass would pay
that on every frame. So such buffers are kept and lent again. Every buffer is held through a :class:`Lease`, and a
buffer is lent again only after its lease has ended. Who ends a lease differs by kind: a scratch lease is given
back explicitly by the function that took it; an output lease is owned by the arrays made from it and ends when the
last of them is garbage (a reference count decides, through ``weakref.finalize``), because a caller who keeps a
frame's images cannot be asked to hand them back. The two kinds:

* **Output leases** (:func:`pooled`, :func:`pooled_rows`, :func:`pooled_array`, :func:`pooled_rows_array`):
  the array handed out is made from its lease (numpy's ``__array_interface__``), so the array, every numpy
  view of it and every Warp array made from it reference the lease. The lease ends when the last of them is
  dropped, and its buffer goes back to the pool then (``weakref.finalize``, in whichever thread drops it).
  A frame, or any view of its outputs, that the caller keeps is never written by a later frame. A raw
  pointer (``ctypes``, ``__array_interface__['data']``, ``wp.array(ptr=...)``) does not hold the lease:
  keep an array alive as long as its pointer is used.
* **Scratch leases** (:func:`take`, :meth:`Lease.give_back`): a buffer one function takes and gives back
  itself when it is done (the rasterizer's work arrays for a call, which the next call clears). A scratch lease
  that is never given back (its function failed part-way) is dropped with its buffer: its state is unknown.

At most ``keep`` buffers of a kind are kept (leased or free); more are plain allocations that nobody keeps.
:func:`release_buffers` lets every free buffer go (leased ones are dropped when their lease ends).
Thread-safe: leases may be taken and ended from any thread.
"""

from __future__ import annotations

import math
import threading
import weakref
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import warp as wp

__all__ = ["Lease", "pooled", "pooled_rows", "pooled_array", "pooled_rows_array", "pooled_arrays", "filled_array",
           "take", "release_buffers", "kept_bytes", "host_layout"]


class _Kind:
    """The kept buffers of one kind: those free to lend, and how many are lent out."""

    __slots__ = ("free", "leased")

    def __init__(self) -> None:
        self.free: list[Any] = []
        self.leased = 0


_LOCK = threading.Lock()
_KINDS: dict[tuple, _Kind] = {}
_ENDED: deque = deque()  # (kind, generation, buffer or None) of ended leases: appended by finalizers, drained below
_GEN = [0]  # bumped by release_buffers: leases taken before it end without coming back


class Lease:
    """One kept buffer while it is lent. ``buffer`` is the pool's allocation (a numpy array on the CPU, or a
    device Warp array for a scratch lease). An output lease exposes ``__array_interface__`` (the handed-out
    shape over the buffer's memory), so arrays made from it keep it alive."""

    __slots__ = ("buffer", "kind", "gen", "_end", "__array_interface__", "__weakref__")

    def __init__(self, kind: tuple, buffer: Any, gen: int, *, returns_on_drop: bool) -> None:
        self.buffer, self.kind, self.gen = buffer, kind, gen
        # an output lease ends when nothing references it; a scratch lease dropped without give_back() frees its
        # slot and takes its buffer with it
        self._end = weakref.finalize(self, _ENDED.append, (kind, self.gen, buffer if returns_on_drop else None))
        self._end.atexit = False

    def give_back(self) -> None:
        """End a scratch lease: its buffer is lent again, as the caller leaves it. Once only; later calls do
        nothing."""
        if self._end.detach() is not None:
            _ENDED.append((self.kind, self.gen, self.buffer))

    def array(self, shape: tuple[int, ...], dtype: np.dtype) -> np.ndarray:
        """An array of ``shape`` over the start of the buffer that keeps this lease alive."""
        self.__array_interface__ = {"shape": tuple(shape), "typestr": np.dtype(dtype).str, "version": 3,
                                    "data": (self.buffer.ctypes.data, False)}
        return np.asarray(self)


def _drain() -> None:
    """Take the ended leases' buffers back (under _LOCK)."""
    while _ENDED:
        kind, gen, buf = _ENDED.popleft()
        k = _KINDS.get(kind)
        if k is None or gen != _GEN[0]:
            continue  # released meanwhile: the buffer goes with its lease
        k.leased -= 1
        if buf is not None:
            k.free.append(buf)


def _lend(kind: tuple, pick: Callable[[list], int | None], make: Callable[[], Any], keep: int, keepable: bool,
          *, returns_on_drop: bool) -> tuple[Any, Lease | None]:
    """A free kept buffer of ``kind`` that ``pick`` chooses (an index into the free list, or None), else a new
    one from ``make``: kept (leased) while fewer than ``keep`` are and it is ``keepable``; when ``keep`` are kept
    already, a new buffer takes the place of the first free one ``pick`` passed over (the kept buffers adapt).
    Returns (buffer, its lease, or None for a buffer nobody keeps)."""
    with _LOCK:
        _drain()
        k = _KINDS.setdefault(kind, _Kind())
        i = pick(k.free)
        if i is not None:
            buf = k.free.pop(i)
        else:
            buf = None
            if keepable and k.leased + len(k.free) >= keep and k.free:
                k.free.pop(0)  # the smallest (the free list is kept sorted by size where sizes differ)
            if not keepable or k.leased + len(k.free) >= keep:
                return make(), None
        k.leased += 1
        gen = _GEN[0]
    if buf is None:
        try:
            buf = make()
        except BaseException:
            with _LOCK:
                if gen == _GEN[0] and kind in _KINDS:
                    _KINDS[kind].leased -= 1
            raise
    return buf, Lease(kind, buf, gen, returns_on_drop=returns_on_drop)


_LAYOUTS: dict[type, tuple[tuple[int, ...], np.dtype]] = {}  # Warp dtype -> (its own axes, numpy scalar dtype)


def host_layout(shape: int | Sequence[int], dtype: type) -> tuple[tuple[int, ...], np.dtype]:
    """The numpy (shape, dtype) of a Warp array of ``shape`` and ``dtype`` (a vector type adds its own axes)."""
    shape = (int(shape),) if isinstance(shape, int | np.integer) else tuple(int(d) for d in shape)
    lay = _LAYOUTS.get(dtype) or _layout(dtype)
    return (*shape, *lay[0]), lay[1]


def _layout(dtype: type) -> tuple[tuple[int, ...], np.dtype]:
    """(a Warp dtype's own axes, its numpy scalar dtype), kept in _LAYOUTS."""
    scalar = getattr(dtype, "_wp_scalar_type_", dtype)
    lay = _LAYOUTS[dtype] = (tuple(getattr(dtype, "_shape_", ())), np.dtype(wp.dtype_to_numpy(scalar)))
    return lay


def _lend_exact(shape: tuple[int, ...], dt: np.dtype, keep: int, max_bytes: int, tag: str):
    """:func:`pooled`'s buffer and lease (None: a buffer nobody keeps)."""
    return _lend(("exact", shape, dt.str, tag), lambda free: 0 if free else None, lambda: np.empty(shape, dt), keep,
                 math.prod(shape) * dt.itemsize <= max_bytes, returns_on_drop=True)


def _lend_rows(n: int, rest: tuple[int, ...], dt: np.dtype, keep: int, tag: str):
    """:func:`pooled_rows`' buffer and lease (None: a buffer nobody keeps)."""
    grain = 1 << max(n.bit_length() - 7, 0)  # <= 1/64 more rows: a slowly growing frame still hits
    rows = -(-n // grain) * grain

    def pick(free: list) -> int | None:
        free.sort(key=lambda b: b.shape[0])
        return next((i for i, b in enumerate(free) if b.shape[0] >= n), None)

    return _lend(("rows", rest, dt.str, tag), pick, lambda: np.empty((rows, *rest), dt), keep, True,
                 returns_on_drop=True)


def pooled(shape: tuple[int, ...], dtype: type, keep: int = 2, max_bytes: int = 64 << 20, *,
           tag: str = "") -> np.ndarray:
    """An uninitialised host array for an output, on an output lease: a kept buffer of this (shape, dtype) whose
    last lease has ended, else a new one, kept when fewer than ``keep`` are and it is at most ``max_bytes``.
    ``tag`` names a kind of its own (buffers of other tags are never lent for it)."""
    shape = tuple(int(d) for d in shape)
    dt = np.dtype(dtype)
    buf, lease = _lend_exact(shape, dt, keep, max_bytes, tag)
    return buf if lease is None else lease.array(shape, dt)


def pooled_rows(shape: tuple[int, ...], dtype: type, keep: int = 2, *, tag: str = "") -> np.ndarray:
    """An uninitialised host array of ``shape`` on an output lease of a kept buffer with at least ``shape[0]`` rows
    (the smallest free one), else of a new one with up to 1/64 more rows (at most 1.6% unused), kept in place of
    the smallest free one when ``keep`` are kept already. For outputs whose length changes from frame to frame (a
    tessellation's points and triangles): an exact-shape pool (:func:`pooled`) would never hit, and a frame of
    134 M triangles writes 2.5 GB that would otherwise be faulted in again on every frame. ``tag`` names a kind of
    its own (buffers of other tags are never lent for it)."""
    n, rest = int(shape[0]), tuple(int(d) for d in shape[1:])
    dt = np.dtype(dtype)
    buf, lease = _lend_rows(n, rest, dt, keep, tag)
    return buf[:n] if lease is None else lease.array((n, *rest), dt)


def pooled_array(shape: int | Sequence[int], dtype: type, device: str | wp.Device | None = None, *,
                 keep: int = 1, max_bytes: int = 1 << 30) -> wp.array:
    """A Warp array from :func:`pooled` on the CPU (the Warp array holds the lease); ``wp.empty`` on CUDA. For
    outputs as large as the heightmap that a frame makes and drops (an error pass's maps): one kept per shape."""
    dev = wp.get_device(device)
    if not dev.is_cpu:
        return wp.empty(shape, dtype=dtype, device=dev)
    a = pooled(*host_layout(shape, dtype), keep, max_bytes)
    return wp.array(a, dtype=dtype, device=dev, copy=False)


def filled_array(shape: int | Sequence[int], dtype: type, value: float, device: str | wp.Device | None = None, *,
                 keep: int = 2, max_bytes: int = 64 << 20) -> wp.array:
    """A Warp array holding ``value`` everywhere: on the CPU from :func:`pooled` (a kept buffer, filled), on CUDA
    ``wp.zeros`` / ``wp.full``."""
    dev = wp.get_device(device)
    if not dev.is_cpu:
        return wp.zeros(shape, dtype=dtype, device=dev) if value == 0 else wp.full(shape, value=value, dtype=dtype,
                                                                                   device=dev)
    a = pooled(*host_layout(shape, dtype), keep, max_bytes)
    a.fill(value)
    return wp.array(a, dtype=dtype, device=dev, copy=False)


def pooled_rows_array(n: int, dtype: type, device: str | wp.Device | None = None, *, keep: int = 2) -> wp.array:
    """A Warp array of ``n`` items from :func:`pooled_rows` on the CPU; ``wp.empty`` on CUDA."""
    dev = wp.get_device(device)
    if not dev.is_cpu:
        return wp.empty(n, dtype=dtype, device=dev)
    a = pooled_rows(*host_layout(n, dtype), keep)
    return wp.array(a, dtype=dtype, device=dev, copy=False)


BLOCK_ALIGN = 64  # bytes: where each array of a block starts (a cache line; SIMD stores align to it)


def pooled_arrays(fields: Sequence[tuple[int, type]], device: str | wp.Device | None = None, *, tag: str,
                  rows: bool = True, keep: int = 2, max_bytes: int = 64 << 20,
                  host: bool = False) -> list[wp.array] | tuple[list[wp.array], list[np.ndarray] | None]:
    """Warp arrays of ``n`` items of ``dtype`` for each ``(n, dtype)`` of ``fields``, carved on the CPU from one
    output lease of a kept byte buffer, each at a :data:`BLOCK_ALIGN` boundary: outputs that a call makes together
    and that live together (a tessellation's point fields and triangles, a frame's two images) take one lease
    instead of one each. The lease ends when the last of the arrays (or anything made from them) is dropped. The
    buffer is of kind ``tag``: with ``rows`` as :func:`pooled_rows` (the smallest free one with room, lengths that
    change from call to call), else as :func:`pooled` (exactly this size, kept when at most ``max_bytes``). On
    CUDA: ``wp.empty`` each. With ``host``: (the arrays, numpy arrays over the same memory, each ``(n, *the dtype's
    axes)`` and holding the lease too; None on CUDA)."""
    dev = wp.get_device(device)
    if not dev.is_cpu:
        arrays = [wp.empty(n, dtype=dt, device=dev) for n, dt in fields]
        return (arrays, None) if host else arrays
    starts, lays, total = [], [], 0
    for n, dt in fields:
        lay = _LAYOUTS.get(dt) or _layout(dt)
        starts.append(total)
        lays.append(lay)
        total += -(-(int(n) * math.prod(lay[0]) * lay[1].itemsize) // BLOCK_ALIGN) * BLOCK_ALIGN
    lines = max(total // BLOCK_ALIGN, 1)
    u8 = np.dtype(np.uint8)
    buf, lease = (_lend_rows(lines, (BLOCK_ALIGN,), u8, keep, tag) if rows else
                  _lend_exact((lines, BLOCK_ALIGN), u8, keep, max_bytes, tag))
    base = buf.ctypes.data
    flat = buf.reshape(-1) if lease is None or not host else lease.array((lines * BLOCK_ALIGN,), u8)

    def holds(ptr: int, size: int, lease: Lease | np.ndarray = flat if lease is None or host else lease) -> None:
        """The arrays' deleter: nothing to free; while an array lives, it holds the lease (or the unkept buffer)."""

    arrays = [wp.array(ptr=base + o, shape=(int(n),), dtype=dt, device=dev, deleter=holds)
              for o, (n, dt) in zip(starts, fields, strict=True)]
    if not host:
        return arrays
    views = [flat[o:o + int(n) * math.prod(inner) * npdt.itemsize].view(npdt).reshape(int(n), *inner)
             for o, (n, _), (inner, npdt) in zip(starts, fields, lays, strict=True)]
    return arrays, views


def take(kind: tuple, make: Callable[[], Any], keep: int = 2) -> Lease:
    """A scratch lease of a buffer of ``kind`` (any hashable naming its size, dtype and device): a free kept one,
    as the last holder gave it back, or a new one from ``make``. The caller gives it back
    (:meth:`Lease.give_back`) when it is done and the buffer is in the state the next taker expects; a lease
    that is dropped instead takes its buffer with it. At most ``keep`` are kept per kind."""
    buf, lease = _lend(("scratch", *kind), lambda free: len(free) - 1 if free else None, make, keep, True,
                       returns_on_drop=False)
    return lease if lease is not None else Lease(("unkept",), buf, -1, returns_on_drop=False)


def release_buffers() -> int:
    """Let every free kept buffer go, and forget the lent ones (they are dropped with their leases); returns the
    bytes let go now. For an application done with frames of a large heightmap: the error pass keeps one
    buffer of each heightmap-sized kind (up to 1 GiB each), the tessellator two of each of its outputs."""
    with _LOCK:
        _drain()
        n = sum(int(getattr(b, "nbytes", 0) or 0) for k in _KINDS.values() for b in k.free)
        _KINDS.clear()
        _GEN[0] += 1
    return n


def kept_bytes() -> dict[str, int]:
    """What the pool keeps now: ``{"free": bytes, "free_buffers": n, "leased_buffers": n}``."""
    with _LOCK:
        _drain()
        return {"free": sum(int(getattr(b, "nbytes", 0) or 0) for k in _KINDS.values() for b in k.free),
                "free_buffers": sum(len(k.free) for k in _KINDS.values()),
                "leased_buffers": sum(k.leased for k in _KINDS.values())}

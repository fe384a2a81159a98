"""Pyramids and overview windows of a streamed heightmap: selection and displacement that read only what a
frame needs.

A :class:`StreamedPyramid` gives the quadtree its per-node (min, max, geometric error) without the grid
in memory, in one of two ways:

* **exact** (files and arrays; any source with ``exact=True``): built once, root by root (a root's
  window of samples at a time, never the grid), by the same kernel as the in-memory pyramids, so every
  value is bit for bit the in-memory one. For a file the result is kept in a cache beside it
  (``<file>.twcache/``, or ``~/.cache/terrainwarp/tiles/`` when that folder is read-only), reused across
  runs and rebuilt when the file's content changes (a SHA-256 of the whole file, worked out again whenever
  its size, modification time, change time or inode differ: :func:`terrainwarp.io.cache.content_digest`).
  The same pass writes the point-sampled overviews (steps 2, 4, ...) that far patches read, tile by tile
  (a root row's strip and one row of tiles per step in memory, written with ``pwrite``: the build's memory
  is a few tiles and the pyramid's node arrays, whatever the raster's size), and the file's height range.
  The cache checks itself (:mod:`terrainwarp.io.cache`): the node arrays (12 bytes a node: about 1% of the
  raster) when opened, the overviews tile by tile as each is read; a missing, truncated or corrupt file is
  rebuilt (or the error names it; an overview tile that fails its check mid-frame is read from the file
  instead, and its overview rebuilt on the next open), and threads and processes that open a new file at
  once build its cache once, under a lock, the others waiting.
* **on demand** (procedural sources, whose overviews have a known :meth:`detail_bound`): the nodes a
  selection visits are worked out in blocks of ``BLOCK`` x ``BLOCK`` nodes from the overview whose step
  is 1/8 of the node's vertex spacing (each node seen through an (8T + 1)^2 window), and widened by the
  bound on what that overview leaves out: min - b, max + b, error + b. The bounds are conservative, so
  the selection refines at least as far as the exact pyramid would; they are exact (b = 0) where the
  step is 1. Blocks live in an LRU of ``MAX_BLOCKS``.

:func:`overview_windows` picks, for a frame's patches, one window per overview step: the bounding box of
the patches whose vertex spacing is at least that step, so memory follows the frame, not the grid.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from collections.abc import Callable

import numpy as np

from ..heightmap import StreamedHeightmap
from ..io.cache import CacheError, CacheFolder, TiledWriter
from ..io.tiles import TILE, GeoTiffSource, TileCache
from ..kernels.pyramid import node_stats

__all__ = ["StreamedPyramid", "overview_windows", "root_pyramid", "BLOCK", "MAX_BLOCKS"]

BLOCK = 4  # nodes per side of an on-demand stats block
MAX_BLOCKS = 65536  # on-demand blocks kept (3 x 4 x 4 float32 each: 12 MiB in all)
FINEST = 8  # the finest step a node is measured at: 1/8 of its vertex spacing (1 at the finest levels)
WINDOW_MARGIN = 2  # overview samples around a window's patches (bilinear footprint and central differences)
BUILD_CACHE_MB = 16  # the pyramid build's own tile cache (a root row's edge tiles; each tile read once)


class StreamedPyramid:
    """Per-node (min, max, geometric error) of a streamed heightmap's quadtree: ``stats_at(level, x, y)``.

    Args:
        hm: the heightmap.
        roots, root_cells, depth, tess: the quadtree's layout (:func:`terrainwarp.lod.quadtree.layout`).
        exact: build the exact pyramid root by root (default: when the source cannot bound its overviews).
        progress: called with the number of roots done, while building an exact pyramid.
        map: ``map(fn, items, shared)`` to build the roots elsewhere (``terrainwarp.experiments.runner.Runner.map``:
            the sweeps' Dask workers, each reading its own tiles); None: in this process.
    """

    def __init__(self, hm: StreamedHeightmap, roots: tuple[int, int], root_cells: float, depth: int, tess: int,
                 *, exact: bool | None = None, device: str = "cpu", progress: Callable[[int], None] | None = None,
                 map: Callable | None = None):
        self.hm, self.roots, self.root_cells, self.depth, self.tess = hm, roots, float(root_cells), depth, tess
        self.device, self.map = device, map
        self.exact = (not math.isfinite(hm.source.detail_bound(2))) if exact is None else bool(exact)
        self.levels: list[tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None
        self._blocks: OrderedDict[tuple[int, int, int], np.ndarray] = OrderedDict()
        self._lock = threading.Lock()
        self.counters = {"blocks_built": 0, "block_hits": 0, "cache": "none"}
        if self.exact:
            self.levels = self._exact(progress)

    # -- the provider ------------------------------------------------------------------------------
    def stats_at(self, level: int, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(min, max, error): the exact pyramid's, or on demand the tightest bounds measured so far for each
        node (min - b, max + b, error + b at the finest step it was measured at; the coarsest step's for a
        node not measured yet)."""
        x = np.asarray(x, np.int64)
        y = np.asarray(y, np.int64)
        if self.levels is not None:
            mn, mx, er = self.levels[level]
            return (np.asarray(mn[y, x], np.float32), np.asarray(mx[y, x], np.float32),
                    np.asarray(er[y, x], np.float32))
        out = np.zeros((3, len(x)), np.float32)
        todo = np.arange(len(x))
        steps = self.steps(level)
        for step in reversed(steps):
            have = self._have(level, x[todo], y[todo], step) if step != steps[0] else np.ones(len(todo), bool)
            if have.any():
                mn, mx, er, pad = self.measured(level, x[todo[have]], y[todo[have]], step)
                out[:, todo[have]] = (mn - pad, mx + pad, er + pad)
                todo = todo[~have]
        return out[0], out[1], out[2]

    def steps(self, level: int) -> list[int]:
        """The overview steps a level's nodes are measured at, coarse to fine: the node step (half the vertex
        spacing), then a quarter of it, down to 1/FINEST of the spacing (a node never reads more than
        (FINEST T + 1)^2 samples, whatever its size). An exact pyramid: [1]."""
        if self.levels is not None:
            return [1]
        spacing = self.root_cells / 2.0**level / self.tess
        finest = 1 << max(0, int(math.floor(math.log2(max(spacing / FINEST, 1.0)) + 1e-9)))
        s, out = self.node_step(level), []
        while s > finest:
            out.append(s)
            s //= 4
        return out + [max(s, finest)]

    def measured(self, level: int, x: np.ndarray, y: np.ndarray,
                 step: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.float32]:
        """(min, max, error) of nodes (level, x, y) measured at overview ``step`` (bounds from below of the
        exact ones; exact at step 1), and b, the source's bound on what the step misses."""
        x = np.asarray(x, np.int64)
        y = np.asarray(y, np.int64)
        bound = np.float32(self.hm.source.detail_bound(step))
        if not len(x):
            return np.zeros(0, np.float32), np.zeros(0, np.float32), np.zeros(0, np.float32), bound
        bid = (y // BLOCK) * ((self.roots[0] << level) // BLOCK + 1) + x // BLOCK
        _, first, inv = np.unique(bid, return_index=True, return_inverse=True)
        blocks = np.stack([self._block(level, step, int(y[i] // BLOCK), int(x[i] // BLOCK)) for i in first])
        out = blocks[inv.reshape(-1), :, y % BLOCK, x % BLOCK]  # (n, 3): one gather for every node
        return out[:, 0].copy(), out[:, 1].copy(), out[:, 2].copy(), bound

    def _have(self, level: int, x: np.ndarray, y: np.ndarray, step: int) -> np.ndarray:
        """True for nodes whose block at ``step`` was measured already (nothing is measured here)."""
        bx, by = x // BLOCK, y // BLOCK
        bid = by * ((self.roots[0] << level) // BLOCK + 1) + bx
        ub, first, inv = np.unique(bid, return_index=True, return_inverse=True)
        with self._lock:
            have = np.array([(level, step, int(by[i]), int(bx[i])) in self._blocks for i in first], bool)
        return have[inv.reshape(-1)] if len(ub) else np.zeros(0, bool)

    def _block(self, level: int, step: int, by: int, bx: int) -> np.ndarray:
        key = (level, step, by, bx)
        with self._lock:
            blk = self._blocks.get(key)
            if blk is not None:
                self._blocks.move_to_end(key)
                self.counters["block_hits"] += 1
                return blk
        blk = self._make_block(level, step, by, bx)
        with self._lock:
            self._blocks[key] = blk
            self.counters["blocks_built"] += 1
            while len(self._blocks) > MAX_BLOCKS:
                self._blocks.popitem(last=False)
        return blk

    def node_step(self, level: int) -> int:
        """The coarsest overview step a level's nodes are measured at: a power of two, at most half their
        vertex spacing (a node is seen through at least (2T + 1)^2 samples); 1 at the finest levels."""
        spacing = self.root_cells / 2.0**level / self.tess
        return 1 << max(0, int(math.floor(math.log2(max(spacing / 2.0, 1.0)) + 1e-9)))

    def _make_block(self, level: int, s: int, by: int, bx: int) -> np.ndarray:
        """Measured stats of nodes [by*B, by*B + B) x [bx*B, bx*B + B) of ``level`` at overview step ``s``."""
        side = self.root_cells / 2.0**level / s  # a node's side in overview samples
        lr, lc = self.hm.source.level_shape(s)
        r0, c0 = int(round(by * BLOCK * side)), int(round(bx * BLOCK * side))
        blk = np.zeros((3, BLOCK, BLOCK), np.float32)
        if r0 > lr - 1 or c0 > lc - 1:
            return blk  # every node of the block lies outside the grid (never drawn)
        rows = min(int(math.ceil(BLOCK * side)) + 1, lr - r0)
        cols = min(int(math.ceil(BLOCK * side)) + 1, lc - c0)
        win = self.hm.window(s, r0, c0, rows, cols)
        (mn, mx, er), = node_stats(win, (BLOCK, BLOCK), side, 0, self.tess, device=self.device)
        blk[0], blk[1], blk[2] = mn, mx, er
        return blk

    # -- the exact pyramid, root by root -------------------------------------------------------------
    def _exact(self, progress: Callable[[int], None] | None) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        src = self.hm.source
        if not isinstance(src, GeoTiffSource):
            return self._build(progress, {})[0]
        cache = src.cache()
        names = [self._stats_name(lv) for lv in range(self.depth + 1)]
        steps = self._overview_steps()
        wanted = names + [_overview_name(st) for st in steps]
        if not cache.check(wanted):
            self.counters["cache"] = "reused"
            return self._load(cache, names, steps)
        levels = None
        try:
            with cache.building() as b:  # one builder; the others wait here, then find the files built
                todo = b.todo(wanted)
                if todo:
                    writers = {st: b.tiled(_overview_name(st), src.level_shape(st), TILE) for st in steps
                               if _overview_name(st) in todo}
                    levels, heights = self._build(progress, writers)
                    for name, arrs in zip(names, levels, strict=True):
                        if name in todo:
                            with open(b.path(name), "wb") as f:
                                np.save(f, np.stack(arrs))
                    if heights is not None:  # the file's height range, from the same pass
                        b.set_value("height_range", list(heights))
                    self.counters["cache"] = "built" if set(todo) == set(wanted) else "repaired"
                else:
                    self.counters["cache"] = "reused"
        except OSError as e:
            bad = cache.check(wanted)
            name = next(iter(bad), wanted[0])
            raise CacheError(f"{cache.path / name}: {bad.get(name, 'not built')}, and the pyramid cache cannot be "
                             f"(re)built there: {e.strerror or e}") from None
        got = self._load(cache, names, steps)
        return got if levels is None else levels

    def _load(self, cache: CacheFolder, names: list[str], steps: list[int]) -> list:
        """The layout's pyramid memory-mapped from the checked files, and the overviews handed to the source
        (:class:`terrainwarp.io.cache.TiledArray`: read tile by tile, each tile checked as read)."""
        try:
            levels = [tuple(np.load(cache.path / n, mmap_mode="r")) for n in names]
            body = cache.manifest()
            for st in steps:
                self.hm.source.levels[st] = cache.tiled(_overview_name(st), body)
        except (OSError, ValueError) as e:  # checked just now: changed on disk since (by something else)
            raise CacheError(f"{cache.path}: a pyramid cache file changed on disk while it was opened: {e}") from None
        return levels

    def _build(self, progress: Callable[[int], None] | None, writers: dict[int, TiledWriter]
               ) -> tuple[list[tuple[np.ndarray, np.ndarray, np.ndarray]], tuple[float, float] | None]:
        """Every root's window through the in-memory kernel (:func:`root_pyramid`), here or on the workers of
        ``map``, a root row at a time, then placed; each root's values are the same wherever it ran. The
        point-sampled overviews of ``writers`` (step -> :class:`terrainwarp.io.cache.TiledWriter`) are written in
        the same pass, a row of tiles as soon as its rows are in (memory: a root row's strip and a row of tiles
        per step). Returns the node arrays and the finite heights' (min, max) (None: no finite height)."""
        nx, nz = self.roots
        s0 = self.root_cells
        whole = s0 != int(s0)  # fractional roots: node origins are not integer shifts; one window, the grid
        levels = [tuple(np.zeros((nz << lv, nx << lv), np.float32) for _ in range(3)) for lv in range(self.depth + 1)]
        rows = [[(0, 0, nz, nx)]] if whole else [[(y, x, 1, 1) for x in range(nx)] for y in range(nz)]
        spec = (self.hm.source, s0, self.depth, self.tess, tuple(writers))
        bands = {st: _TileRows(w) for st, w in writers.items()}
        lo, hi = np.inf, -np.inf
        # its own tile cache, of about a row of roots' tiles (roots share the tiles along their edges)
        tiles = TileCache(self.hm.source, BUILD_CACHE_MB)
        for ranges in rows:
            if self.map is not None:
                parts = self.map(root_pyramid, ranges, spec)
                bad = [p for p in parts if isinstance(p, Exception)]
                if bad:
                    raise ValueError(f"heightmap: a root's pyramid failed on a worker: {bad[0]}")
            else:  # one root at a time: each root's window and overviews dropped once placed
                parts = (root_pyramid(spec, r, tiles=tiles) for r in ranges)
            strips = {st: None for st in writers}
            for (y, x, _, _), part in zip(ranges, parts, strict=True):
                if part is not None:
                    stats, subs, (plo, phi) = part
                    lo, hi = min(lo, plo), max(hi, phi)
                    for lv, arrs in enumerate(stats):
                        a, b = y << lv, x << lv
                        for dst, src in zip(levels[lv], arrs, strict=True):
                            dst[a:a + src.shape[0], b:b + src.shape[1]] = src
                    for st, sub in subs.items():
                        if strips[st] is None:
                            strips[st] = np.full((sub.shape[0], writers[st].shape[1]), np.nan, np.float32)
                        c0 = int(x * s0) // st
                        strips[st][:, c0:c0 + sub.shape[1]] = sub
                if progress is not None:
                    progress(1)
            for st, strip in strips.items():
                if strip is not None:
                    bands[st].add(int(ranges[0][0] * s0) // st, strip)
            del parts, strips
        return levels, (None if not np.isfinite(lo) else (float(lo), float(hi)))

    def _overview_steps(self) -> list[int]:
        """The point-sampled overviews a file's cache holds: steps 2, 4, ... dividing S_0, down to 2 samples a
        side (none with fractional roots)."""
        if self.root_cells != int(self.root_cells):
            return []
        out, step = [], 2
        while int(self.root_cells) % step == 0 and min(self.hm.source.level_shape(step)) >= 2:
            out.append(step)
            step *= 2
        return out

    def _stats_name(self, lv: int) -> str:
        nx, nz = self.roots
        return f"stats_r{nx}x{nz}_t{self.tess}_d{self.depth}_L{lv}.npy"


def _overview_name(step: int) -> str:
    return f"overview_{step}.npy"


def root_pyramid(spec: tuple, item: tuple[int, int, int, int], *, tiles: TileCache | None = None
                 ) -> tuple[list, dict[int, np.ndarray], tuple[float, float]] | None:
    """The pyramid of roots ``item`` = (y, x, rows of roots, columns of roots) from its window of samples, its
    point-sampled overviews at the steps in ``spec`` (with the grid's clamped last row and column where the roots
    hold them) and its finite heights' (min, max) (+-inf: none), or None
    when the roots lie outside the grid. A root's nodes read only samples inside the root's closed extent, and
    with an integer S_0 the window's coordinates are the grid's shifted by an integer: every value is bit for
    bit the whole grid's. Runs anywhere (a Dask worker reads its own tiles)."""
    source, s0, depth, tess, steps = spec
    y, x, ny_, nx_ = item
    hh, ww = source.shape
    r0, c0 = int(y * s0), int(x * s0)
    if r0 > hh - 1 or c0 > ww - 1:
        return None
    rows = min(int(math.ceil(ny_ * s0)) + 1, hh - r0)
    cols = min(int(math.ceil(nx_ * s0)) + 1, ww - c0)
    win = (tiles if tiles is not None else TileCache(source, 64)).window(1, r0, c0, rows, cols)
    stats = node_stats(win, (nx_, ny_), s0, depth, tess)
    last_r, last_c = r0 + rows == hh, c0 + cols == ww  # the window holds the grid's last row / column
    subs = {st: np.ascontiguousarray(win[np.ix_(_overview_rows(rows, st, last_r), _overview_rows(cols, st, last_c))])
            for st in steps if r0 % st == 0 and c0 % st == 0}
    finite = win[np.isfinite(win)]
    return stats, subs, ((float(finite.min()), float(finite.max())) if finite.size else (np.inf, -np.inf))


def _overview_rows(n: int, step: int, last: bool) -> np.ndarray:
    """The rows (columns) of a window of ``n`` starting on a multiple of ``step`` that its step-``step`` overview
    samples: ``0, step, ...``, and the window's last one when it is the grid's last and not among them (the
    overview's clamped edge: :meth:`terrainwarp.io.tiles.TileSource.read`)."""
    idx = np.arange(0, n, step)
    return np.append(idx, n - 1) if last and (n - 1) % step else idx


class _TileRows:
    """An overview's rows arriving in order, a strip at a time (a strip's first row may repeat the last one
    in); each row of tiles is written (:class:`terrainwarp.io.cache.TiledWriter`) as soon as its ``tile + 1``
    rows are in, and the strips below the next row of tiles are dropped."""

    def __init__(self, writer: TiledWriter):
        self.w, self.t = writer, writer.tile
        self.strips: list[tuple[int, np.ndarray]] = []  # (first overview row, rows), in order
        self.next = 0  # the next row of tiles to write

    def add(self, r0: int, strip: np.ndarray) -> None:
        self.strips.append((r0, strip))
        last = r0 + len(strip) - 1
        rows, t = self.w.shape[0], self.t
        while self.next < self.w.grid[0] and (last >= self.next * t + t or last == rows - 1):
            a, b = self.next * t, min(self.next * t + t, rows - 1) + 1
            band = np.empty((b - a, self.w.shape[1]), np.float32)
            for s0, s in self.strips:  # later strips overwrite a shared row with the same values
                lo, hi = max(a, s0), min(b, s0 + len(s))
                if lo < hi:
                    band[lo - a:hi - a] = s[lo - s0:hi - s0]
            for tj in range(self.w.grid[1]):
                self.w.write(self.next, tj, band[:, tj * t:tj * t + t + 1])
            self.next += 1
            self.strips = [(s0, s) for s0, s in self.strips if s0 + len(s) > self.next * t]


def overview_windows(hm: StreamedHeightmap, origin_cells: np.ndarray, size_cells: np.ndarray,
                     factor: np.ndarray) -> list[tuple[int, int, int, int, int]]:
    """The windows a frame's patches read: (shift, r0, c0, rows, cols) in step-2^shift overview samples,
    finest first.

    A patch reads the overview of the largest power-of-two step not above its vertex spacing (side /
    largest tessellation factor); each step's window is the bounding box of
    its patches, ``WINDOW_MARGIN`` samples wider, clipped to the grid."""
    if len(size_cells) == 0:
        return []
    spacing = np.asarray(size_cells, np.float64) / np.maximum(np.asarray(factor, np.float64), 1.0)
    shift = np.floor(np.log2(np.maximum(spacing, 1.0)) + 1e-9).astype(np.int64)
    lo = np.asarray(origin_cells, np.float64)
    hi = lo + np.asarray(size_cells, np.float64)[:, None]
    out = []
    for sh in np.unique(shift):
        m = shift == sh
        s = float(1 << int(sh))
        lr, lc = hm.source.level_shape(1 << int(sh))
        c0 = int(max(0, math.floor(lo[m, 0].min() / s) - WINDOW_MARGIN))
        r0 = int(max(0, math.floor(lo[m, 1].min() / s) - WINDOW_MARGIN))
        c1 = int(min(lc - 1, math.ceil(hi[m, 0].max() / s) + WINDOW_MARGIN))
        r1 = int(min(lr - 1, math.ceil(hi[m, 1].max() / s) + WINDOW_MARGIN))
        if c0 <= c1 and r0 <= r1:
            out.append((int(sh), r0, c0, r1 - r0 + 1, c1 - c0 + 1))
    return out

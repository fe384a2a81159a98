"""Heights read a tile at a time: tiled sources, point-sampled overviews and an LRU tile cache.

A streamed heightmap (:class:`terrainwarp.heightmap.StreamedHeightmap`) never holds its grid: it asks its
:class:`TileSource` for square tiles of ``TILE + 1`` samples a side (neighbours share a row or column, so
a window that ends on a multiple of ``TILE`` needs no further tile), at a ``step`` of 1 (full resolution)
or a power of two (an overview), and keeps the tiles it read in a :class:`TileCache` with a memory cap.

Overviews are point-sampled: sample ``(i, j)`` of the step-``s`` overview is sample ``(min(i s, H - 1),
min(j s, W - 1))`` of the (H, W) grid, bit for bit: the grid's points ``0, s, 2 s, ...``, then, where ``H - 1``
(``W - 1``) is not a multiple of ``s``, the grid's last row (column) as the overview's last. So every overview
holds the grid's edge, where the tessellator clamps a patch that reaches past the grid: a vertex there reads
the grid's last sample, as in memory (:mod:`terrainwarp.kernels.stack` reads the overview's last, shorter cell
by its true width). A vertex that falls on a grid point reads the same height from every overview that holds
the point (so a frame drawn from overviews keeps the heightmap's values where it has them; an averaging
overview would move every height). GDAL's own overviews of a GeoTIFF are area-sampled (a cell of a 2x overview
is centred between grid points), so a :class:`GeoTiffSource` takes its overviews from the pyramid cache built
beside the file (:mod:`terrainwarp.lod.streaming`), which writes them in the same pass as the min/max and error
pyramids.

Sources:

* :class:`ArraySource`: an in-memory array (tests, and a heightmap that fits).
* :class:`FbmSource`: the fBm of :meth:`terrainwarp.Heightmap.fbm`, generated window by window by the
  same kernel (``kernels.noise.fbm`` with ``step``): any window, at any step, equals that part of
  the whole grid bit for bit, and :meth:`FbmSource.detail_bound` bounds what an overview leaves out.
* :class:`GeoTiffSource`: a GeoTIFF (or any GDAL raster) through rasterio windows; heights, no-data,
  spacing, CRS and orientation decoded exactly as :func:`terrainwarp.io.geotiff.read_geotiff` does.
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import os
import threading
from collections import OrderedDict
from pathlib import Path
from typing import Any

import numpy as np

from ..kernels import noise
from ..kernels.checks import check_bool, check_int, check_number, is_number
from . import geotiff
from .cache import CacheFolder, CorruptTile, TiledArray, content_digest

__all__ = ["TILE", "DEFAULT_CACHE_MB", "TileSource", "ArraySource", "FbmSource", "GeoTiffSource", "TileCache",
           "cache_mb_from_env", "cache_dir_for"]

TILE = 256  # samples per tile side, at every step
DEFAULT_CACHE_MB = 512.0  # the tile cache's cap when neither the argument nor TERRAINWARP_TILE_CACHE_MB says
PERLIN_SLOPE = 2.5  # bound on |d noise / d input| per axis of the 2-D gradient noise (measured 2.00)
F32_MAX = float(np.finfo(np.float32).max)
PERLIN_CURVATURE = 12.0  # bound on |d2 noise / d input2| per axis (measured 8.15; quintic fade: smooth)


def cache_mb_from_env(cache_mb: float | None) -> float:
    """The tile cache's cap in MiB: ``cache_mb`` if given, else ``TERRAINWARP_TILE_CACHE_MB``, else 512."""
    if cache_mb is None:
        env = os.environ.get("TERRAINWARP_TILE_CACHE_MB")
        if env is None or not env.strip():
            return DEFAULT_CACHE_MB
        try:
            cache_mb = float(env)
        except ValueError:
            raise ValueError(f"TERRAINWARP_TILE_CACHE_MB: expected a number of MiB, got {env!r}") from None
        name = "TERRAINWARP_TILE_CACHE_MB"
    else:
        name = "cache_mb"
    if not is_number(cache_mb) or not math.isfinite(cache_mb) or cache_mb <= 0:
        raise ValueError(f"{name}: expected a positive number of MiB, got {cache_mb!r}")
    return float(cache_mb)


def cache_dir_for(path: Path) -> Path:
    """Where a file's caches live: ``<file>.twcache`` beside it when its folder is writable, else under
    ``~/.cache/terrainwarp/tiles``."""
    beside = path.with_name(path.name + ".twcache")
    if os.access(path.parent, os.W_OK):
        return beside
    key = hashlib.sha256(str(path.resolve()).encode()).hexdigest()[:16]
    return Path.home() / ".cache" / "terrainwarp" / "tiles" / f"{path.name}-{key}"


# ------------------------------------------------------------------------------------------------
# sources
# ------------------------------------------------------------------------------------------------
class TileSource:
    """A grid of heights read by windows. Subclasses set the attributes and implement :meth:`lattice`;
    :meth:`read` assembles an overview's window from it.

    Attributes:
        shape: (rows, cols) of the full-resolution grid.
        dx, dz: spacing in metres; origin: world (x, z) of sample (0, 0); name, meta: as a Heightmap's.
        path: the file read, or None.
    """

    shape: tuple[int, int]
    dx: float
    dz: float
    origin: tuple[float, float] = (0.0, 0.0)
    name: str = "tiles"
    meta: dict[str, Any]
    path: Path | None = None

    def level_shape(self, step: int) -> tuple[int, int]:
        """(rows, cols) of the step-``step`` overview: samples ``0, step, 2 step, ...`` inside the grid, and the
        grid's last row (column) after them where it is not one of those."""
        return (_level_len(self.shape[0], step), _level_len(self.shape[1], step))

    def read(self, step: int, r0: int, c0: int, rows: int, cols: int) -> np.ndarray:
        """(rows, cols) float32 heights of the step-``step`` overview from its sample (r0, c0) (inside it),
        NaN at no-data: sample (i, j) is the grid's (min(i step, H - 1), min(j step, W - 1)), read through
        :meth:`lattice` (a window holding the clamped last row or column is up to four lattice reads).
        Uncached: :class:`TileCache` calls this once per tile."""
        s = int(step)
        kr, kc = _on_lattice(self.shape[0], s, r0, rows), _on_lattice(self.shape[1], s, c0, cols)
        if kr == rows and kc == cols:
            return self.lattice(r0 * s, c0 * s, rows, cols, s)
        out = np.empty((rows, cols), np.float32)
        for a, b, n, g0 in ((0, kr, kr, r0 * s), (kr, rows, rows - kr, self.shape[0] - 1)):
            for c, d, m, h0 in ((0, kc, kc, c0 * s), (kc, cols, cols - kc, self.shape[1] - 1)):
                if n and m:
                    out[a:b, c:d] = self.lattice(g0, h0, n, m, s)
        return out

    def lattice(self, row0: int, col0: int, rows: int, cols: int, step: int) -> np.ndarray:
        """(rows, cols) float32 grid samples (row0 + i step, col0 + j step), all inside the grid, NaN at
        no-data (the sources' one read)."""
        raise NotImplementedError

    def detail_bound(self, step: int) -> float:
        """A bound on ``|height - bilinear interpolation of the step-step overview|`` anywhere (metres): 0 at
        step 1, inf where nothing bounds it (a file: its pyramids are exact instead)."""
        return 0.0 if step == 1 else math.inf

    def fingerprint(self) -> str:
        """Changes whenever the heights may have changed (caches built from the source key on it)."""
        raise NotImplementedError

    def height_range(self, tiles: TileCache) -> tuple[float, float]:
        """(min, max) of the finite heights: every tile read once (a file keeps the answer in its cache)."""
        return _scan_range(self, tiles)

    def where(self) -> str:
        return str(self.path) if self.path is not None else self.name


class ArraySource(TileSource):
    """An in-memory (H, W) float32 array read by windows (as a file would be)."""

    def __init__(self, heights: np.ndarray, dx: float = 1.0, dz: float = 1.0, origin=(0.0, 0.0),
                 name: str = "array", meta: dict | None = None):
        h = np.asarray(heights)
        if h.dtype != np.float32 or h.ndim != 2 or min(h.shape) < 1:
            raise TypeError(f"heights: expected a 2-D float32 array, got {h.dtype} {h.shape}")
        self.h = h
        self.shape = (int(h.shape[0]), int(h.shape[1]))
        self.dx, self.dz, self.origin, self.name = float(dx), float(dz), tuple(origin), name
        self.meta = dict(meta or {})

    def lattice(self, row0: int, col0: int, rows: int, cols: int, step: int) -> np.ndarray:
        s = int(step)
        return np.ascontiguousarray(self.h[row0:row0 + (rows - 1) * s + 1:s, col0:col0 + (cols - 1) * s + 1:s])

    def fingerprint(self) -> str:
        return "array:" + hashlib.sha256(np.ascontiguousarray(self.h).tobytes()).hexdigest()[:16]

    def height_range(self, tiles: TileCache) -> tuple[float, float]:
        return (float(np.nanmin(self.h)), float(np.nanmax(self.h)))


class FbmSource(TileSource):
    """The fBm terrain of :meth:`terrainwarp.Heightmap.fbm` (same parameters, same heights), never held:
    windows are generated on demand by the noise kernel. Sizes beyond memory are fine (2^20 + 1 squared
    is 1.1 T samples); sample indices must stay below 2^24 for the float32 noise coordinate."""

    def __init__(self, rows: int, cols: int | None = None, *, seed: int = 0, max_height: float = 1000.0,
                 dx: float = 10.0, dz: float | None = None, feature_size: float = 256.0, octaves: int = 8,
                 gain: float = 0.5, lacunarity: float = 2.0, ridged: bool = False):
        cols = rows if cols is None else cols
        for nm, v in (("rows", rows), ("cols", cols), ("octaves", octaves)):
            check_int(nm, v, 1)
        check_int("octaves", octaves, 1, noise.MAX_OCTAVES)  # more is a hang, not a terrain
        if max(rows, cols) > 2**24:
            raise ValueError(f"rows, cols: at most 2^24 samples per side (float32 noise coordinates), got "
                             f"{rows} x {cols}")
        check_int("seed", seed)
        check_bool("ridged", ridged)
        for nm, v in (("max_height", max_height), ("dx", dx), ("feature_size", feature_size),
                      ("gain", gain), ("lacunarity", lacunarity)) + ((("dz", dz),) if dz is not None else ()):
            check_number(nm, v, 0.0, lo_open=True)
        _check_octave_series(int(octaves), float(gain), float(lacunarity), float(feature_size))
        self.shape = (int(rows), int(cols))
        self.dx, self.dz = float(dx), float(dz if dz is not None else dx)
        self.max_height, self.feature_size = float(max_height), float(feature_size)
        self.seed, self.octaves, self.gain, self.lacunarity, self.ridged = (
            int(seed), int(octaves), float(gain), float(lacunarity), bool(ridged))
        self.name = f"fbm{rows}x{cols}s{seed}"
        self.meta = {"source": "fbm", "seed": self.seed, "max_height": self.max_height,
                     "feature_size": self.feature_size, "octaves": self.octaves, "gain": gain,
                     "lacunarity": lacunarity, "ridged": ridged, "streamed": True}

    def lattice(self, row0: int, col0: int, rows: int, cols: int, step: int) -> np.ndarray:
        a = noise.fbm(int(rows), int(cols), seed=self.seed, base_frequency=1.0 / self.feature_size,
                      octaves=self.octaves, lacunarity=self.lacunarity, gain=self.gain, ridged=self.ridged,
                      row0=int(row0), col0=int(col0), step=int(step))
        return ((a + np.float32(1.0)) * np.float32(0.5 * self.max_height)).astype(np.float32)  # as Heightmap.fbm

    def detail_bound(self, step: int) -> float:
        """Octave by octave, the smallest of three bounds on bilinear interpolation over cells of side r =
        ``step`` of an octave of frequency f (per sample): its curvature, ``(r^2 / 8)(|f_xx| + |f_zz|)`` <=
        C2 (f r)^2 / 4; its slope, C1 f r; and its whole range. Ridged noise has kinks: slope and range
        only. The constants bound the measured extremes of the noise with a 25-50% margin."""
        if step <= 1:
            return 0.0
        amp, norm, total = 1.0, 0.0, 0.0
        freq = 1.0 / self.feature_size
        for _ in range(self.octaves):
            fr = freq * step
            b = min(PERLIN_SLOPE * fr * (2.0 if self.ridged else 1.0), 2.0 * 0.70710678)
            if not self.ridged:
                b = min(b, PERLIN_CURVATURE * fr * fr / 4.0)
            total += amp * b
            norm += amp
            amp *= self.gain
            freq *= self.lacunarity
        return float(total / (0.70710678 * norm) * 0.5 * self.max_height * 1.0001)  # 1e-4: float32 rounding

    def height_range(self, tiles: TileCache) -> tuple[float, float]:
        """Of the overview at most 1024 samples a side, widened by :meth:`detail_bound` (never scanned: the
        grid may hold 10^12 samples)."""
        step = 1
        while max(self.level_shape(step)) > 1024:
            step *= 2
        ov = tiles.window(step, 0, 0, *self.level_shape(step))
        pad = self.detail_bound(step)
        return (max(0.0, float(ov.min()) - pad), min(self.max_height, float(ov.max()) + pad))

    def fingerprint(self) -> str:
        return "fbm:" + repr((self.shape, self.seed, self.max_height, self.feature_size, self.octaves,
                              self.gain, self.lacunarity, self.ridged))


def _check_octave_series(octaves: int, gain: float, lacunarity: float, feature_size: float) -> None:
    """The noise kernel sums ``octaves`` octaves in float32: amplitudes ``gain**k`` (and their sum) and noise
    coordinates ``index * lacunarity**k / feature_size`` (index < 2^24) must stay finite there, or the heights
    come out NaN. Raises ValueError naming ``gain`` or ``lacunarity``."""
    top = math.log(F32_MAX)
    k = octaves - 1
    if k * max(math.log(gain), 0.0) + math.log(octaves) >= top:
        raise ValueError(f"gain: {gain!r} over {octaves} octaves overflows the kernel's float32 amplitudes "
                         f"(gain**{k} x {octaves} must stay below 3.4e38)")
    if k * max(math.log(lacunarity), 0.0) + math.log(2.0**24 / feature_size) >= top:
        raise ValueError(f"lacunarity: {lacunarity!r} over {octaves} octaves overflows the kernel's float32 noise "
                         f"coordinates (2^24 x lacunarity**{k} / feature_size must stay below 3.4e38)")


class GeoTiffSource(TileSource):
    """A GeoTIFF (or any GDAL raster) read through rasterio windows: only the file's blocks under a window
    are decoded. Heights, no-data (NaN), spacing, CRS and the north-up orientation are those of
    :func:`terrainwarp.io.geotiff.read_geotiff` on the whole file. Overviews (step > 1) come from the
    pyramid cache beside the file when one is attached (``levels``), else from full-resolution reads."""

    def __init__(self, path: str | os.PathLike, *, band: int = 1, dx: float | None = None,
                 dz: float | None = None):
        self.path = Path(path)
        self.header = geotiff.read_header(self.path, band=band, dx=dx, dz=dz)
        self.band = self.header.band
        self.shape = self.header.shape
        self.dx, self.dz = self.header.dx, self.header.dz
        self.name = self.path.stem
        self.meta = dict(self.header.meta, streamed=True)
        self.levels: dict[int, TiledArray] = {}  # step -> the cache's point-sampled overview, checked tile by tile
        self._local = threading.local()

    def read(self, step: int, r0: int, c0: int, rows: int, cols: int) -> np.ndarray:
        lv = self.levels.get(step) if step > 1 else None
        if lv is not None:
            try:
                return lv.window(r0, c0, rows, cols)
            except CorruptTile:  # read from the file from now on (the overview is rebuilt on the next open)
                self.levels.pop(step, None)
        return super().read(step, r0, c0, rows, cols)

    def lattice(self, row0: int, col0: int, rows: int, cols: int, step: int) -> np.ndarray:
        s = int(step)
        full = geotiff.read_oriented(self.header, self._dataset(), row0, col0, (rows - 1) * s + 1, (cols - 1) * s + 1)
        return np.ascontiguousarray(full[::s, ::s])

    def __getstate__(self) -> dict:  # to a Dask worker: the path and header, not the open datasets
        state = dict(self.__dict__)
        state.pop("_local", None)
        state["levels"] = {}
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._local = threading.local()

    def _dataset(self):
        """One open dataset per thread (GDAL handles are not shared across threads)."""
        ds = getattr(self._local, "ds", None)
        if ds is None:
            ds = self._local.ds = geotiff.open_raster(self.path)
        return ds

    def fingerprint(self) -> str:
        """Path, band and the SHA-256 of the file's whole content (:func:`terrainwarp.io.cache.content_digest`:
        worked out once, kept beside the cache with the file's size, times and inode, and again whenever one of
        them changes), so any edit of the file is seen."""
        digest = content_digest(self.path, cache_dir_for(self.path))
        return f"file:{self.path.resolve()}:band{self.band}:sha256:{digest}"

    def cache(self) -> CacheFolder:
        """The file's cache folder (:func:`cache_dir_for`), keyed on :meth:`fingerprint`: its pyramids and
        overviews (:mod:`terrainwarp.lod.streaming`) and its height range."""
        return CacheFolder(cache_dir_for(self.path), self.fingerprint())

    def height_range(self, tiles: TileCache) -> tuple[float, float]:
        """Kept in the file's cache folder (the manifest's ``height_range``): worked out by the pyramid's build,
        or, asked first, by a scan of every tile (through a cache of its own: the frames' tiles stay theirs)."""
        cache = self.cache()
        got = cache.value("height_range")
        if isinstance(got, list) and len(got) == 2 and all(isinstance(v, float) for v in got):
            return (got[0], got[1])
        lo, hi = _scan_range(self, TileCache(self, 16))  # its own small cache: a scan reads every tile once
        with contextlib.suppress(OSError):  # a read-only place: scanned again next time
            with cache.building() as b:
                b.set_value("height_range", [lo, hi])
        return lo, hi


def _level_len(n: int, step: int) -> int:
    """Samples along an axis of ``n`` in the step-``step`` overview: ``0, step, ...`` up to ``n - 1``, and
    ``n - 1`` itself when it is not a multiple of ``step``."""
    return -(-(int(n) - 1) // int(step)) + 1


def _on_lattice(n: int, step: int, i0: int, count: int) -> int:
    """How many of overview samples ``i0 .. i0 + count - 1`` (an axis of ``n``) lie on the lattice ``i step``
    (the rest, at most the one last sample, is the grid's clamped last sample ``n - 1``)."""
    return max(0, min(int(count), (int(n) - 1) // int(step) - int(i0) + 1))


def _scan_range(src: TileSource, tiles: TileCache) -> tuple[float, float]:
    lo, hi = math.inf, -math.inf
    lr, lc = src.level_shape(1)
    for ti in range(0, (lr - 1) // TILE + 1):
        for tj in range(0, (lc - 1) // TILE + 1):
            t = tiles.tile(1, ti, tj)
            if np.isfinite(t).any():
                lo, hi = min(lo, float(np.nanmin(t))), max(hi, float(np.nanmax(t)))
    if not math.isfinite(lo):
        raise ValueError(f"heights: every sample of {src.where()} is no-data")
    return lo, hi


# ------------------------------------------------------------------------------------------------
# the cache
# ------------------------------------------------------------------------------------------------
class TileCache:
    """Least-recently-used tiles of one source, at most ``cache_mb`` MiB of them.

    Counters (:attr:`counters`): ``tiles_read`` and ``bytes_read`` (from the source), ``hits`` (served from
    the cache), ``evicted``, ``resident_bytes`` and ``peak_bytes``. Thread-safe: concurrent readers of the
    same missing tile may both read it (the counters say so); the cache keeps one."""

    def __init__(self, source: TileSource, cache_mb: float | None = None):
        self.source = source
        self.cap = int(cache_mb_from_env(cache_mb) * 2**20)
        self._tiles: OrderedDict[tuple[int, int, int], np.ndarray] = OrderedDict()
        self._lock = threading.Lock()
        self.counters = {"tiles_read": 0, "bytes_read": 0, "hits": 0, "evicted": 0, "resident_bytes": 0,
                         "peak_bytes": 0}

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            return dict(self.counters)

    def tile(self, step: int, ti: int, tj: int) -> np.ndarray:
        """Tile (ti, tj) of the step-``step`` overview: samples ti * TILE .. ti * TILE + TILE (TILE + 1 of them:
        neighbouring tiles share a row or column; fewer at the grid's far edges)."""
        key = (int(step), int(ti), int(tj))
        with self._lock:
            t = self._tiles.get(key)
            if t is not None:
                self._tiles.move_to_end(key)
                self.counters["hits"] += 1
                return t
        t = self._read(key)
        with self._lock:
            if key not in self._tiles:
                self._tiles[key] = t
                self.counters["resident_bytes"] += t.nbytes
                self.counters["peak_bytes"] = max(self.counters["peak_bytes"], self.counters["resident_bytes"])
            while self.counters["resident_bytes"] > self.cap and len(self._tiles) > 1:
                _, old = self._tiles.popitem(last=False)
                self.counters["resident_bytes"] -= old.nbytes
                self.counters["evicted"] += 1
        return t

    def _read(self, key: tuple[int, int, int]) -> np.ndarray:
        step, ti, tj = key
        lr, lc = self.source.level_shape(step)
        r0, c0 = ti * TILE, tj * TILE
        rows, cols = min(TILE + 1, lr - r0), min(TILE + 1, lc - c0)  # one shared row and column with the next
        hh, ww = self.source.shape
        what = f"tile (step {step}, row {ti}, col {tj}: samples {r0 * step}..{min((r0 + rows - 1) * step, hh - 1)} " \
               f"x {c0 * step}..{min((c0 + cols - 1) * step, ww - 1)}) of {self.source.where()}"
        if rows < 1 or cols < 1:
            raise ValueError(f"{what}: outside the {lr} x {lc} grid")
        try:
            t = self.source.read(step, r0, c0, rows, cols)
        except (OSError, ValueError, RuntimeError) as e:  # a GeoTIFF source's say the file block and GDAL's cause
            msg = str(e).splitlines()[0] if str(e) else type(e).__name__
            msg = msg.removeprefix(f"path: {self.source.where()}: ")  # named once, in `what`
            raise ValueError(f"{what}: {msg}" if "cannot be read" in msg else f"{what}: cannot be read: {msg}") from e
        if t.shape != (rows, cols) or t.dtype != np.float32:
            raise ValueError(f"{what}: the source returned {t.dtype} {t.shape}, expected float32 ({rows}, {cols})")
        if np.isinf(t).any():
            raise ValueError(f"{what}: holds infinite heights")
        t.setflags(write=False)
        with self._lock:
            self.counters["tiles_read"] += 1
            self.counters["bytes_read"] += t.nbytes
        return t

    def window(self, step: int, r0: int, c0: int, rows: int, cols: int, out: np.ndarray | None = None) -> np.ndarray:
        """(rows, cols) float32 of the step-``step`` overview from sample (r0, c0), assembled from tiles
        (the window must lie inside the overview), into ``out`` when given (a writable (rows, cols) float32 array:
        a frame's windows assembled in one buffer)."""
        step = check_int("step", step, 1)  # 1: full resolution; 2, 4, ...: overviews
        lr, lc = self.source.level_shape(step)
        if r0 < 0 or c0 < 0 or rows < 1 or cols < 1 or r0 + rows > lr or c0 + cols > lc:
            raise ValueError(f"window: rows {r0}..{r0 + rows - 1}, cols {c0}..{c0 + cols - 1} outside the step-"
                             f"{step} overview ({lr} x {lc}) of {self.source.where()}")
        if out is None:
            out = np.empty((rows, cols), np.float32)
        elif out.shape != (rows, cols) or out.dtype != np.float32 or not out.flags.writeable:
            raise ValueError(f"out: expected a writable ({rows}, {cols}) float32 array, got {out.dtype} {out.shape}")
        last_r, last_c = r0 + rows - 1, c0 + cols - 1
        # tiles share their last row and column with the next: a window ending on a tile boundary (as
        # power-of-two node windows do) needs no tile past it
        for ti in range(r0 // TILE, max(r0, last_r - 1) // TILE + 1):
            for tj in range(c0 // TILE, max(c0, last_c - 1) // TILE + 1):
                t = self.tile(step, ti, tj)
                a0, b0 = max(r0, ti * TILE), max(c0, tj * TILE)
                a1, b1 = min(last_r + 1, ti * TILE + t.shape[0]), min(last_c + 1, tj * TILE + t.shape[1])
                out[a0 - r0:a1 - r0, b0 - c0:b1 - c0] = t[a0 - ti * TILE:a1 - ti * TILE, b0 - tj * TILE:b1 - tj * TILE]
        return out

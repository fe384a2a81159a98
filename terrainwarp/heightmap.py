"""Heightmaps: float32 heights in metres on a regular grid with spacing (dx, dz).

Sample (i, j) sits at world (x0 + j*dx, h[i, j], z0 + i*dz) (see :mod:`terrainwarp.camera`).
Sources: numpy arrays of any integer or float dtype, image files through OpenImageIO (8/16-bit PNG,
16-bit and float TIFF, float EXR), ``.npy``, the real SRTM DEMs that matplotlib ships, and
procedural fBm noise. The designer controls of mrbsp-lod-visibility.txt section 1 (sea level, height
scale, seabed factor, smoothing that spares mountains) return new heightmaps.
"""

from __future__ import annotations

import math
import os
import tokenize
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from .io import geotiff
from .io.files import atomic_path, write_image
from .io.geodesy import metres_per_degree
from .io.memory import check_heightmap_fits
from .io.native import native_stderr_silenced
from .io.tiles import TILE, ArraySource, FbmSource, GeoTiffSource, TileCache, TileSource
from .kernels import sampling
from .kernels.checks import check_choice, check_int, is_number

# metres_per_degree lives in io.geodesy; re-exported as before
__all__ = ["Heightmap", "StreamedHeightmap", "Held", "metres_per_degree", "DEFAULT_SPACING", "DefaultSpacingWarning"]

#: The sample spacing (metres) taken for a file that carries none (an image, a .npy), with a warning.
DEFAULT_SPACING = 1.0


class DefaultSpacingWarning(UserWarning):
    """A heightmap loaded from a file that carries no sample spacing got :data:`DEFAULT_SPACING`."""

EXAMPLES = ("jacksboro", "topobathy")
HOST_SAMPLES = 64  # Heightmap.sample of at most this many bilinear points runs on the host (the same bits)


def _positive(name: str, v: object) -> float:
    if not is_number(v):
        raise TypeError(f"{name}: expected a positive number of metres, got {v!r}")
    f = float(v)
    if not (math.isfinite(f) and f > 0.0):
        raise ValueError(f"{name}: expected a positive finite number of metres, got {v}")
    return f


def _heights(name: str, a: object, max_height: float | None, allow_nan: bool) -> tuple[np.ndarray, np.dtype]:
    """(float32 heights, the source dtype) of an (H, W) or (H, W, 1) array of any integer or float dtype, by
    :meth:`Heightmap.from_array`'s rules (``max_height``: a normalised image); errors name ``name``."""
    arr = np.asarray(a)
    if arr.dtype == object or arr.dtype.kind not in "iuf":
        raise TypeError(f"{name}: expected an integer or float array, got dtype {arr.dtype}")
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    check_heights(name, arr, allow_nan=allow_nan)  # shape, then values (the scaled ones below)
    h64 = None
    if max_height is not None:
        n = _positive("max_height", max_height)
        with np.errstate(over="ignore", invalid="ignore"):  # an overflow to inf is refused below
            if arr.dtype.kind in "iu":
                h64 = arr.astype(np.float64) / float(np.iinfo(arr.dtype).max) * n
            else:
                h64 = arr.astype(np.float64) * n
        if arr.dtype.kind == "f":
            check_heights(name, h64, allow_nan=allow_nan)  # scaling may overflow to inf
    with np.errstate(over="ignore"):
        h = (h64 if h64 is not None else arr).astype(np.float32)
    if np.isinf(h).any():
        raise ValueError(f"{name}: heights overflow float32 (|h| > 3.4e38)")
    return h, arr.dtype


def check_heights(name: str, h: np.ndarray, *, allow_nan: bool) -> None:
    """The one set of rules for heights, shared by :meth:`Heightmap.from_array` and the constructor: a
    non-empty 2D grid; float heights finite, NaN only as no-data holes (``allow_nan``) and never every
    one of them. Raises ValueError naming ``name``."""
    if h.ndim != 2:
        raise ValueError(f"{name}: expected a 2D array (H, W), got shape {h.shape}")
    if h.size == 0:
        raise ValueError(f"{name}: expected a non-empty array, got shape {h.shape}")
    if not np.issubdtype(h.dtype, np.floating):
        return
    n_inf = int(np.isinf(h).sum())
    if n_inf:
        raise ValueError(f"{name}: expected finite heights, got {n_inf} infinite values")
    nn = int(np.isnan(h).sum())
    if nn and not allow_nan:
        raise ValueError(f"{name}: {nn} NaN heights; pass allow_nan=True to treat NaN as no-data holes")
    if nn == h.size:
        raise ValueError(f"{name}: every height is NaN")


def grid_bounds(origin: tuple[float, float], shape: tuple[int, int], dx: float,
                dz: float) -> tuple[tuple[float, float], tuple[float, float]]:
    """((xmin, zmin), (xmax, zmax)) in world metres of a (rows, cols) grid whose sample (0, 0) is at ``origin``."""
    x0, z0 = origin
    return ((x0, z0), (x0 + (shape[1] - 1) * dx, z0 + (shape[0] - 1) * dz))


@dataclass
class Held:
    """What frames keep with a heightmap between calls, one named slot per kind, each keyed by what it depends on
    (``render`` fills them; a caller who holds its own ``Terrain`` or source needs none of them).

    Attributes:
        schemes: by device, the cache the LOD schemes drawn by name (``LodConfig(policy="cdlod")``) keep their
            prepared pyramids in, shared by every setting of the heightmap.
        streamed_sources: by (the ``LodConfig``'s fields, device), the ``StreamedSource`` that draws a streamed
            heightmap's frames (its pyramids and tile cache persist from frame to frame).
        loaded: a streamed heightmap's whole grid, loaded once for the stages that read every sample (curvature,
            the reference frame and the error).
        terrains: by device, the prepared ``Terrain`` of each LOD layout (roots, tess) drawn lately, least
            recently drawn first (``render`` keeps a few), so a plain render loop prepares once.
        beside_hole: (H, W) bool, the finite samples next to a no-data hole
            (:func:`terrainwarp.measure.sample_error.beside_hole`), worked out on first use.
    """

    schemes: dict[str, dict] = field(default_factory=dict)
    terrains: dict[str, Any] = field(default_factory=dict)
    streamed_sources: dict[tuple, Any] = field(default_factory=dict)
    loaded: Heightmap | None = None
    beside_hole: np.ndarray | None = None

    def clear(self) -> None:
        """Let go of everything held."""
        self.schemes.clear()
        self.terrains.clear()
        self.streamed_sources.clear()
        self.loaded = self.beside_hole = None


@dataclass(frozen=True, eq=False)
class Heightmap:
    """A regular grid of heights.

    Attributes:
        heights: (H, W) float32 metres, read-only. Row i runs along +z, column j along +x.
            NaN marks no-data holes (``from_array`` accepts them only with ``allow_nan=True``); the
            constructor and ``from_array`` check the heights by the same rules (:func:`check_heights`).
        dx, dz: sample spacing along x (columns) and z (rows), metres.
        origin: world (x, z) of sample (0, 0), metres (float64; far-from-origin terrains keep their
            precision because the pipeline subtracts the eye in float64 before casting to float32).
        name: a label for reports.
        meta: free-form provenance (source file, CRS, latitude used for spacing, ...).
    """

    heights: np.ndarray
    dx: float = 1.0
    dz: float = 1.0
    origin: tuple[float, float] = (0.0, 0.0)
    name: str = "heightmap"
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        h = self.heights
        if not isinstance(h, np.ndarray) or h.dtype != np.float32 or h.ndim != 2:
            raise TypeError("heights: use Heightmap.from_array() to build a Heightmap from arbitrary data")
        check_heights("heights", h, allow_nan=True)  # NaN: no-data holes, as from_array(allow_nan=True)
        h = np.ascontiguousarray(h)
        h.setflags(write=False)
        object.__setattr__(self, "heights", h)
        object.__setattr__(self, "dx", _positive("dx", self.dx))
        object.__setattr__(self, "dz", _positive("dz", self.dz))
        o = np.asarray(self.origin, dtype=np.float64).reshape(-1)
        if o.shape != (2,) or not np.all(np.isfinite(o)):
            raise ValueError(f"origin: expected 2 finite numbers (x, z), got {self.origin!r}")
        object.__setattr__(self, "origin", (float(o[0]), float(o[1])))

    # -- constructors ------------------------------------------------------------------------------
    @classmethod
    def from_array(cls, a: object, dx: float = 1.0, dz: float | None = None, *,
                   max_height: float | None = None, origin: tuple[float, float] = (0.0, 0.0),
                   allow_nan: bool = False, name: str = "array", meta: dict | None = None) -> Heightmap:
        """A heightmap from a 2D array of any integer or float dtype.

        Args:
            a: (H, W) array (or (H, W, 1)); int8..uint64, float16..float64.
            dx, dz: spacing in metres (dz defaults to dx).
            max_height: if given, ``a`` is a normalised image: integers are divided by their dtype's
                maximum, floats are taken as [0, 1]; the result is multiplied by ``max_height`` (N in
                deaconu2021, "Terrain generation"). If None, values are metres as they are.
            allow_nan: accept NaN as no-data holes (default: NaN is an error).
        """
        if isinstance(a, Heightmap):
            raise TypeError("a: already a Heightmap")
        h, source_dtype = _heights("a", a, max_height, allow_nan)
        dxf = _positive("dx", dx)
        dzf = _positive("dz", dz if dz is not None else dx)
        m = {"source_dtype": str(source_dtype)}
        if meta:
            m.update(meta)
        return cls(heights=h, dx=dxf, dz=dzf, origin=origin, name=name, meta=m)

    @classmethod
    def load(cls, path: str | os.PathLike, dx: float | None = None, dz: float | None = None, *,
             max_height: float | None = None, channel: int = 0, allow_nan: bool = False,
             **raster_options: Any) -> Heightmap:
        """Load a heightmap from an image file (OpenImageIO), a ``.npy`` file, or a GeoTIFF / GDAL raster.

        8- and 16-bit PNG and TIFF keep their integer values as metres unless ``max_height`` is given
        (then they are normalised by the dtype's maximum and scaled by it); float TIFF and EXR are
        metres. Multi-channel images use ``channel``. Such files carry no spacing: ``dx`` defaults to
        :data:`DEFAULT_SPACING` (1 m), with a :class:`DefaultSpacingWarning` saying so, and ``dz`` to ``dx``.

        A georeferenced TIFF (GeoTIFF) and the other rasters GDAL reads (.vrt, .img, .asc, .hgt, ...; see
        :data:`terrainwarp.io.geotiff.GDAL_EXTS`) go through :func:`terrainwarp.io.geotiff.read_geotiff`: metre
        spacing, heights and orientation come from the georeferencing (``dx``/``dz`` override the spacing),
        band ``channel + 1`` is read, no-data cells become NaN (whatever ``allow_nan`` says), and
        ``raster_options`` (``window``, ``bounds``, ``decimate``, ``resampling``) are passed on. What was
        assumed is in ``meta`` and ``meta["summary"]``.
        """
        p = Path(path)
        if not p.exists():
            raise FileNotFoundError(f"path: no such file: {p}")
        if p.is_dir():
            raise ValueError(f"path: expected a file, got a directory: {p}")
        if p.stat().st_size == 0:
            raise ValueError(f"path: file is empty: {p}")
        channel = check_int("channel", channel, 0)
        ext = p.suffix.lower()
        if geotiff.is_gdal_raster(p) or (raster_options and ext in geotiff.TIFF_EXTS):
            if max_height is not None:
                raise ValueError(f"max_height: not used for georeferenced rasters ({p.name}); heights come "
                                 "from the file's values, scale and offset")
            r = geotiff.read_geotiff(p, band=channel + 1, dx=dx, dz=dz, **raster_options)
            h, _ = _heights(f"path: {p}", r.heights, None, True)  # a float band may hold infinities
            return cls(heights=h, dx=r.dx, dz=r.dz, name=r.name, meta=r.meta)
        if raster_options:
            raise TypeError(f"{sorted(raster_options)[0]}: only GeoTIFF / GDAL rasters take "
                            f"{', '.join(sorted(raster_options))}; {p.name} is read by OpenImageIO or numpy")
        arr = _read_npy(p) if ext == ".npy" else _read_image(p, channel)
        h, source_dtype = _heights(f"path: {p}", arr, max_height, allow_nan)
        meta = {"source_dtype": str(source_dtype), "source": str(p),
                **({} if max_height is None else {"max_height": float(max_height)}),
                **({"channel": channel} if channel else {})}
        if dx is None:  # an image or .npy file carries no spacing: the default is said, once per load
            meta["spacing"] = f"{DEFAULT_SPACING:g} m assumed: {p.name} carries no spacing"
            warnings.warn(f"dx: {p.name} carries no sample spacing; {DEFAULT_SPACING:g} m assumed (pass dx=, in "
                          "metres, to Heightmap.load)", DefaultSpacingWarning, stacklevel=2)
            dx = DEFAULT_SPACING
        return cls(heights=h, dx=_positive("dx", dx), dz=_positive("dz", dz if dz is not None else dx), name=p.stem,
                   meta=meta)

    @classmethod
    def open(cls, path: str | os.PathLike, dx: float | None = None, dz: float | None = None, *, band: int = 1,
             cache_mb: float | None = None) -> StreamedHeightmap:
        """Open a GeoTIFF (or any GDAL raster) without reading it: a :class:`StreamedHeightmap` that reads the
        windows a frame needs. Spacing, CRS, no-data and orientation are those :meth:`load` finds.

        Args:
            dx, dz: spacing overriding the georeferencing's (as in :meth:`load`).
            band: 1-based band.
            cache_mb: the tile cache's cap in MiB (default ``TERRAINWARP_TILE_CACHE_MB``, else 512).
        """
        return StreamedHeightmap(GeoTiffSource(path, band=band, dx=dx, dz=dz), cache_mb=cache_mb)

    @classmethod
    def example(cls, name: str = "jacksboro") -> Heightmap:
        """A real DEM shipped with matplotlib.

        * ``"jacksboro"``: SRTM 3-arc-second DEM of the Jacksboro fault, Tennessee, 344 x 403 int16
          metres; spacing converted from degrees to metres on WGS84 at the centre latitude.
        * ``"topobathy"``: 91 x 120 float32 topography and bathymetry off the Pacific Northwest
          (negative heights below sea level); its rows run north to south after a flip.
        """
        from matplotlib import cbook  # lazy: heavy optional dependency

        check_choice("name", name, EXAMPLES)
        if name == "jacksboro":
            d = cbook.get_sample_data("jacksboro_fault_dem.npz")
            z = np.asarray(d["elevation"])
            # The file's 'ymin' is the northern edge of row 0; rows run south, i.e. +z. No flip.
            lat = 0.5 * (float(d["ymin"]) + float(d["ymax"]))
            mlon, mlat = metres_per_degree(lat)
            dx = float(d["dx"]) * mlon
            dz = float(d["dy"]) * mlat
            return cls.from_array(z, dx, dz, name="jacksboro", meta={
                "source": "matplotlib sample data jacksboro_fault_dem.npz (SRTM)", "latitude_deg": lat,
                "spacing_deg": [float(d["dx"]), float(d["dy"])], "flipped_rows": False})
        d = cbook.get_sample_data("topobathy.npz")
        z = np.asarray(d["topo"])
        lat_a = np.asarray(d["latitude"], dtype=np.float64)
        lon_a = np.asarray(d["longitude"], dtype=np.float64)
        flipped = bool(lat_a[-1] > lat_a[0])
        if flipped:  # south-up: make row 0 the northern row
            z = z[::-1]
        lat = float(lat_a.mean())
        mlon, mlat = metres_per_degree(lat)
        dx = float(np.mean(np.diff(lon_a))) * mlon
        dz = float(np.abs(np.mean(np.diff(lat_a)))) * mlat
        return cls.from_array(z, dx, dz, name="topobathy", meta={
            "source": "matplotlib sample data topobathy.npz", "latitude_deg": lat, "flipped_rows": flipped})

    @classmethod
    def fbm(cls, rows: int, cols: int | None = None, *, seed: int = 0, max_height: float = 1000.0,
            dx: float = 10.0, dz: float | None = None, feature_size: float = 256.0, octaves: int = 8,
            gain: float = 0.5, lacunarity: float = 2.0, ridged: bool = False) -> Heightmap:
        """Procedural fractal terrain (fBm of gradient noise), deterministic for a seed.

        Heights lie in [0, max_height]. ``feature_size`` is the wavelength of the first octave in
        samples. Any window of a larger terrain with the same parameters equals that part of it.
        """
        cols = rows if cols is None else cols
        for nm, v in (("rows", rows), ("cols", cols)):
            check_int(nm, v, 1)
        check_heightmap_fits("rows" if rows >= cols else "cols", rows, cols)
        # the streamed source's rules and noise: one set of checks, the same heights as any window of it
        src = FbmSource(rows, cols, seed=seed, max_height=max_height, dx=dx, dz=dz, feature_size=feature_size,
                        octaves=octaves, gain=gain, lacunarity=lacunarity, ridged=ridged)
        h = src.read(1, 0, 0, int(rows), int(cols))
        return cls.from_array(h, src.dx, src.dz, name=src.name, meta={
            "source": "fbm", "seed": src.seed, "max_height": src.max_height, "feature_size": src.feature_size,
            "octaves": src.octaves,
            "gain": src.gain, "lacunarity": src.lacunarity, "ridged": src.ridged})

    # -- properties --------------------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.heights.shape[0]), int(self.heights.shape[1]))

    @property
    def bounds_xz(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """((xmin, zmin), (xmax, zmax)) of the sample grid in world metres."""
        return grid_bounds(self.origin, self.shape, self.dx, self.dz)

    @cached_property
    def height_range(self) -> tuple[float, float]:
        """(min, max) of the finite heights, metres. Worked out once: the heights are read-only, and every
        frame's tint asks for it (a masked copy of the whole grid per call cost tens of ms at 4097^2)."""
        return (float(np.nanmin(self.heights)), float(np.nanmax(self.heights)))

    @cached_property
    def has_nodata(self) -> bool:
        """True when some height is NaN (a no-data hole); worked out once (every LOD frame asks)."""
        return bool(np.isnan(self.heights).any())

    @cached_property
    def held(self) -> Held:
        """What frames keep with this heightmap between calls (:class:`Held`). Not pickled."""
        return Held()

    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k != "held"}

    def __repr__(self) -> str:
        lo, hi = self.height_range
        return (f"Heightmap({self.name!r}, shape={self.shape}, dx={self.dx:.4g}, dz={self.dz:.4g}, "
                f"heights=[{lo:.4g}, {hi:.4g}] m)")

    # -- sampling ----------------------------------------------------------------------------------
    def sample(self, x: object, z: object, method: str = "bilinear") -> np.ndarray:
        """Heights at world (x, z), float32, by the device's bilinear or bicubic filter."""
        xa = np.asarray(x, dtype=np.float64)
        za = np.asarray(z, dtype=np.float64)
        if method == "bilinear" and max(xa.size, za.size) <= HOST_SAMPLES:  # a launch costs more than the points
            h = self.heights
            return _bilinear_on_host(lambda i, j: h[i, j], self.shape, self.origin, self.dx, self.dz, xa, za)
        u = (xa - self.origin[0]) / self.dx
        v = (za - self.origin[1]) / self.dz
        return sampling.sample_grid(self.heights, u, v, method)

    # -- designer controls (mrbsp-lod-visibility.txt, section 1) -----------------------------------
    def designed(self, *, sea_level: float = 0.0, height_scale: float = 1.0, seabed: float = 1.0,
                 smoothing: int = 0, mountain_height: float | None = None) -> Heightmap:
        """The designer's controls of mrbsp section 1, applied in this order:

        1. sea level: heights are shifted by ``-sea_level`` ("sink" with > 0, "float" with < 0);
        2. seabed factor: heights below the new sea level are multiplied by ``seabed`` (< 1 makes
           the sea shallower, so beaches, the land within a few metres of sea level, grow);
        3. height scale: everything is multiplied by ``height_scale`` (the highest peak);
        4. smoothing: ``smoothing`` passes of a 3x3 binomial filter, except on mountains (samples at
           or above ``mountain_height`` after scaling, default the 85th percentile), which keep their
           jagged peaks.
        """
        for nm, v in (("sea_level", sea_level), ("height_scale", height_scale), ("seabed", seabed)):
            if not math.isfinite(float(v)):
                raise ValueError(f"{nm}: expected a finite number, got {v}")
        if height_scale <= 0 or seabed < 0:
            raise ValueError("height_scale: expected > 0 and seabed: expected >= 0")
        if int(smoothing) < 0:
            raise ValueError(f"smoothing: expected >= 0 passes, got {smoothing}")
        h = self.heights.astype(np.float64) - float(sea_level)
        h = np.where(h < 0.0, h * float(seabed), h) * float(height_scale)
        if smoothing:
            fin = np.isfinite(h)
            thr = float(np.percentile(h[fin], 85.0)) if mountain_height is None else float(mountain_height)
            mountain = h >= thr
            for _ in range(int(smoothing)):
                p = np.pad(h, 1, mode="edge")
                k = np.array([1.0, 2.0, 1.0])
                s = sum(k[a] * k[b] * p[a:a + h.shape[0], b:b + h.shape[1]] for a in range(3) for b in range(3))
                h = np.where(mountain, h, s / 16.0)
        return Heightmap.from_array(h, self.dx, self.dz, origin=self.origin, allow_nan=True,
                                    name=self.name + "-designed", meta={**self.meta, "designed": {
                                        "sea_level": sea_level, "height_scale": height_scale,
                                        "seabed": seabed, "smoothing": int(smoothing)}})

    # -- saving ------------------------------------------------------------------------------------
    def save(self, path: str | os.PathLike) -> Path:
        """Save losslessly: ``.tif``/``.tiff``/``.exr`` as float32, ``.npy`` as float32, ``.png`` as
        16-bit integers (only when every height is an integer in [0, 65535]; otherwise a ValueError
        suggests a float format). Written to a temporary name, then renamed.

        A heightmap read from a GeoTIFF / GDAL raster saves ``.tif``/``.tiff`` as a GeoTIFF with its CRS,
        transform, nodata, scale/offset and source dtype (see :func:`terrainwarp.io.geotiff.write_geotiff`).
        """
        p = Path(path)
        ext = p.suffix.lower()
        h = self.heights
        if ext in (".tif", ".tiff"):
            if geotiff.is_georeferenced(self.meta):
                return geotiff.write_geotiff(self, p)
        if ext == ".npy":
            with atomic_path(p) as tmp:
                np.save(tmp, h)
            return p
        if ext == ".png":
            if not (np.all(np.isfinite(h)) and np.all(h == np.round(h)) and h.min() >= 0 and h.max() <= 65535):
                raise ValueError("path: PNG stores 16-bit integers; these heights are not integers in "
                                 "[0, 65535]: save as .tif or .exr (float32) instead")
            write_image(p, h.astype(np.uint16))
            return p
        if ext in (".tif", ".tiff", ".exr"):
            write_image(p, h)
            return p
        raise ValueError(f"path: expected a .png, .tif, .tiff, .exr or .npy file name, got {p.name!r}")


# -- OpenImageIO ------------------------------------------------------------------------------------
def _read_image(p: Path, channel: int) -> np.ndarray:
    import OpenImageIO as oiio  # lazy: heavy optional dependency

    geotiff.check_tiff_layout(p)  # libtiff would guess at a mixed-up block layout (see there)
    with native_stderr_silenced():  # libpng prints "libpng error: ..." itself; the ValueError says it
        inp = oiio.ImageInput.open(str(p))
    if inp is None:
        raise ValueError(f"path: cannot read {p} as an image: {_one_line(oiio.geterror()) or 'unknown format'}")
    try:
        spec = inp.spec()
        if spec.width <= 0 or spec.height <= 0:
            raise ValueError(f"path: image {p} is empty ({spec.width}x{spec.height})")
        if not 0 <= channel < spec.nchannels:
            raise ValueError(f"channel: expected 0..{spec.nchannels - 1} for {p}, got {channel}")
        check_heightmap_fits("path", spec.height, spec.width, what=f"image {p.name}")  # from the header
        with native_stderr_silenced():
            px = inp.read_image(0, 0, channel, channel + 1, oiio.UNKNOWN)
        if px is None:
            raise ValueError(f"path: {p} is corrupt or truncated: {_one_line(inp.geterror())}")
    finally:
        inp.close()
    arr = np.asarray(px)
    if arr.ndim == 3:
        arr = arr[:, :, 0]
    if arr.dtype == np.float16:
        arr = arr.astype(np.float32)
    return arr


def _one_line(err: str) -> str:
    """OpenImageIO's error text (one line per library layer) as one line, repeats left out."""
    parts: list[str] = []
    for line in err.splitlines():
        if line.strip() and line.strip() not in parts:
            parts.append(line.strip())
    return "; ".join(parts)


def _read_npy(p: Path) -> np.ndarray:
    """The array of a ``.npy`` file, its header checked first: a readable header (numpy's parser raises
    several types on a damaged one), non-negative dimensions, a 2D grid (or (H, W, 1)) that fits in memory.
    Raises ValueError naming the file."""
    try:
        with p.open("rb") as f:
            version = np.lib.format.read_magic(f)
            shape, _, _ = (np.lib.format.read_array_header_1_0(f) if version == (1, 0)
                           else np.lib.format.read_array_header_2_0(f))
    except (ValueError, TypeError, SyntaxError, EOFError, tokenize.TokenError) as e:
        raise ValueError(f"path: cannot read {p} as .npy: its header is damaged: {_one_line(str(e))}") from e
    if any(int(v) < 0 for v in shape) or not (len(shape) == 2 or (len(shape) == 3 and shape[2] == 1)):
        raise ValueError(f"path: {p} holds an array of shape {tuple(shape)}; expected a 2D grid (H, W) or (H, W, 1)")
    check_heightmap_fits("path", shape[0], shape[1], what=f"array in {p.name}")
    try:
        return np.load(p, allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:  # a short body, an object array
        raise ValueError(f"path: cannot read {p} as .npy: {_one_line(str(e))}") from e


# -- streamed ---------------------------------------------------------------------------------------
class StreamedHeightmap:
    """A heightmap read a tile at a time: a :class:`Heightmap`'s interface (shape, spacing, origin, name,
    meta, bounds, height range, sampling) over a :class:`terrainwarp.io.tiles.TileSource`, with the grid
    never held. Frames read the tiles under the patches they draw, at the step their level needs
    (:mod:`terrainwarp.lod.streaming`); tiles live in an LRU cache with a memory cap (``cache_mb``,
    default ``TERRAINWARP_TILE_CACHE_MB`` or 512 MiB) whose counters (:meth:`counters`) frames report.

    Build one with :meth:`Heightmap.open` (a GeoTIFF), :meth:`fbm` (a procedural terrain of any size) or
    :meth:`of` (an in-memory heightmap read as tiles). :meth:`load` reads the whole grid into a
    :class:`Heightmap` (when it fits), bit for bit the heights the in-memory path reads.
    """

    def __init__(self, source: TileSource, *, cache_mb: float | None = None):
        if not isinstance(source, TileSource):
            raise TypeError(f"source: expected a TileSource, got {type(source).__name__}")
        self.source = source
        self.tiles = TileCache(source, cache_mb)
        self.shape: tuple[int, int] = (int(source.shape[0]), int(source.shape[1]))
        self.dx, self.dz = float(source.dx), float(source.dz)
        self.origin: tuple[float, float] = (float(source.origin[0]), float(source.origin[1]))
        self.name = source.name
        self.meta = source.meta
        self.held = Held()  # what frames keep with it between calls

    @classmethod
    def fbm(cls, rows: int, cols: int | None = None, *, cache_mb: float | None = None, **fbm: Any) -> StreamedHeightmap:
        """The terrain :meth:`Heightmap.fbm` makes with the same arguments, generated window by window (any
        size up to 2^24 samples a side)."""
        return cls(FbmSource(rows, cols, **fbm), cache_mb=cache_mb)

    @classmethod
    def of(cls, heightmap: Heightmap, *, cache_mb: float | None = None) -> StreamedHeightmap:
        """An in-memory heightmap read through tiles (for comparing the streamed path with the in-memory one)."""
        if not isinstance(heightmap, Heightmap):
            raise TypeError(f"heightmap: expected a Heightmap, got {type(heightmap).__name__}")
        hm = heightmap
        return cls(ArraySource(hm.heights, hm.dx, hm.dz, hm.origin, hm.name, hm.meta), cache_mb=cache_mb)

    @property
    def bounds_xz(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """((xmin, zmin), (xmax, zmax)) of the sample grid in world metres."""
        return grid_bounds(self.origin, self.shape, self.dx, self.dz)

    @cached_property
    def height_range(self) -> tuple[float, float]:
        """(min, max) of the finite heights, metres: exact for a file (scanned once tile by tile, then kept in
        its cache folder) and an array; for a procedural source, of its coarse overview widened by what the
        overview can miss (see the source's ``height_range``)."""
        return self.source.height_range(self.tiles)

    def known_height_range(self) -> tuple[float, float] | None:
        """:attr:`height_range` when it costs no scan of the terrain: worked out already, kept in a file's cache,
        or cheap for the source (an fBm's overview, an array); None for a file whose range is not known yet (its
        pyramid's build works it out)."""
        if "height_range" in self.__dict__ or not isinstance(self.source, GeoTiffSource):
            return self.height_range
        got = self.source.cache().value("height_range")
        return (float(got[0]), float(got[1])) if isinstance(got, list) and len(got) == 2 else None

    def __repr__(self) -> str:
        return (f"StreamedHeightmap({self.name!r}, shape={self.shape}, dx={self.dx:.4g}, dz={self.dz:.4g}, "
                f"{type(self.source).__name__})")

    def counters(self) -> dict[str, int]:
        """The tile cache's counters: tiles_read, bytes_read, hits, evicted, resident_bytes, peak_bytes."""
        return self.tiles.snapshot()

    def window(self, step: int, r0: int, c0: int, rows: int, cols: int, out: np.ndarray | None = None) -> np.ndarray:
        """(rows, cols) float32 of the step-``step`` point-sampled overview from its sample (r0, c0), written into
        ``out`` when given (a writable (rows, cols) float32 array)."""
        args = [check_int(n, v) for n, v in (("step", step), ("r0", r0), ("c0", c0), ("rows", rows), ("cols", cols))]
        return self.tiles.window(*args, out=out)

    def load(self) -> Heightmap:
        """The whole grid as an in-memory :class:`Heightmap` (refused when it would not fit)."""
        check_heightmap_fits("heightmap", *self.shape, what=f"streamed heightmap {self.name}")
        h = self.window(1, 0, 0, *self.shape)
        return Heightmap(heights=h, dx=self.dx, dz=self.dz, origin=self.origin, name=self.name, meta=dict(self.meta))

    def sample(self, x: object, z: object, method: str = "bilinear") -> np.ndarray:
        """Heights at world (x, z), float32, bit for bit :meth:`Heightmap.sample` (bilinear only): each point
        reads the 2 x 2 samples around it from the tiles."""
        if method != "bilinear":
            raise ValueError(f"method: a streamed heightmap samples 'bilinear', got {method!r}")
        return _bilinear_on_host(self._values, self.shape, self.origin, self.dx, self.dz, x, z)

    def _values(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """Full-resolution samples (i, j), gathered tile by tile."""
        out = np.empty(len(i), np.float32)
        tid = (i // TILE) * (self.shape[1] // TILE + 1) + j // TILE
        for t in np.unique(tid):
            m = tid == t
            ti, tj = int(i[m][0] // TILE), int(j[m][0] // TILE)
            out[m] = self.tiles.tile(1, ti, tj)[i[m] - ti * TILE, j[m] - tj * TILE]
        return out


def _bilinear_on_host(values: Callable[[np.ndarray, np.ndarray], np.ndarray], shape: tuple[int, int],
                      origin: tuple[float, float], dx: float, dz: float, x: object, z: object) -> np.ndarray:
    """Bilinear heights at world (x, z), float32, bit for bit the device's filter (``sampling.sample_bilinear``):
    its float32 steps in its order, on the host. ``values(i, j)`` gives the samples (i, j) (int64 arrays)."""
    xa, za = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(z, dtype=np.float64))
    out_shape = xa.shape
    hh, ww = shape
    # the kernel's steps: float32 grid coordinates, clamped to the grid, then floor
    u = np.clip(((xa.reshape(-1) - origin[0]) / dx).astype(np.float32), 0, np.float32(ww - 1))
    v = np.clip(((za.reshape(-1) - origin[1]) / dz).astype(np.float32), 0, np.float32(hh - 1))
    j0, i0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    j1, i1 = np.minimum(j0 + 1, ww - 1), np.minimum(i0 + 1, hh - 1)
    h00, h01, h10, h11 = values(i0, j0), values(i0, j1), values(i1, j0), values(i1, j1)
    fu, fv = u - j0.astype(np.float32), v - i0.astype(np.float32)
    b, c, d = h01 - h00, h10 - h00, h11 - h00
    top = np.float32(0.0) + (b - np.float32(0.0)) * fu
    bot = c + (d - c) * fu
    return (h00 + (top + (bot - top) * fv)).reshape(out_shape)

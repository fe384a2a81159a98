"""Real DEMs through rasterio (GDAL): GeoTIFF and the other rasters GDAL reads (.vrt, .img, .asc, .hgt, ...).

What a file's georeferencing becomes (every assumption is written into ``Heightmap.meta`` and the
one-paragraph :func:`describe`):

* Heights: band ``band`` (1-based, as in GDAL) of the file, ``raw * scale + offset`` from the band's
  scale/offset tags, converted to metres when the band's unit tag names feet; no-data cells (the band's
  nodata value, or its mask band) become NaN and are counted.
* Spacing in metres: a projected CRS's pixel size in its linear unit times the unit's length in metres
  (grid metres: the projection's scale factor is not applied); a geographic CRS's pixel size in degrees
  converted at the latitude of the centre of the part read, on the CRS's own ellipsoid (dx shrinks with
  cos(latitude), dz does not). A raster with a geotransform but no CRS: its pixel size taken as metres.
  ``dx``/``dz`` given by the caller override all of this (and say so).
* Orientation: row i of the heightmap runs along +z, which is south (x east, y up, z south is
  right-handed). A north-up raster (negative y pixel size) is used as it is; a south-up one (positive y
  pixel size) is flipped so that row 0 is its northern row, and an east-to-west one (negative x pixel size)
  is mirrored so that column 0 is its western column. Rotated or sheared geotransforms are refused.
* World origin: (0, 0) is the centre of the north-western sample read; ``meta["sample00_crs"]`` gives its
  CRS coordinates.

Large rasters: ``window`` (pixel rows/columns of the file) or ``bounds`` (CRS coordinates) read only that
part, and ``decimate=k`` reads every k x k block as one sample (GDAL ``out_shape`` with ``resampling``,
which uses the file's overviews when it has them), never the whole file.

:func:`write_geotiff` writes a heightmap read here back as a GeoTIFF with its CRS, transform, nodata,
scale/offset and dtype (int16, uint16 and float32 round trips are bit-exact).
"""

from __future__ import annotations

import math
import os
import re
import struct
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple, Protocol

import numpy as np

from ..kernels.checks import check_choice, check_int, check_number
from .files import atomic_path
from .geodesy import WGS84_A, WGS84_INV_F, metres_per_degree
from .memory import check_heightmap_fits

if TYPE_CHECKING:  # rasterio and affine are imported where used (heavy optional dependencies)
    from affine import Affine
    from rasterio.crs import CRS
    from rasterio.io import DatasetReader
    from rasterio.windows import Window

__all__ = ["GDAL_EXTS", "TIFF_EXTS", "GeoRaster", "HeightGrid", "RasterHeader", "check_tiff_layout", "describe",
           "gdal_cause",
           "is_gdal_raster", "is_georeferenced", "open_raster", "read_failure", "read_header", "read_oriented",
           "read_geotiff", "write_geotiff", "write_tiled"]

# Extensions always read through GDAL; TIFF_EXTS only when the file carries georeferencing (plain TIFFs
# stay with OpenImageIO, see Heightmap.load) or the caller asks for a window, bounds or decimation.
GDAL_EXTS = (".vrt", ".img", ".asc", ".hgt", ".dem", ".bil", ".bt", ".ter", ".xyz", ".grd", ".nc", ".jp2")
TIFF_EXTS = (".tif", ".tiff", ".gtiff")

# Vertical units (band unit tags) -> metres. Unknown units are reported and taken as metres.
_VERTICAL_UNITS = {
    "m": 1.0, "metre": 1.0, "meter": 1.0, "metres": 1.0, "meters": 1.0,
    "ft": 0.3048, "foot": 0.3048, "feet": 0.3048, "international foot": 0.3048,
    "us survey foot": 1200.0 / 3937.0, "us-ft": 1200.0 / 3937.0, "ftus": 1200.0 / 3937.0,
    "us survey feet": 1200.0 / 3937.0,
}
# GDAL's resamplings that a read can use (min, max and med are warp-only: GDAL refuses them in a read)
_RESAMPLING = ("nearest", "average", "bilinear", "cubic", "cubic_spline", "lanczos", "mode", "rms")
_SAVE_DTYPES = ("int8", "uint8", "int16", "uint16", "int32", "uint32", "float32", "float64")
# Relative tolerance under which a transform's rotation/shear terms count as zero (float noise in files).
_SHEAR_RTOL = 1e-12


class HeightGrid(Protocol):
    """What :func:`describe` and :func:`write_geotiff` need of a heightmap: a :class:`GeoRaster` or a
    :class:`terrainwarp.Heightmap` (io sits below the core types and does not import them)."""

    @property
    def heights(self) -> np.ndarray: ...  # (H, W) float32 metres, NaN at no-data
    @property
    def dx(self) -> float: ...
    @property
    def dz(self) -> float: ...
    @property
    def name(self) -> str: ...
    @property
    def meta(self) -> dict[str, Any]: ...


# -- helpers ---------------------------------------------------------------------------------------
def _rasterio():
    try:
        import rasterio  # lazy: heavy optional dependency
    except ImportError as e:  # pragma: no cover - rasterio is a dependency
        raise ImportError("reading GeoTIFF/GDAL rasters needs rasterio: pip install rasterio") from e
    return rasterio


_TIFF_MAGIC = {b"II*\x00": ("<", False), b"MM\x00*": (">", False), b"II+\x00": ("<", True), b"MM\x00+": (">", True)}
_TILE_TAGS = {322: "TileWidth", 323: "TileLength", 324: "TileOffsets", 325: "TileByteCounts"}
_STRIP_TAGS = {273: "StripOffsets", 279: "StripByteCounts"}


def _first_ifd_tags(p: Path) -> set[int] | None:
    """The tags of a TIFF's (or BigTIFF's) first image directory, or None when ``p`` is not a TIFF or its
    directory cannot be read (the reader then says why)."""
    with p.open("rb") as f:
        head = f.read(16)
        if head[:4] not in _TIFF_MAGIC:
            return None
        e, big = _TIFF_MAGIC[head[:4]]
        ifd = struct.unpack(e + ("Q" if big else "I"), head[8:16] if big else head[4:8])[0]
        f.seek(min(ifd, 2**62))
        raw = f.read(8 if big else 2)
        if len(raw) < (8 if big else 2):
            return None
        n = struct.unpack(e + ("Q" if big else "H"), raw)[0]
        size = 20 if big else 12
        body = f.read(min(n, 4096) * size)
    return {struct.unpack(e + "H", body[k:k + 2])[0] for k in range(0, len(body) - size + 1, size)}


def check_tiff_layout(path: str | os.PathLike) -> None:
    """Refuse a TIFF whose first image mixes up its block layout: tile offsets without both tile sizes (or a
    tile size without its partner), or strip offsets beside tile sizes. libtiff then guesses ("RowsPerStrip
    not defined ... assuming all one strip") and decodes tile data as a strip: OpenImageIO returns scrambled
    heights, and GDAL 3.10 (rasterio 1.4.4) uninitialised memory that differs from run to run. A file that
    is not a TIFF, or whose directory cannot be read, passes (its reader reports it)."""
    p = Path(path)
    try:
        tags = _first_ifd_tags(p)
    except (OSError, struct.error):
        return
    if tags is None:
        return
    tiled = {322, 323} <= tags
    wrong = ([_STRIP_TAGS[t] for t in _STRIP_TAGS if t in tags] if tiled else
             [_TILE_TAGS[t] for t in _TILE_TAGS if t in tags])
    if wrong:
        layout = "tiled (TileWidth and TileLength)" if tiled else "striped (no TileWidth and TileLength pair)"
        raise ValueError(f"path: {p} is damaged: its first image is {layout} but holds {', '.join(wrong)}; "
                         "its pixels cannot be located")


def _open(p: Path) -> DatasetReader:
    rasterio = _rasterio()
    check_tiff_layout(p)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        try:
            return rasterio.open(p)
        except rasterio.errors.RasterioIOError as e:
            raise ValueError(f"path: cannot read {p} as a GDAL raster: {e}") from e


def is_gdal_raster(path: str | os.PathLike) -> bool:
    """True when :meth:`Heightmap.load` should read ``path`` through rasterio: a GDAL-only extension, or a
    TIFF that carries a CRS, a geotransform or ground control points (a GeoTIFF). Plain TIFFs, and
    unreadable files, are False (left to OpenImageIO and its error messages)."""
    p = Path(path)
    ext = p.suffix.lower()
    if ext in GDAL_EXTS:
        return True
    if ext not in TIFF_EXTS:
        return False
    try:
        with _open(p) as src:
            return src.crs is not None or not src.transform.is_identity or bool(src.gcps[0])
    except ValueError:
        return False


def _ellipsoid(crs: CRS) -> dict[str, Any]:
    """(name, semi-major axis a in metres, inverse flattening) of a CRS's ellipsoid, parsed from its WKT;
    WGS84 when the WKT does not name one."""
    wkt = crs.to_wkt()
    m = re.search(r'(?:SPHEROID|ELLIPSOID)\["([^"]*)",\s*([0-9.eE+-]+),\s*([0-9.eE+-]+)', wkt)
    if m is None:
        return {"name": "WGS 84 (assumed: the CRS names no ellipsoid)", "a": WGS84_A, "inv_f": WGS84_INV_F}
    return {"name": m.group(1), "a": float(m.group(2)), "inv_f": float(m.group(3))}


def _crs_name(crs: CRS) -> str:
    try:
        auth = crs.to_authority()
    except Exception:  # noqa: BLE001 - some CRSs have no authority code
        auth = None
    m = re.match(r'\s*[A-Z_]+\["([^"]*)"', crs.to_wkt())
    label = m.group(1) if m else crs.to_string()
    return f"{label} ({auth[0]}:{auth[1]})" if auth else label


def _int_arg(name: str, v: object, lo: int) -> int:
    return check_int(name, v, lo)


def _pixel_window(src: DatasetReader, window: object, bounds: object) -> tuple[int, int, int, int]:
    """(row_off, col_off, height, width) in file pixels, inside the raster."""
    H, W = src.height, src.width
    if window is not None and bounds is not None:
        raise ValueError("window: give a pixel window or bounds, not both")
    if window is None and bounds is None:
        return (0, 0, H, W)
    if bounds is not None:
        b = np.asarray(bounds, dtype=np.float64).reshape(-1)
        if b.shape != (4,) or not np.all(np.isfinite(b)) or b[0] >= b[2] or b[1] >= b[3]:
            raise ValueError(f"bounds: expected (left, bottom, right, top) in CRS units with left < right "
                             f"and bottom < top, got {bounds!r}")
        t = src.transform  # axis-aligned (checked by the caller)
        with np.errstate(over="ignore"):  # a tiny pixel size puts far bounds at +-inf pixels: clipped below
            cs = [float(np.clip((x - t.c) / t.a, -1.0, W + 1.0)) for x in (b[0], b[2])]
            rs = [float(np.clip((y - t.f) / t.e, -1.0, H + 1.0)) for y in (b[1], b[3])]
        # cells that the bounds touch (a cell is kept when any part of it lies inside; 1e-9 px of slack)
        r0, r1 = math.floor(min(rs) + 1e-9), math.ceil(max(rs) - 1e-9)
        c0, c1 = math.floor(min(cs) + 1e-9), math.ceil(max(cs) - 1e-9)
        r0, c0, r1, c1 = max(r0, 0), max(c0, 0), min(r1, H), min(c1, W)
        if r1 <= r0 or c1 <= c0:
            raise ValueError(f"bounds: {tuple(float(v) for v in b)} does not overlap the raster "
                             f"{tuple(float(v) for v in src.bounds)}")
        return (r0, c0, r1 - r0, c1 - c0)
    if hasattr(window, "row_off"):  # a rasterio Window
        rw = (window.row_off, window.col_off, window.height, window.width)
    else:
        try:
            (ra, rb), (ca, cb) = window
        except (TypeError, ValueError) as e:
            raise ValueError(f"window: expected ((row_start, row_stop), (col_start, col_stop)) or a "
                             f"rasterio Window, got {window!r}") from e
        rw = (ra, ca, rb - ra, cb - ca)
    if not all(isinstance(v, int | np.integer) or float(v).is_integer() for v in rw):
        raise ValueError(f"window: expected whole pixels, got {window!r}")
    r0, c0, h, w = (int(v) for v in rw)
    if r0 < 0 or c0 < 0 or h <= 0 or w <= 0 or r0 + h > H or c0 + w > W:
        raise ValueError(f"window: expected a non-empty window inside the {H}x{W} raster, got rows "
                         f"[{r0}, {r0 + h}) and columns [{c0}, {c0 + w})")
    return (r0, c0, h, w)


# -- reading ---------------------------------------------------------------------------------------
class GeoRaster(NamedTuple):
    """What :func:`read_geotiff` read: plain arrays and metadata (:meth:`terrainwarp.Heightmap.load` builds
    the Heightmap from it).

    Attributes:
        heights: (H, W) float32 metres, NaN at no-data, row 0 the northern row, column 0 the western one.
        dx, dz: spacing in metres, east-west (columns) and north-south (rows).
        name: a label (the file's stem).
        meta: the CRS (WKT), the transform of the part read (file orientation), nodata, scale/offset,
            dtype, the flips, the latitude used for a geographic CRS, and ``meta["summary"]``
            (:func:`describe`).
    """

    heights: np.ndarray
    dx: float
    dz: float
    name: str
    meta: dict[str, Any]


class _Part(NamedTuple):
    """The part of one band read from an open raster, and the band's tags."""

    raw: np.ndarray  # (n, m) file values, file orientation
    holes: np.ndarray  # (n, m) bool, no-data
    transform: Affine  # of the samples read
    window: tuple[int, int, int, int]  # (row_off, col_off, height, width) in file pixels, whole blocks
    dtype: np.dtype
    nodata: float | None
    scale: float
    offset: float
    unit: str
    crs: CRS | None
    georef: bool


def read_geotiff(path: str | os.PathLike, *, band: int = 1, window: object = None, bounds: object = None,
                 decimate: int = 1, resampling: str = "average", dx: float | None = None,
                 dz: float | None = None) -> GeoRaster:
    """Read a GeoTIFF (or any GDAL raster) as heights in metres, north-up.

    Args:
        path: the raster file.
        band: 1-based band number.
        window: ``((row_start, row_stop), (col_start, col_stop))`` in file pixels, or a rasterio
            ``Window``; only these pixels are read.
        bounds: ``(left, bottom, right, top)`` in the CRS's units; every cell they touch is read.
        decimate: read every ``decimate`` x ``decimate`` block of the window as one sample (rows and columns
            past the last whole block are dropped); spacing grows by this factor.
        resampling: how GDAL makes one sample from a block: ``"average"`` (default; the block mean, no-data
            cells left out), ``"nearest"``, ``"bilinear"``, ... (a ``rasterio.enums.Resampling`` name).
        dx, dz: spacing in metres overriding the one derived from the georeferencing.

    Returns:
        GeoRaster with ``heights`` (H, W) float32 metres (NaN at no-data), row 0 the northern row, spacing
        ``dx`` (east-west) and ``dz`` (north-south) in metres, and ``meta`` holding the CRS (WKT), the
        transform of the part read (file orientation), nodata, scale/offset, dtype, the flips, the
        latitude used for a geographic CRS, and ``meta["summary"]`` (:func:`describe`).

    Raises:
        ValueError: unreadable file, bad band/window/bounds/decimate, a rotated or sheared transform, a
            window that holds only no-data.
    """
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"path: no such file: {p}")
    k = _int_arg("decimate", decimate, 1)
    check_choice("resampling", resampling, _RESAMPLING)
    with _open(p) as src:
        b = _band(src, band, p)
        pw = _pixel_window(src, window, bounds)
        check_heightmap_fits("window" if window is not None else "bounds" if bounds is not None else "path",
                             pw[2] // k, pw[3] // k, what=f"part of {p.name} read as heights",
                             hint="read a part with window= or bounds=, or one sample per k x k block "
                                  "with decimate=k")  # from the header, before GDAL decodes anything
        part = _read_part(src, b, pw, k, resampling)
        file_meta = dict(source=str(p), driver=src.driver, band=b, band_count=src.count,
                         raster_shape=[int(src.height), int(src.width)],
                         area_or_point=src.tags().get("AREA_OR_POINT", "Area"))
    n_holes = int(part.holes.sum())
    if n_holes == part.raw.size:
        raise ValueError(f"path: every cell of band {b} in the part read of {p} is no-data ({part.nodata})")
    h64, vf, notes = _decode(part)
    h64, sdx, sdz, meta = _described(part, h64, p, file_meta, b, k, resampling, dx, dz, vf, notes)
    meta["nodata_count"] = n_holes
    r = GeoRaster(np.ascontiguousarray(h64.astype(np.float32)), sdx, sdz, p.stem, meta)
    meta["summary"] = describe(r)
    return r


def _described(part: _Part, h64: np.ndarray, p: Path, file_meta: dict, b: int, k: int, resampling: str,
               dx: float | None, dz: float | None, vf: float,
               notes: list[str]) -> tuple[np.ndarray, float, float, dict[str, Any]]:
    """(heights north-up, dx, dz, meta) of a part read: what :func:`read_geotiff` and :func:`read_header` say."""
    sdx, sdz, meta = _spacing(part, p, dx, dz)
    h64, flip_rows, flip_cols, s00 = _orient(h64, part)
    tw, (r0, c0, nk, mk) = part.transform, part.window
    n, m = part.raw.shape
    meta.update(
        source=file_meta["source"], driver=file_meta["driver"], band=b, band_count=file_meta["band_count"],
        crs=part.crs.to_wkt() if part.crs is not None else None,
        crs_name=_crs_name(part.crs) if part.crs is not None else None,
        transform=[tw.a, tw.b, tw.c, tw.d, tw.e, tw.f],
        raster_shape=file_meta["raster_shape"],
        window=[r0, c0, nk, mk], decimate=k, resampling=resampling if k > 1 else None,
        source_dtype=str(part.dtype), nodata=None if part.nodata is None else float(part.nodata),
        nodata_count=None, scale=part.scale, offset=part.offset, vertical_unit=part.unit or None,
        vertical_unit_m=vf, area_or_point=file_meta["area_or_point"], flipped_rows=bool(flip_rows),
        flipped_cols=bool(flip_cols), sample00_crs=[float(s00[0]), float(s00[1])],
        centre_crs=[float(tw.c + tw.a * m / 2.0), float(tw.f + tw.e * n / 2.0)],
        spacing_note=meta.pop("spacing_note"), notes=notes,
    )
    return h64, sdx, sdz, meta


# -- the whole raster read by windows (a streamed heightmap) -----------------------------------------
# GDAL's block cache while reading windows (its default is 5% of the machine's memory): the caller keeps the decoded
# tiles (the tile cache), so GDAL's needs only the blocks that neighbouring tiles share along their edges
BLOCK_CACHE_MB = 8


class RasterHeader(NamedTuple):
    """What :func:`read_geotiff` would say of the whole raster, read from the header only.

    ``shape`` is (rows, cols) north-up; ``meta`` as :class:`GeoRaster`'s (without ``nodata_count`` and
    ``summary``, which need every cell); ``flip`` the (rows, cols) flips of the file's orientation; ``tags``
    the band's decoding (nodata, scale, offset, vertical unit's metres, dtype)."""

    path: Path
    band: int
    shape: tuple[int, int]
    dx: float
    dz: float
    meta: dict[str, Any]
    flip: tuple[bool, bool]
    tags: _Part


def open_raster(path: str | os.PathLike) -> DatasetReader:
    """An open rasterio dataset (the caller closes it), with :func:`read_geotiff`'s error for a bad file."""
    return _open(Path(path))


def read_header(path: str | os.PathLike, *, band: int = 1, dx: float | None = None,
                dz: float | None = None) -> RasterHeader:
    """The whole raster's shape, spacing, CRS, no-data and orientation as :func:`read_geotiff` finds them,
    without reading a cell (windows are read with :func:`read_oriented`)."""
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"path: no such file: {p}")
    if p.is_dir() or p.stat().st_size == 0:
        raise ValueError(f"path: expected a non-empty raster file, got {p}")
    with _open(p) as src:
        b = _band(src, band, p)
        h, w = int(src.height), int(src.width)
        dtype = np.dtype(src.dtypes[b - 1])
        probe = _read_part(src, b, (0, 0, 1, 1), 1, "nearest")  # the band's tags, from one cell
        file_meta = dict(source=str(p), driver=src.driver, band=b, band_count=src.count, raster_shape=[h, w],
                         area_or_point=src.tags().get("AREA_OR_POINT", "Area"))
    # the whole raster's part, without its cells: a zero-strided stand-in carries the shape
    part = probe._replace(raw=np.broadcast_to(np.zeros(1, dtype), (h, w)),
                          holes=np.broadcast_to(np.zeros(1, bool), (h, w)), transform=probe.transform,
                          window=(0, 0, h, w))
    unit = part.unit
    vf = _VERTICAL_UNITS.get(unit.lower(), 1.0)
    notes = [f"unknown vertical unit {unit!r}: values taken as metres"] if unit and unit.lower() not in \
        _VERTICAL_UNITS else []
    _, sdx, sdz, meta = _described(part, part.raw, p, file_meta, b, 1, "nearest", dx, dz, vf, notes)
    return RasterHeader(p, b, (h, w), sdx, sdz, meta, (meta["flipped_rows"], meta["flipped_cols"]), part)


def read_oriented(header: RasterHeader, src: DatasetReader, r0: int, c0: int, rows: int, cols: int) -> np.ndarray:
    """(rows, cols) float32 heights (NaN at no-data) of the north-up window from sample (r0, c0), decoded as
    :func:`read_geotiff` decodes the whole raster (bit for bit the same values)."""
    h, w = header.shape
    fr, fc = header.flip
    fr0 = h - r0 - rows if fr else r0  # the window in file rows / columns
    fc0 = w - c0 - cols if fc else c0
    with _rasterio().Env(GDAL_CACHEMAX=BLOCK_CACHE_MB):  # the caller caches tiles: GDAL's cache would double it
        part = _read_part(src, header.band, (fr0, fc0, rows, cols), 1, "nearest")
    h64, _, _ = _decode(part)
    if fr:
        h64 = h64[::-1]
    if fc:
        h64 = h64[:, ::-1]
    return np.ascontiguousarray(h64.astype(np.float32))


# -- window ------------------------------------------------------------------------------------------
def _band(src: DatasetReader, band: object, p: Path) -> int:
    """The 1-based band to read, checked against the raster, whose transform is checked too."""
    b = _int_arg("band", band, 1)
    if b > src.count:
        raise ValueError(f"band: expected 1..{src.count} for {p}, got {band}")
    if np.dtype(src.dtypes[b - 1]).kind not in "iuf":
        raise ValueError(f"path: band {b} of {p} holds {src.dtypes[b - 1]} values; heights need a real "
                         "(integer or float) band")
    _check_transform(src, p)
    return b


def _check_transform(src: DatasetReader, p: Path) -> None:
    """Refuse what is not a grid aligned with east and north: ground control points, rotation/shear, a
    zero pixel size."""
    t = src.transform
    if t.is_identity and src.gcps[0]:
        raise ValueError(f"path: {p} is georeferenced by {len(src.gcps[0])} ground control points, not "
                         "a geotransform; resample it onto a grid first, e.g. `gdalwarp -t_srs <CRS> "
                         "in.tif out.tif`")
    scale_ref = max(abs(t.a), abs(t.e))
    if abs(t.b) > _SHEAR_RTOL * scale_ref or abs(t.d) > _SHEAR_RTOL * scale_ref:  # b, d below: 0
        raise ValueError(
            f"path: {p} has a rotated or sheared geotransform (row/column terms b={t.b!r}, d={t.d!r}); "
            "terrainwarp needs a grid aligned with east and north: resample it first, e.g. "
            "`gdalwarp -t_srs <its CRS> in.tif north_up.tif`")
    if t.a == 0.0 or t.e == 0.0 or not all(math.isfinite(v) for v in (t.a, t.b, t.c, t.d, t.e, t.f)):
        raise ValueError(f"path: {p} has a degenerate geotransform (pixel size {t.a}, {t.e}; origin {t.c}, {t.f})")


def _read_part(src: DatasetReader, b: int, pixel_window: tuple[int, int, int, int], k: int,
               resampling: str) -> _Part:
    """Band ``b`` over ``pixel_window`` (whole ``k`` x ``k`` blocks), its no-data cells and its tags."""
    from affine import Affine  # lazy: heavy optional dependency (with rasterio)
    from rasterio.enums import Resampling  # lazy: heavy optional dependency
    from rasterio.windows import Window

    r0, c0, h, w = pixel_window
    n, m = h // k, w // k
    if n < 1 or m < 1:
        raise ValueError(f"decimate: {k} leaves no sample of the {h}x{w} window")
    win = Window(c0, r0, m * k, n * k)
    rs = getattr(Resampling, resampling)
    dtype = np.dtype(src.dtypes[b - 1])
    try:
        raw = src.read(b, window=win, out_shape=(n, m), resampling=rs) if k > 1 else src.read(b, window=win)
        holes, nodata = _no_data(src, b, raw, win, k, dtype)
    except _rasterio().errors.RasterioError as e:
        raise ValueError(read_failure(src, b, pixel_window, e)) from e
    t = src.transform
    return _Part(
        raw=raw, holes=holes, transform=Affine(t.a * k, 0.0, t.c + t.a * c0, 0.0, t.e * k, t.f + t.e * r0),
        window=(r0, c0, n * k, m * k), dtype=dtype, nodata=nodata,
        scale=float(src.scales[b - 1] if src.scales[b - 1] is not None else 1.0),
        offset=float(src.offsets[b - 1] if src.offsets[b - 1] is not None else 0.0),
        unit=(src.units[b - 1] or "").strip(), crs=src.crs, georef=src.crs is not None or not t.is_identity)


# GDAL names the block it could not decode by its block indices ("IReadBlock failed at X offset 3, Y offset 1")
_BLOCK = re.compile(r"IReadBlock failed at X offset (\d+), Y offset (\d+)")


def gdal_cause(e: BaseException) -> str:
    """GDAL's own words for a failed call, from rasterio's exception chain: the innermost message (what
    went wrong: ``ZIPDecode: Decoding error ...``) first, then the outer ones that add something, each once;
    rasterio's ``Read failed. See previous exception for details.`` left out."""
    msgs: list[str] = []
    seen: set[int] = set()
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        m = " ".join(str(e).split())
        if m and "See previous exception" not in m and m not in msgs:
            msgs.append(m)
        e = e.__cause__ or e.__context__
    inner = [m.split(": ", 1)[1] if _BLOCK.search(m) and ": " in m else m for m in reversed(msgs)]
    out: list[str] = []
    for m in inner:
        m = _BLOCK.sub("", m).strip(" :")
        if m and not any(m in o for o in out):
            out.append(m)
    return "; ".join(out) or type(e).__name__


def read_failure(src: DatasetReader, b: int, pixel_window: tuple[int, int, int, int], e: BaseException) -> str:
    """The message for a read of ``pixel_window`` (row_off, col_off, height, width) of band ``b`` that GDAL
    could not do: the file, the band, the file block GDAL names (its pixel rows and columns) or else the
    window, and GDAL's cause (:func:`gdal_cause`)."""
    r0, c0, h, w = pixel_window
    where = f"rows {r0}..{r0 + h - 1}, columns {c0}..{c0 + w - 1}"
    found = [mm for x in _chain(e) for mm in [_BLOCK.search(str(x))] if mm]
    if found:
        bx, by = int(found[0].group(1)), int(found[0].group(2))
        bh, bw = src.block_shapes[b - 1]
        where = (f"block (row {by}, col {bx}) of {bh} x {bw} pixels: rows {by * bh}.."
                 f"{min((by + 1) * bh, src.height) - 1}, columns {bx * bw}..{min((bx + 1) * bw, src.width) - 1}")
    return f"path: {src.name}: band {b}, {where}: cannot be read: {gdal_cause(e)}"


def _chain(e: BaseException | None) -> list[BaseException]:
    out: list[BaseException] = []
    while e is not None and e not in out:
        out.append(e)
        e = e.__cause__ or e.__context__
    return out


# -- no-data -----------------------------------------------------------------------------------------
def _no_data(src: DatasetReader, b: int, raw: np.ndarray, win: Window, k: int,
             dtype: np.dtype) -> tuple[np.ndarray, float | None]:
    """(holes (n, m) bool, the nodata value in effect): the band's nodata value, else its mask band, and
    NaN in a float band."""
    from rasterio.enums import MaskFlags, Resampling  # lazy: heavy optional dependency

    nodata = src.nodatavals[b - 1]
    if nodata is not None and not np.issubdtype(dtype, np.floating) and not math.isfinite(nodata):
        nodata = None  # a NaN/inf nodata tag on an integer band matches no cell
    if nodata is not None:
        nd = np.asarray(nodata).astype(dtype)
        holes = np.isnan(raw) if np.isnan(nd) else (raw == nd)
    elif MaskFlags.all_valid not in src.mask_flag_enums[b - 1]:  # a mask band or alpha
        mk = src.read_masks(b, window=win, out_shape=raw.shape, resampling=Resampling.nearest) if k > 1 \
            else src.read_masks(b, window=win)
        holes = mk == 0
    else:
        holes = np.zeros(raw.shape, dtype=bool)
    if np.issubdtype(dtype, np.floating):
        holes |= np.isnan(raw)
    return holes, nodata


def _decode(part: _Part) -> tuple[np.ndarray, float, list[str]]:
    """(heights float64 metres with NaN holes, the vertical unit's length in metres, notes)."""
    unit = part.unit
    vf = _VERTICAL_UNITS.get(unit.lower(), 1.0)
    notes: list[str] = []
    if unit and unit.lower() not in _VERTICAL_UNITS:
        notes.append(f"unknown vertical unit {unit!r}: values taken as metres")
    with np.errstate(invalid="ignore"):  # a float band's signalling NaNs are no-data holes like the others
        h64 = (part.raw.astype(np.float64) * part.scale + part.offset) * vf
    h64[part.holes] = np.nan
    return h64, vf, notes


# -- spacing -----------------------------------------------------------------------------------------
def _spacing(part: _Part, p: Path, dx: float | None, dz: float | None) -> tuple[float, float, dict[str, Any]]:
    """(dx, dz) in metres and the meta that says how they were found (``meta["spacing_note"]``)."""
    tw, crs = part.transform, part.crs
    px, py = abs(tw.a), abs(tw.e)  # CRS units per sample
    meta: dict[str, Any] = {}
    if crs is not None and crs.is_geographic:
        sdx, sdz, how = _geographic_spacing(part, p, meta)
    elif crs is not None:
        kind = "projected" if crs.is_projected else "local"  # a local (engineering) CRS: its own unit, no projection
        try:
            lu, lf = crs.linear_units_factor if crs.is_projected else crs.units_factor
        except Exception as e:  # noqa: BLE001 - rasterio raises CRSError for unknown units
            raise ValueError(f"path: {p}: cannot tell the linear unit of its CRS {crs.to_string()!r}; "
                             "pass dx and dz in metres") from e
        sdx, sdz = px * lf, py * lf
        meta.update(crs_kind=kind, linear_unit=lu, linear_unit_m=lf)
        how = (f"projected CRS: {px:.6g} x {py:.6g} {lu} (x {lf:.12g} m) grid metres; the "
               "projection's scale factor is not applied") if kind == "projected" else \
            f"local CRS: {px:.6g} x {py:.6g} {lu} (x {lf:.12g} m)"
    elif part.georef:
        sdx, sdz = px, py
        meta.update(crs_kind="none")
        how = f"no CRS: the pixel size {px:.6g} x {py:.6g} taken as metres"
    else:
        sdx, sdz = 1.0, 1.0
        meta.update(crs_kind="none")
        how = "no georeferencing: spacing 1 m"
    if dx is not None or dz is not None:  # as in Heightmap.load: dz defaults to dx
        sdx = check_number("dx", dx, 0.0, lo_open=True) if dx is not None else sdx
        sdz = check_number("dz", dz, 0.0, lo_open=True) if dz is not None else sdx if dx is not None else sdz
        how += f"; overridden by the caller to dx={sdx:.6g}, dz={sdz:.6g} m"
    meta["spacing_note"] = how
    return sdx, sdz, meta



def _geographic_spacing(part: _Part, p: Path, meta: dict[str, Any]) -> tuple[float, float, str]:
    """A geographic CRS's pixel size in degrees converted to metres at the latitude of the centre of the
    part read, on the CRS's own ellipsoid; adds what it used to ``meta``."""
    tw, crs = part.transform, part.crs
    n = part.raw.shape[0]
    px, py = abs(tw.a), abs(tw.e)
    ell = _ellipsoid(crs)
    to_deg = crs.units_factor[1] * 180.0 / math.pi  # CRS angular unit -> degrees
    f = 1.0 / ell["inv_f"] if ell["inv_f"] else 0.0
    lat = (tw.f + tw.e * n / 2.0) * to_deg
    if not -90.0 < lat < 90.0:
        raise ValueError(f"path: {p}: the centre latitude {lat} deg is outside (-90, 90)")
    mlon, mlat = metres_per_degree(lat, a=ell["a"], f=f)
    sdx, sdz = px * to_deg * mlon, py * to_deg * mlat
    lat_n = max(min(tw.f * to_deg, 89.999999), -89.999999)
    lat_s = max(min((tw.f + tw.e * n) * to_deg, 89.999999), -89.999999)
    var = [metres_per_degree(v, a=ell["a"], f=f)[0] / mlon for v in (lat_n, lat_s)]
    meta.update(crs_kind="geographic", latitude_deg=lat, ellipsoid=ell, spacing_deg=[px * to_deg, py * to_deg],
                dx_variation=[min(var), max(var)])
    how = (f"geographic CRS: {px * to_deg:.6g} x {py * to_deg:.6g} deg converted at the centre "
           f"latitude {lat:.5f} deg on the {ell['name']} ellipsoid (a={ell['a']:.3f} m, "
           f"1/f={ell['inv_f']:.12g}); the true east-west spacing varies from "
           f"{min(var) * sdx:.4g} to {max(var) * sdx:.4g} m across the rows")
    return sdx, sdz, how


# -- orientation -------------------------------------------------------------------------------------
def _orient(h64: np.ndarray, part: _Part) -> tuple[np.ndarray, bool, bool, tuple[float, float]]:
    """Row 0 north, column 0 west: (heights, rows flipped, columns mirrored, CRS coordinates of the centre
    of the sample that becomes (0, 0))."""
    tw = part.transform
    n, m = h64.shape
    flip_rows = part.georef and tw.e > 0
    flip_cols = part.georef and tw.a < 0
    if flip_rows:
        h64 = h64[::-1]
    if flip_cols:
        h64 = h64[:, ::-1]
    i00 = n - 1 if flip_rows else 0
    j00 = m - 1 if flip_cols else 0
    return h64, flip_rows, flip_cols, (tw.c + tw.a * (j00 + 0.5), tw.f + tw.e * (i00 + 0.5))


def describe(hm: HeightGrid) -> str:
    """One paragraph saying what was read and every assumption made (for the CLI and reports)."""
    mt = hm.meta
    H, W = hm.heights.shape
    parts = [f"{mt.get('source', hm.name)}: {H} x {W} samples"]
    if mt.get("band_count") is not None:
        parts[0] += (f" from band {mt['band']} of {mt['band_count']} ({mt.get('driver')}, "
                     f"{mt.get('source_dtype')})")
    rs = mt.get("raster_shape")
    win = mt.get("window")
    if rs and win and (win != [0, 0, rs[0], rs[1]] or mt.get("decimate", 1) > 1):
        parts.append(f"window rows {win[0]}..{win[0] + win[2]}, columns {win[1]}..{win[1] + win[3]} of "
                     f"{rs[0]} x {rs[1]}" + (f", decimated {mt['decimate']}x by {mt['resampling']}"
                                             if mt.get("decimate", 1) > 1 else ""))
    parts.append(f"CRS {mt.get('crs_name') or 'none'}")
    if "spacing_note" in mt:
        parts.append(f"spacing dx={hm.dx:.6g} m, dz={hm.dz:.6g} m ({mt['spacing_note']})")
    else:
        parts.append(f"spacing dx={hm.dx:.6g} m, dz={hm.dz:.6g} m")
    if mt.get("scale", 1.0) != 1.0 or mt.get("offset", 0.0) != 0.0:
        parts.append(f"heights = raw x {mt['scale']:.9g} + {mt['offset']:.9g}")
    if mt.get("vertical_unit"):
        parts.append(f"vertical unit {mt['vertical_unit']!r} (x {mt.get('vertical_unit_m', 1.0):.9g} m)")
    parts.append(f"{mt.get('nodata_count', int(np.isnan(hm.heights).sum()))} no-data cells as NaN holes"
                 + (f" (nodata value {mt['nodata']:.9g})" if mt.get("nodata") is not None else ""))
    flips = [s for s, on in (("rows flipped (the file is south-up)", mt.get("flipped_rows")),
                             ("columns mirrored (the file runs east to west)", mt.get("flipped_cols"))) if on]
    parts.append("; ".join(flips) if flips
                 else "north-up as stored: row i along +z (south), column j along +x (east)")
    if "sample00_crs" in mt:
        parts.append(f"world (0, 0) is the sample centred at CRS ({mt['sample00_crs'][0]:.10g}, "
                     f"{mt['sample00_crs'][1]:.10g})")
    finite = hm.heights[np.isfinite(hm.heights)]
    parts.append(f"heights {float(finite.min()):.6g}..{float(finite.max()):.6g} m")
    parts.extend(mt.get("notes", []))
    return "; ".join(parts) + "."


# -- writing ---------------------------------------------------------------------------------------
def is_georeferenced(meta: dict) -> bool:
    """True when ``meta`` came from :func:`read_geotiff` (it holds a transform to write back)."""
    return isinstance(meta, dict) and "transform" in meta and "crs" in meta


def _encode(h: np.ndarray, dtype: np.dtype, scale: float, offset: float, vf: float,
            nodata: float | None) -> np.ndarray | None:
    """Raw values of ``dtype`` whose decoding (as :func:`read_geotiff` does it) gives back ``h`` bit for
    bit, or None when there are none."""
    holes = np.isnan(h)
    if holes.any() and nodata is None and not np.issubdtype(dtype, np.floating):
        return None
    raw64 = (h.astype(np.float64) / vf - offset) / scale
    if np.issubdtype(dtype, np.integer):
        info = np.iinfo(dtype)
        raw64 = np.round(raw64)
        fin = ~holes
        if fin.any() and (raw64[fin].min() < info.min or raw64[fin].max() > info.max):
            return None
    with np.errstate(invalid="ignore"):
        raw = np.where(holes, 0, raw64).astype(dtype)
    back = ((raw.astype(np.float64) * scale + offset) * vf).astype(np.float32)
    ok = np.array_equal(back[~holes], h[~holes])
    if nodata is not None:
        nd = np.asarray(nodata).astype(dtype)
        raw = np.where(holes, nd, raw).astype(dtype)
        if not (np.isnan(nd) if np.issubdtype(dtype, np.floating) else False):
            ok = ok and not np.any(raw[~holes] == nd)  # a real height must not read back as no-data
    elif holes.any():
        raw = np.where(holes, np.nan, raw).astype(dtype)
    return raw if ok else None


def write_geotiff(hm: HeightGrid, path: str | os.PathLike) -> Path:
    """Write ``hm`` as a single-band GeoTIFF with the CRS, transform, nodata, scale/offset, unit and dtype
    it was read with (``hm.meta`` from :func:`read_geotiff`), in the file's original row/column order.

    Heights that the source dtype cannot hold exactly (edited heightmaps) are written as float32 metres
    (scale 1, offset 0), nodata NaN where there are holes. Written to a temporary name, then renamed.
    """
    rasterio = _rasterio()
    from affine import Affine  # lazy: heavy optional dependency (with rasterio)

    mt = hm.meta
    if not is_georeferenced(mt):
        raise ValueError("hm: its meta holds no georeferencing (not read by read_geotiff)")
    p = Path(path)
    shape = tuple(int(s) for s in hm.heights.shape)
    H, W = shape
    win = mt.get("window")
    if win is not None and (H, W) != (win[2] // mt.get("decimate", 1), win[3] // mt.get("decimate", 1)):
        raise ValueError(f"hm: shape {shape} differs from the {win[2] // mt.get('decimate', 1)} x "
                         f"{win[3] // mt.get('decimate', 1)} raster its georeferencing describes; build a "
                         "Heightmap without that meta to save it as a plain TIFF")
    h = hm.heights
    if mt.get("flipped_rows"):
        h = h[::-1]
    if mt.get("flipped_cols"):
        h = h[:, ::-1]
    h = np.ascontiguousarray(h)
    dtype = np.dtype(mt.get("source_dtype", "float32"))
    if str(dtype) not in _SAVE_DTYPES:
        dtype = np.dtype(np.float32)
    scale, offset = float(mt.get("scale", 1.0)), float(mt.get("offset", 0.0))
    vf = float(mt.get("vertical_unit_m", 1.0))
    unit = mt.get("vertical_unit")
    nodata = mt.get("nodata")
    raw = _encode(h, dtype, scale, offset, vf, nodata)
    if raw is None:  # fall back to float32 metres
        dtype, scale, offset, vf, unit = np.dtype(np.float32), 1.0, 0.0, 1.0, "m"
        if np.isnan(h).any() and (nodata is None or not np.isfinite(np.float32(nodata))
                                  or np.any(h == np.float32(nodata))):
            nodata = float("nan")
        raw = _encode(h, dtype, scale, offset, vf, nodata)
        assert raw is not None
    profile = dict(driver="GTiff", width=W, height=H, count=1, dtype=str(dtype),
                   crs=rasterio.crs.CRS.from_wkt(mt["crs"]) if mt.get("crs") else None,
                   transform=Affine(*mt["transform"]), nodata=nodata, compress="deflate",
                   BIGTIFF="IF_SAFER")
    if H >= 512 and W >= 512:
        profile.update(tiled=True, blockxsize=256, blockysize=256)
    with atomic_path(p) as tmp:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
            with rasterio.open(tmp, "w", **profile) as dst:
                dst.write(raw, 1)
                if scale != 1.0 or offset != 0.0:
                    dst.scales = (scale,)
                    dst.offsets = (offset,)
                if unit:
                    dst.units = (unit,)
    return p


def write_tiled(path: str | os.PathLike, shape: tuple[int, int], read: Callable[[int, int, int, int], np.ndarray], *,
                dx: float = 1.0, dz: float | None = None, origin: tuple[float, float] = (0.0, 0.0),
                crs: str = "EPSG:3857", block: int = 256, overviews: tuple[int, ...] = (2, 4, 8, 16),
                progress: Callable[[int], None] | None = None) -> Path:
    """Write a float32 heightmap larger than memory as a tiled, deflate-compressed GeoTIFF (a cloud-optimised
    layout: internal tiles of ``block`` samples, and GDAL overviews), one band of tiles at a time.

    Args:
        shape: (rows, cols); row 0 is the northern row (the file is north-up, +z is south).
        read: ``read(r0, c0, rows, cols)`` -> float32 heights of that window (e.g. a tile source's).
        dx, dz: spacing in metres (a projected CRS in metres, so :func:`read_geotiff` finds it again).
        origin: CRS (x, y) of the centre of the north-western cell (:meth:`terrainwarp.Heightmap.load` puts
            that sample at world (0, 0) whatever it is).
        overviews: GDAL overview factors built after the data (nearest); () for none.
        progress: called with the rows written, band by band.
    """
    rasterio = _rasterio()
    from affine import Affine  # lazy: heavy optional dependency (with rasterio)
    from rasterio.enums import Resampling  # lazy: heavy optional dependency
    from rasterio.windows import Window

    h, w = (int(v) for v in shape)
    dz = dx if dz is None else dz
    p = Path(path)
    x0, y0 = origin  # north-up: rows go down the CRS's y axis
    profile = dict(driver="GTiff", width=w, height=h, count=1, dtype="float32", crs=rasterio.crs.CRS.from_string(crs),
                   transform=Affine(dx, 0.0, x0 - dx / 2.0, 0.0, -dz, y0 + dz / 2.0), nodata=None,
                   compress="deflate", tiled=True, blockxsize=block, blockysize=block, BIGTIFF="IF_SAFER")
    with atomic_path(p) as tmp:
        with rasterio.open(tmp, "w", **profile) as dst:
            for r0 in range(0, h, block):
                rows = min(block, h - r0)
                for c0 in range(0, w, 8 * block):
                    cols = min(8 * block, w - c0)
                    dst.write(np.ascontiguousarray(read(r0, c0, rows, cols), np.float32), 1,
                              window=Window(c0, r0, cols, rows))
                if progress is not None:
                    progress(rows)
            if overviews:
                dst.build_overviews(list(overviews), Resampling.nearest)
                dst.update_tags(ns="rio_overview", resampling="nearest")
    return p

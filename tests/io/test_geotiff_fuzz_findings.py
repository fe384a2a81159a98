"""What the fuzz suite (tests/fuzz_runner.py, issue 31) found in the GeoTIFF and tile loaders, each kept as a
small input made here: a corrupt tile, a damaged block layout, a non-finite geotransform, spacing overrides
that are not numbers, a signalling NaN, a step of 0, fBm parameters that hang or are not what they say; and
one seen while fixing them (a complex band read as real)."""

from __future__ import annotations

import math
import struct
import warnings

import numpy as np
import pytest
import rasterio
from affine import Affine

from terrainwarp import Heightmap
from terrainwarp.heightmap import StreamedHeightmap
from terrainwarp.io.geotiff import check_tiff_layout
from terrainwarp.io.tiles import ArraySource, FbmSource, TileCache
from terrainwarp.kernels.noise import MAX_OCTAVES


def from_origin(west, north, xsize, ysize):
    """rasterio.transform.from_origin without its deprecated Affine * Affine."""
    return Affine(xsize, 0.0, west, 0.0, -ysize, north)


def _geotiff(path, a, **profile):
    with rasterio.open(path, "w", driver="GTiff", width=a.shape[1], height=a.shape[0], count=1, dtype=str(a.dtype),
                       **{"crs": "EPSG:32617", "transform": from_origin(500000, 4e6, 30, 30), **profile}) as d:
        d.write(a, 1)
    return path


def _ifd(b: bytes) -> list[tuple[int, int, int, int]]:
    """(entry offset, tag, type, value offset) of the first IFD of a little-endian classic TIFF."""
    assert b[:4] == b"II*\x00"
    ifd = struct.unpack("<I", b[4:8])[0]
    n = struct.unpack("<H", b[ifd:ifd + 2])[0]
    out = []
    for k in range(n):
        at = ifd + 2 + 12 * k
        tag, typ, count = struct.unpack("<HHI", b[at:at + 8])
        size = {1: 1, 2: 1, 3: 2, 4: 4, 12: 8}.get(typ, 1) * count
        out.append((at, tag, typ, at + 8 if size <= 4 else struct.unpack("<I", b[at + 8:at + 12])[0]))
    return out


def _rename_tags(path, renames: dict[int, int]) -> None:
    """Give IFD entries another tag number (the way a damaged directory loses or gains a field)."""
    b = bytearray(path.read_bytes())
    for at, tag, _, _ in _ifd(bytes(b)):
        if tag in renames:
            b[at:at + 2] = struct.pack("<H", renames[tag])
    path.write_bytes(bytes(b))


def _corrupt_block(path, row: int, col: int) -> None:
    """Overwrite the compressed bytes of one block (GDAL's BLOCK_OFFSET_<col>_<row> item says where)."""
    with rasterio.open(path) as s:
        off = int(s.get_tag_item(f"BLOCK_OFFSET_{col}_{row}", "TIFF", bidx=1))
        size = int(s.get_tag_item(f"BLOCK_SIZE_{col}_{row}", "TIFF", bidx=1))
    b = bytearray(path.read_bytes())
    b[off:off + size] = b"\xff" * size
    path.write_bytes(bytes(b))


# -- a corrupt block: the file, the band, the block and GDAL's cause, never "Read failed" ---------------------
def test_a_corrupt_block_names_the_file_the_block_and_gdals_cause(tmp_path):
    a = (np.random.default_rng(0).random((64, 64)) * 100).astype(np.float32)
    p = _geotiff(tmp_path / "dem.tif", a, tiled=True, blockxsize=16, blockysize=16, compress="deflate")
    _corrupt_block(p, 1, 3)
    block = (r"band 1, block \(row 1, col 3\) of 16 x 16 pixels: rows 16\.\.31, columns 48\.\.63: cannot be read: "
             r"ZIPDecode")
    with pytest.raises(ValueError, match=rf"^path: .*dem\.tif: {block}") as e:
        Heightmap.load(p)
    assert "previous exception" not in str(e.value)
    # the streamed path: the tile that needed the block, the file once, the same block and cause
    with pytest.raises(ValueError, match=rf"^tile \(step 1, row 0, col 0: samples 0\.\.63 x 0\.\.63\) of .*dem\.tif: "
                                         rf"{block}") as e:
        Heightmap.open(p).load()
    assert str(e.value).count("dem.tif") == 1 and "previous exception" not in str(e.value)
    # a window clear of the block still reads
    assert Heightmap.load(p, window=((0, 16), (0, 48))).shape == (16, 48)


# -- a damaged block layout: libtiff would guess, GDAL would return uninitialised memory ----------------------
def test_tile_offsets_without_tile_sizes_are_refused_not_read_as_garbage(tmp_path):
    # fuzz finding: a 40 x 300 tiled deflate GeoTIFF whose TileWidth/TileLength entries were lost read as one
    # strip, with heights that differed from run to run (GDAL 3.10, rasterio 1.4.4)
    a = (np.random.default_rng(1).random((40, 300)) * 100).astype(np.float32)
    p = _geotiff(tmp_path / "lost.tif", a, tiled=True, blockxsize=256, blockysize=256, compress="deflate")
    _rename_tags(p, {322: 65000, 323: 65001})
    msg = r"lost\.tif is damaged: its first image is striped .* but holds TileOffsets, TileByteCounts"
    with pytest.raises(ValueError, match=msg):
        Heightmap.load(p)
    with pytest.raises(ValueError, match=msg):
        Heightmap.open(p)


def test_strip_offsets_beside_tile_sizes_and_a_plain_tiff_are_refused_too(tmp_path):
    a = (np.random.default_rng(2).random((40, 40)) * 100).astype(np.float32)
    p = _geotiff(tmp_path / "mixed.tif", a, tiled=True, blockxsize=16, blockysize=16)
    _rename_tags(p, {324: 273})  # TileOffsets become StripOffsets
    with pytest.raises(ValueError, match=r"mixed\.tif is damaged: its first image is tiled .* holds StripOffsets"):
        Heightmap.load(p)
    # a TIFF without georeferencing goes to OpenImageIO, which decodes the tile as a strip: the same check
    q = tmp_path / "plain.tif"
    with warnings.catch_warnings():  # deliberately no georeferencing
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        d = rasterio.open(q, "w", driver="GTiff", width=300, height=40, count=1, dtype="float32", tiled=True,
                          blockxsize=256, blockysize=256)
    with d:
        d.write((np.random.default_rng(3).random((40, 300)) * 100).astype(np.float32), 1)
    check_tiff_layout(q)  # whole: passes
    _rename_tags(q, {322: 65000, 323: 65001})
    with pytest.raises(ValueError, match=r"plain\.tif is damaged"):
        Heightmap.load(q)


def test_layout_check_passes_valid_tiffs_and_other_files(tmp_path):
    a = np.zeros((20, 20), np.float32)
    for kw in ({}, {"tiled": True, "blockxsize": 16, "blockysize": 16}, {"BIGTIFF": "YES"}):
        check_tiff_layout(_geotiff(tmp_path / "ok.tif", a, **kw))
    (tmp_path / "x.npy").write_bytes(b"\x93NUMPY")
    (tmp_path / "short.tif").write_bytes(b"II*\x00\x08")
    check_tiff_layout(tmp_path / "x.npy")
    check_tiff_layout(tmp_path / "short.tif")  # its reader reports what is wrong


# -- georeferencing that cannot be used --------------------------------------------------------------------
@pytest.mark.parametrize("t", [Affine(math.inf, 0, 0, 0, -1, 0), Affine(math.nan, 0, 0, 0, -1, 0),
                               Affine(30, 0, math.nan, 0, -30, 0)])
def test_a_non_finite_geotransform_is_refused_naming_the_file(tmp_path, t):
    # fuzz finding: an infinite pixel scale gave "dx: expected a positive finite number of metres, got inf",
    # blaming an argument the caller never gave; Heightmap.open accepted it (dz = nan)
    p = _geotiff(tmp_path / "inf.tif", np.ones((8, 8), np.float32), transform=t)
    for read in (Heightmap.load, Heightmap.open):
        with pytest.raises(ValueError, match=r"^path: .*inf\.tif has a degenerate geotransform"):
            read(p)


def test_bounds_far_outside_a_tiny_pixel_size_read_what_they_cover(tmp_path):
    # fuzz finding: bounds on a raster whose pixel size is 1e-300 became infinite pixel coordinates, and
    # math.floor raised OverflowError ("cannot convert float infinity to integer")
    p = _geotiff(tmp_path / "tiny.tif", np.ones((8, 8), np.float32), transform=Affine(1e-300, 0, 0, 0, -1e-300, 0))
    assert Heightmap.load(p, bounds=(-1e10, -1e10, 1e10, 1e10)).shape == (8, 8)  # they hold the whole raster
    assert Heightmap.load(p, bounds=(0, -4e-300, 4e-300, 0)).shape == (4, 4)
    with pytest.raises(ValueError, match=r"^bounds: .* does not overlap the raster"):
        Heightmap.load(p, bounds=(1e10, 1e10, 2e10, 2e10))


@pytest.mark.parametrize("unit, metres", [("metre", 1.0), ("US survey foot", 1200.0 / 3937.0)])
def test_a_local_crs_gives_spacing_in_its_own_unit(tmp_path, unit, metres):
    # fuzz finding: mutated GeoKeys turned a UTM CRS into LOCAL_CS["...", UNIT["metre", 1]], which was refused:
    # "cannot tell the linear unit of its CRS" (rasterio defines linear_units_factor for projected CRSs only)
    from rasterio.crs import CRS

    wkt = f'LOCAL_CS["site",UNIT["{unit}",{metres!r}],AXIS["Easting",EAST],AXIS["Northing",NORTH]]'
    p = _geotiff(tmp_path / "site.tif", np.ones((4, 4), np.float32), crs=CRS.from_wkt(wkt),
                 transform=from_origin(0, 40, 10, 10))
    hm = Heightmap.load(p)
    assert hm.dx == pytest.approx(10 * metres, rel=1e-12) and hm.dz == pytest.approx(10 * metres, rel=1e-12)
    assert hm.meta["crs_kind"] == "local" and hm.meta["linear_unit"] == unit
    assert Heightmap.open(p).dx == hm.dx


@pytest.mark.parametrize("dx, kind", [(math.nan, ValueError), (-3.0, ValueError), (0, ValueError),
                                      ("30", TypeError), (True, TypeError)])
def test_spacing_overrides_are_numbers_for_load_and_open(tmp_path, dx, kind):
    # fuzz finding: Heightmap.open(p, dz=nan) gave a heightmap with dz = nan; "30" became 30.0
    p = _geotiff(tmp_path / "dem.tif", np.ones((8, 8), np.float32))
    for read in (Heightmap.load, Heightmap.open):
        with pytest.raises(kind, match=r"^dx: expected"):
            read(p, dx=dx)
        with pytest.raises(kind, match=r"^dz: expected"):
            read(p, 10.0, dx)
    assert Heightmap.open(p, dz=7.0).dz == 7.0 and Heightmap.open(p, dz=7.0).dx == 30.0


def test_a_complex_band_is_refused(tmp_path):
    # seen while fixing the above: a complex64 band was decoded as its real part (numpy's ComplexWarning)
    p = _geotiff(tmp_path / "cx.tif", np.ones((8, 8), np.complex64))
    with pytest.raises(ValueError, match=r"^path: band 1 of .*cx\.tif holds complex64 values"):
        Heightmap.load(p)
    with pytest.raises(ValueError, match=r"holds complex64 values"):
        Heightmap.open(p)


def test_a_signalling_nan_is_a_hole_without_a_warning(tmp_path):
    a = np.ones((4, 4), np.float32)
    a.view(np.uint32)[1, 2] = 0x7F800001  # a signalling NaN: casting it raised "invalid value encountered"
    p = _geotiff(tmp_path / "snan.tif", a)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        hm = Heightmap.load(p)
    assert np.isnan(hm.heights[1, 2]) and int(np.isnan(hm.heights).sum()) == 1


# -- tiles and procedural sources ----------------------------------------------------------------------------
def test_a_window_at_step_zero_is_refused():
    # fuzz finding: StreamedHeightmap.window(0, ...) raised ZeroDivisionError from level_shape
    tiles = TileCache(ArraySource(np.zeros((9, 9), np.float32)))
    with pytest.raises(ValueError, match=r"^step: expected an integer >= 1, got 0"):
        tiles.window(0, 0, 0, 1, 1)
    with pytest.raises(TypeError, match=r"^step: expected an integer"):
        tiles.window(1.5, 0, 0, 1, 1)
    s = StreamedHeightmap.of(Heightmap.from_array(np.zeros((9, 9), np.float32)))
    with pytest.raises(TypeError, match=r"^r0: expected an integer, got 1.5"):
        s.window(1, 1.5, 0, 2, 2)


def test_fbm_parameters_that_hang_or_are_not_numbers_are_refused():
    # fuzz finding: [heightmap.fbm] octaves = 16777217 with stream = true ran for minutes (a hang)
    with pytest.raises(ValueError, match=rf"^octaves: expected an integer >= 1 and <= {MAX_OCTAVES}"):
        FbmSource(65, octaves=2**24 + 1)
    for kw, kind, name in ((dict(seed="x"), TypeError, "seed"), (dict(seed=1.5), TypeError, "seed"),
                           (dict(ridged="yes"), TypeError, "ridged"), (dict(gain=math.nan), ValueError, "gain")):
        for make in (FbmSource, Heightmap.fbm):
            with pytest.raises(kind, match=rf"^{name}: expected"):
                make(17, **kw)
    assert FbmSource(17, octaves=MAX_OCTAVES).octaves == MAX_OCTAVES
    # fuzz finding: gain = 1e300 is finite in float64 but the kernel's float32 amplitudes overflow: every height
    # came out NaN ("a: 561 NaN heights"); so did a lacunarity whose finest octave overflows the coordinates
    for kw, name in ((dict(gain=1e300), "gain"), (dict(gain=1e5, octaves=9), "gain"),
                     (dict(lacunarity=1e30, octaves=3), "lacunarity")):
        for make in (FbmSource, Heightmap.fbm):
            with pytest.raises(ValueError, match=rf"^{name}: .* overflows the kernel's float32"):
                make(17, **kw)
    h = Heightmap.fbm(17, gain=1e4, octaves=9, lacunarity=1e3).heights  # just inside: finite heights
    assert np.isfinite(h).all()

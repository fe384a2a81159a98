"""GeoTIFF / GDAL rasters through rasterio: heights, metre spacing, orientation, no-data, windows, round
trips.

Every file is built here with rasterio in tmp_path. Spacing references are float64 ECEF chord lengths
between neighbouring sample centres on the CRS's ellipsoid (independent of metres_per_degree; over one
pixel the chord and the arc differ by a relative (d/R)^2/24 < 1e-11).
"""

import math

import numpy as np
import pytest
import rasterio
from affine import Affine
from conftest import digest
from rasterio.transform import from_origin
from rasterio.windows import Window

from terrainwarp import Heightmap
from terrainwarp.io.geotiff import describe, is_gdal_raster, read_geotiff
from terrainwarp.scene import Scene

# rasterio 1.4 composes affine transforms with `*`, which affine 3 marks as pending deprecation
pytestmark = pytest.mark.filterwarnings("ignore:Use `@` matmul:PendingDeprecationWarning")


def _write(path, a, crs, transform, nodata=None, scale=None, offset=None, units=None):
    with rasterio.open(path, "w", driver="GTiff", width=a.shape[1], height=a.shape[0], count=1,
                       dtype=str(a.dtype), crs=crs, transform=transform, nodata=nodata) as d:
        d.write(a, 1)
        if scale is not None:
            d.scales = (scale,)
            d.offsets = (offset,)
        if units is not None:
            d.units = (units,)
    return path


def _ecef(lat_deg, lon_deg, a, f):
    e2 = f * (2.0 - f)
    p, l = math.radians(lat_deg), math.radians(lon_deg)
    n = a / math.sqrt(1.0 - e2 * math.sin(p) ** 2)
    return np.array([n * math.cos(p) * math.cos(l), n * math.cos(p) * math.sin(l),
                     n * (1.0 - e2) * math.sin(p)])


def _chord(lat1, lon1, lat2, lon2, a=6378137.0, f=1.0 / 298.257223563):
    return float(np.linalg.norm(_ecef(lat1, lon1, a, f) - _ecef(lat2, lon2, a, f)))


def _dem(shape, dtype, seed=0):
    rng = np.random.default_rng(seed)
    if np.dtype(dtype) == np.float32:
        return (rng.standard_normal(shape) * 700.0 + 1200.0).astype(np.float32)
    info = np.iinfo(dtype)
    return rng.integers(max(info.min, -500), min(info.max, 9000), size=shape).astype(dtype)


# -- heights, spacing, orientation ----------------------------------------------------------------
def test_utm_north_up_float32_with_nodata(tmp_path):
    a = _dem((20, 24), np.float32)
    a[3, 4] = a[10, 0] = a[19, 23] = -9999.0
    p = _write(tmp_path / "utm.tif", a, "EPSG:32633", from_origin(500000.0, 5000000.0, 30.0, 30.0),
               nodata=-9999.0)
    assert is_gdal_raster(p)
    hm = Heightmap.load(p)
    holes = a == -9999.0
    assert np.array_equal(np.isnan(hm.heights), holes)
    assert hm.meta["nodata_count"] == 3
    np.testing.assert_array_equal(hm.heights[~holes], a[~holes])
    assert (hm.dx, hm.dz) == (30.0, 30.0)
    assert hm.meta["crs_kind"] == "projected" and "32633" in hm.meta["crs_name"]
    assert hm.meta["flipped_rows"] is False
    assert hm.meta["sample00_crs"] == [500015.0, 4999985.0]  # north-west sample's centre
    s = hm.meta["summary"]
    assert "3 no-data" in s and "EPSG:32633" in s and "dx=30 m" in s and s == describe(hm)


def test_south_up_is_flipped_and_reported(tmp_path):
    a = _dem((9, 7), np.int16, seed=1)
    # positive y pixel size: row 0 is the southern row
    p = _write(tmp_path / "s.tif", a, "EPSG:32610", Affine(10.0, 0.0, 400000.0, 0.0, 10.0, 4100000.0))
    hm = Heightmap.load(p)
    np.testing.assert_array_equal(hm.heights, a[::-1].astype(np.float32))  # row 0 now the northern row
    assert hm.meta["flipped_rows"] is True and "south-up" in hm.meta["summary"]
    assert hm.meta["sample00_crs"] == [400005.0, 4100000.0 + 8.5 * 10.0]
    # the north-up equivalent file reads identically
    q = _write(tmp_path / "n.tif", a[::-1].copy(), "EPSG:32610", from_origin(400000.0, 4100090.0, 10.0, 10.0))
    hn = Heightmap.load(q)
    assert hn.meta["flipped_rows"] is False
    assert digest(hn.heights) == digest(hm.heights)


def test_east_to_west_columns_are_mirrored(tmp_path):
    a = _dem((5, 6), np.float32, seed=2)
    p = _write(tmp_path / "ew.tif", a, "EPSG:32633", Affine(-5.0, 0.0, 600030.0, 0.0, -5.0, 5000000.0))
    hm = Heightmap.load(p)
    np.testing.assert_array_equal(hm.heights, a[:, ::-1])
    assert hm.meta["flipped_cols"] is True and hm.dx == 5.0


@pytest.mark.parametrize("lat_top, crs, a_f", [
    (47.0, "EPSG:4326", (6378137.0, 1.0 / 298.257223563)),  # WGS84
    (-33.5, "EPSG:4326", (6378137.0, 1.0 / 298.257223563)),  # southern hemisphere
    (70.25, "EPSG:4230", (6378388.0, 1.0 / 297.0)),  # ED50: International 1924 ellipsoid
])
def test_geographic_spacing_matches_ellipsoid_chords(tmp_path, lat_top, crs, a_f):
    d = 1.0 / 3600.0  # 1 arc-second (SRTM / Copernicus GLO-30)
    rows, cols = 40, 50
    a = _dem((rows, cols), np.int16, seed=3)
    p = _write(tmp_path / "geo.tif", a, crs, from_origin(8.0, lat_top, d, d), nodata=-32768)
    hm = Heightmap.load(p)
    lat_c = lat_top - rows * d / 2.0  # centre of the raster
    assert hm.meta["crs_kind"] == "geographic"
    assert hm.meta["latitude_deg"] == pytest.approx(lat_c, abs=1e-12)
    dx_ref = _chord(lat_c, 8.0, lat_c, 8.0 + d, *a_f)
    dz_ref = _chord(lat_c - d / 2, 8.0, lat_c + d / 2, 8.0, *a_f)
    assert hm.dx == pytest.approx(dx_ref, rel=1e-9)
    assert hm.dz == pytest.approx(dz_ref, rel=1e-9)
    assert hm.dx < hm.dz  # dx shrinks with cos(latitude), dz does not
    assert hm.meta["ellipsoid"]["a"] == a_f[0]
    assert f"{lat_c:.5f}" in hm.meta["summary"]
    np.testing.assert_array_equal(hm.heights, a.astype(np.float32))


def test_ed50_spacing_differs_from_wgs84(tmp_path):
    d = 1.0 / 1200.0
    a = _dem((8, 8), np.int16)
    h1 = Heightmap.load(_write(tmp_path / "w.tif", a, "EPSG:4326", from_origin(0.0, 60.0, d, d)))
    h2 = Heightmap.load(_write(tmp_path / "e.tif", a, "EPSG:4230", from_origin(0.0, 60.0, d, d)))
    assert abs(h1.dx / h2.dx - 1.0) > 1e-5  # the ellipsoid is used, not WGS84 for everything


def test_projected_us_feet_and_vertical_feet(tmp_path):
    a = np.arange(12, dtype=np.int16).reshape(3, 4) * 100
    p = _write(tmp_path / "ft.tif", a, "EPSG:2227", from_origin(6000000.0, 2000000.0, 3.0, 3.0), units="ft")
    hm = Heightmap.load(p)
    assert hm.dx == pytest.approx(3.0 * 1200.0 / 3937.0, rel=1e-12)
    assert hm.meta["linear_unit"] == "US survey foot"
    np.testing.assert_allclose(hm.heights, a.astype(np.float64) * 0.3048, rtol=1e-7)
    back = Heightmap.load(hm.save(tmp_path / "ft2.tif"))
    with rasterio.open(tmp_path / "ft2.tif") as src:
        assert np.array_equal(src.read(1), a) and src.units == ("ft",)
    assert back.heights.tobytes() == hm.heights.tobytes()


def test_scale_offset_tags(tmp_path):
    a = np.array([[0, 1, 2], [1000, -1000, 32767]], dtype=np.int16)
    p = _write(tmp_path / "so.tif", a, "EPSG:32633", from_origin(0.0, 100.0, 1.0, 1.0), scale=0.1,
               offset=-50.0)
    hm = Heightmap.load(p)
    np.testing.assert_array_equal(hm.heights, (a.astype(np.float64) * 0.1 - 50.0).astype(np.float32))
    assert "raw x 0.1 + -50" in hm.meta["summary"]
    hm.save(tmp_path / "so2.tif")
    with rasterio.open(tmp_path / "so2.tif") as src:
        assert src.dtypes[0] == "int16" and np.array_equal(src.read(1), a)
        assert src.scales == (0.1,) and src.offsets == (-50.0,)


def test_rotated_transform_refused(tmp_path):
    a = _dem((4, 4), np.float32)
    t = Affine.translation(500000.0, 5000000.0) @ Affine.rotation(15.0) @ Affine.scale(30.0, -30.0)
    p = _write(tmp_path / "rot.tif", a, "EPSG:32633", t)
    with pytest.raises(ValueError, match="rotated or sheared.*gdalwarp"):
        Heightmap.load(p)
    sh = Affine(30.0, 2.0, 500000.0, 0.0, -30.0, 5000000.0)  # shear only
    with pytest.raises(ValueError, match="rotated or sheared"):
        Heightmap.load(_write(tmp_path / "sh.tif", a, "EPSG:32633", sh))


# -- no-data masks ----------------------------------------------------------------------------------
def test_nan_nodata_and_mask_band(tmp_path):
    a = _dem((6, 6), np.float32)
    a[0, :] = np.nan
    hm = Heightmap.load(_write(tmp_path / "nan.tif", a, "EPSG:32633", from_origin(0, 60, 10, 10),
                               nodata=np.nan))
    assert hm.meta["nodata_count"] == 6 and int(np.isnan(hm.heights).sum()) == 6
    b = _dem((6, 6), np.uint16)
    with rasterio.open(tmp_path / "mask.tif", "w", driver="GTiff", width=6, height=6, count=1, dtype="uint16",
                       crs="EPSG:32633", transform=from_origin(0, 60, 10, 10)) as d:
        d.write(b, 1)
        m = np.full((6, 6), 255, np.uint8)
        m[2:4, 2:5] = 0
        d.write_mask(m)
    hm = Heightmap.load(tmp_path / "mask.tif")
    assert hm.meta["nodata_count"] == 6 and np.array_equal(np.isnan(hm.heights), m == 0)


# -- windows and decimation -----------------------------------------------------------------------
def test_pixel_window_and_bounds_read_the_same_part(tmp_path):
    a = _dem((50, 60), np.float32, seed=4)
    t = from_origin(10.0, 47.0, 0.001, 0.001)
    p = _write(tmp_path / "big.tif", a, "EPSG:4326", t)
    hw = Heightmap.load(p, window=((10, 30), (5, 45)))
    np.testing.assert_array_equal(hw.heights, a[10:30, 5:45])
    assert hw.meta["window"] == [10, 5, 20, 40]
    assert hw.meta["latitude_deg"] == pytest.approx(47.0 - 0.001 * 20.0, abs=1e-12)  # the window's centre
    assert hw.meta["sample00_crs"] == pytest.approx([10.0055, 46.9895], abs=1e-12)
    hb = read_geotiff(p, bounds=(10.005, 47.0 - 0.030, 10.045, 47.0 - 0.010))
    assert digest(hb.heights) == digest(hw.heights) and hb.dx == hw.dx
    hr = read_geotiff(p, window=Window(5, 10, 40, 20))
    assert digest(hr.heights) == digest(hw.heights)
    assert "window rows 10..30, columns 5..45 of 50 x 60" in hw.meta["summary"]


@pytest.mark.parametrize("k", [2, 3])
def test_decimation(tmp_path, k):
    a = _dem((31, 44), np.float32, seed=5)
    p = _write(tmp_path / "dec.tif", a, "EPSG:32633", from_origin(0.0, 1000.0, 2.0, 2.0))
    n, m = 31 // k, 44 // k
    avg = Heightmap.load(p, decimate=k)
    ref = a[: n * k, : m * k].astype(np.float64).reshape(n, k, m, k).mean(axis=(1, 3))
    assert avg.shape == (n, m) and (avg.dx, avg.dz) == (2.0 * k, 2.0 * k)
    np.testing.assert_allclose(avg.heights, ref, rtol=0, atol=1e-3)  # float32 sums of k*k values ~1e3
    near = Heightmap.load(p, decimate=k, resampling="nearest")
    np.testing.assert_array_equal(near.heights, a[k // 2::k, k // 2::k][:n, :m])
    # sample (0, 0) sits at the centre of the first k x k block
    assert near.meta["sample00_crs"] == [k * 1.0, 1000.0 - k * 1.0]


def test_decimation_with_overviews_and_nodata(tmp_path):
    a = _dem((64, 64), np.int16, seed=6)
    a[:4, :4] = -32768  # a whole 4x4 block of holes
    p = _write(tmp_path / "ov.tif", a, "EPSG:32633", from_origin(0.0, 640.0, 10.0, 10.0), nodata=-32768)
    from rasterio.enums import Resampling

    with rasterio.open(p, "r+") as d:
        d.build_overviews([4], Resampling.nearest)
    hm = Heightmap.load(p, decimate=4, resampling="nearest")
    assert hm.shape == (16, 16) and hm.dx == 40.0
    assert np.isnan(hm.heights[0, 0]) and hm.meta["nodata_count"] == 1


# -- round trips ----------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [np.int16, np.uint16, np.float32])
@pytest.mark.parametrize("nodata", [False, True])
@pytest.mark.parametrize("south_up", [False, True])
def test_save_round_trip_bit_exact(tmp_path, dtype, nodata, south_up):
    a = _dem((13, 17), dtype, seed=7)
    nd = None
    if nodata:
        nd = {np.int16: -32768, np.uint16: 65535, np.float32: -3.4028234663852886e38}[dtype]
        a[0, 0] = a[5, 9] = nd
    t = Affine(0.5, 0.0, 300000.0, 0.0, 0.5 if south_up else -0.5, 4000000.0)
    src_p = _write(tmp_path / "in.tif", a, "EPSG:32631", t, nodata=nd)
    hm = Heightmap.load(src_p)
    assert hm.meta["nodata_count"] == (2 if nodata else 0)
    out = hm.save(tmp_path / "out.tif")
    with rasterio.open(src_p) as s, rasterio.open(out) as o:
        assert o.dtypes == s.dtypes and o.crs == s.crs and o.transform == s.transform
        assert o.nodata == s.nodata or (o.nodata is None and s.nodata is None)
        assert o.read(1).tobytes() == s.read(1).tobytes()  # the file's own layout, bit for bit
    assert Heightmap.load(out).heights.tobytes() == hm.heights.tobytes()


def test_edited_heights_fall_back_to_float32(tmp_path):
    a = _dem((8, 8), np.int16)
    hm = Heightmap.load(_write(tmp_path / "i.tif", a, "EPSG:32633", from_origin(0, 80, 10, 10)))
    ed = Heightmap.from_array(hm.heights * np.float32(0.37), hm.dx, hm.dz, meta=dict(hm.meta))
    ed.save(tmp_path / "ed.tif")
    with rasterio.open(tmp_path / "ed.tif") as o:
        assert o.dtypes[0] == "float32" and o.crs.to_epsg() == 32633
    assert Heightmap.load(tmp_path / "ed.tif").heights.tobytes() == ed.heights.tobytes()
    crop = Heightmap.from_array(hm.heights[:4], hm.dx, meta=dict(hm.meta))
    with pytest.raises(ValueError, match="shape"):
        crop.save(tmp_path / "crop.tif")


# -- dispatch, other GDAL formats, scene files ----------------------------------------------------
def test_plain_tiff_stays_with_openimageio_and_asc_goes_to_gdal(tmp_path):
    from terrainwarp.io.files import write_image

    a = np.arange(20, dtype=np.uint16).reshape(4, 5)
    write_image(tmp_path / "plain.tif", a)
    assert not is_gdal_raster(tmp_path / "plain.tif")
    hp = Heightmap.load(tmp_path / "plain.tif", 2.0)
    assert hp.dx == 2.0 and "crs" not in hp.meta
    (tmp_path / "g.asc").write_text("ncols 3\nnrows 2\nxllcorner 100\nyllcorner 200\ncellsize 25\n"
                                    "NODATA_value -9999\n1 2 3\n4 -9999 6\n")
    hg = Heightmap.load(tmp_path / "g.asc")
    assert hg.dx == 25.0 and hg.meta["crs_kind"] == "none" and hg.meta["nodata_count"] == 1
    np.testing.assert_array_equal(hg.heights, [[1, 2, 3], [4, np.nan, 6]])
    assert "taken as metres" in hg.meta["summary"]


def test_dx_override_and_determinism(tmp_path):
    a = _dem((10, 10), np.float32)
    p = _write(tmp_path / "d.tif", a, "EPSG:4326", from_origin(5.0, 45.0, 0.01, 0.01))
    h1, h2 = Heightmap.load(p), Heightmap.load(p)
    assert digest(h1.heights) == digest(h2.heights) and h1.dx == h2.dx and h1.meta == h2.meta
    ho = Heightmap.load(p, 7.0)
    assert (ho.dx, ho.dz) == (7.0, 7.0) and "overridden" in ho.meta["summary"]


def test_scene_file_takes_a_geotiff_path(tmp_path):
    a = _dem((16, 16), np.int16)
    _write(tmp_path / "dem.tif", a, "EPSG:32633", from_origin(0, 160, 10, 10), nodata=-32768)
    (tmp_path / "s.toml").write_text('[heightmap]\npath = "dem.tif"\n')
    sc = Scene.load(tmp_path / "s.toml")
    assert (sc.heightmap.dx, sc.heightmap.dz) == (10.0, 10.0)
    np.testing.assert_array_equal(sc.heightmap.heights, a.astype(np.float32))


def test_clear_errors(tmp_path):
    a = _dem((10, 12), np.float32)
    p = _write(tmp_path / "e.tif", a, "EPSG:32633", from_origin(0, 100, 10, 10), nodata=-1.0)
    cases = [
        (dict(channel=1), "band: expected 1..1"),
        (dict(window=((0, 11), (0, 5))), "window: expected a non-empty window inside the 10x12"),
        (dict(window=((3, 3), (0, 5))), "window"),
        (dict(window="rows"), "window: expected"),
        (dict(bounds=(1000, 1000, 2000, 2000)), "bounds: .* does not overlap"),
        (dict(bounds=(50, 0, 10, 100)), "bounds: expected"),
        (dict(window=((0, 2), (0, 2)), bounds=(0, 0, 10, 10)), "not both"),
        (dict(decimate=0), "decimate: expected an integer >= 1"),
        (dict(decimate=11), "decimate: 11 leaves no sample"),
        (dict(resampling="fancy"), "resampling: expected one of"),
        (dict(max_height=100.0), "max_height: not used"),
    ]
    for kw, msg in cases:
        with pytest.raises(ValueError, match=msg):
            Heightmap.load(p, **kw)
    allnd = np.full((3, 3), -1.0, np.float32)
    with pytest.raises(ValueError, match="every cell .* is no-data"):
        Heightmap.load(_write(tmp_path / "nd.tif", allnd, "EPSG:32633", from_origin(0, 30, 10, 10),
                              nodata=-1.0))
    (tmp_path / "bad.vrt").write_text("<VRTDataset>junk")
    with pytest.raises(ValueError, match="path: cannot read"):
        Heightmap.load(tmp_path / "bad.vrt")
    Heightmap.from_array(np.zeros((2, 2), np.uint16)).save(tmp_path / "p.png")
    with pytest.raises(TypeError, match="decimate: only GeoTIFF"):
        Heightmap.load(tmp_path / "p.png", decimate=2)


def test_srtm_hgt_tile(tmp_path):
    # an SRTM 3-arc-second tile: 1201 x 1201 big-endian int16, georeferenced by its name, -32768 voids
    a = np.random.default_rng(8).integers(-20, 3000, size=(1201, 1201)).astype(">i2")
    a[600, 600] = a[0, 1200] = -32768
    a.tofile(tmp_path / "N47E008.hgt")
    hm = Heightmap.load(tmp_path / "N47E008.hgt")
    assert hm.meta["driver"] == "SRTMHGT" and hm.meta["nodata_count"] == 2
    assert hm.meta["sample00_crs"] == pytest.approx([8.0, 48.0], abs=1e-9)  # samples sit on whole degrees
    assert hm.meta["latitude_deg"] == pytest.approx(47.5, abs=1e-9)
    d = 1.0 / 1200.0
    assert hm.dx == pytest.approx(_chord(47.5, 8.0, 47.5, 8.0 + d), rel=1e-9)
    assert hm.dz == pytest.approx(_chord(47.5 - d / 2, 8.0, 47.5 + d / 2, 8.0), rel=1e-9)
    fin = a != -32768
    np.testing.assert_array_equal(hm.heights[fin], a[fin].astype(np.float32))
    # a GeoTIFF written from it reads back to the same heights and places
    back = Heightmap.load(hm.save(tmp_path / "n47e008.tif"))
    assert back.heights.tobytes() == hm.heights.tobytes()
    assert back.meta["sample00_crs"] == pytest.approx(hm.meta["sample00_crs"], abs=1e-9)
    assert (back.dx, back.dz) == pytest.approx((hm.dx, hm.dz), rel=1e-12)


def test_tiff_with_transform_but_no_crs_and_gcps(tmp_path):
    a = _dem((4, 5), np.float32)
    p = _write(tmp_path / "nocrs.tif", a, None, from_origin(0.0, 40.0, 2.5, 2.5), nodata=-1.0)
    assert is_gdal_raster(p)
    hm = Heightmap.load(p)
    assert hm.dx == 2.5 and hm.meta["crs_kind"] == "none" and "taken as metres" in hm.meta["summary"]
    from rasterio.control import GroundControlPoint

    g = [GroundControlPoint(0, 0, 500000.0, 5000000.0), GroundControlPoint(0, 5, 500050.0, 5000000.0),
         GroundControlPoint(4, 0, 500000.0, 4999960.0)]
    with rasterio.open(tmp_path / "gcp.tif", "w", driver="GTiff", width=5, height=4, count=1, dtype="float32",
                       gcps=g, crs="EPSG:32633") as d:
        d.write(a, 1)
    with pytest.raises(ValueError, match="ground control points"):
        Heightmap.load(tmp_path / "gcp.tif")


def test_mask_band_with_decimation(tmp_path):
    b = _dem((12, 12), np.uint16)
    with rasterio.open(tmp_path / "m.tif", "w", driver="GTiff", width=12, height=12, count=1, dtype="uint16",
                       crs="EPSG:32633", transform=from_origin(0, 120, 10, 10)) as d:
        d.write(b, 1)
        m = np.full((12, 12), 255, np.uint8)
        m[:3, :3] = 0
        d.write_mask(m)
    hm = Heightmap.load(tmp_path / "m.tif", decimate=3, resampling="nearest")
    assert hm.shape == (4, 4) and np.isnan(hm.heights[0, 0]) and hm.meta["nodata_count"] == 1
    np.testing.assert_array_equal(hm.heights[1:, 1:], b[4::3, 4::3].astype(np.float32))

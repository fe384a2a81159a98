import math

import numpy as np
import pytest

from terrainwarp import Heightmap
from terrainwarp.io.geodesy import metres_per_degree


def test_example_dem_shape_and_metre_spacing():
    hm = Heightmap.example()
    assert hm.shape == (344, 403)
    assert hm.heights.dtype == np.float32
    lat = hm.meta["latitude_deg"]
    assert 36.4 < lat < 36.8
    # Independent check: spherical approximation (R = 6371 km) within 0.5% of the ellipsoid value.
    deg = 0.0008333333333333334
    assert hm.dz == pytest.approx(deg * math.pi / 180 * 6371000.0, rel=5e-3)
    assert hm.dx == pytest.approx(deg * math.pi / 180 * 6371000.0 * math.cos(math.radians(lat)), rel=5e-3)
    assert hm.dx < hm.dz  # longitude degrees shrink with cos(latitude)
    lo, hi = hm.height_range
    assert 200 < lo < 300 and 1000 < hi < 1100


def test_metres_per_degree_known_values():
    # WGS84: 1 degree of latitude is 110,574 m at the equator and 111,694 m at the pole.
    assert metres_per_degree(0.0)[1] == pytest.approx(110574.3, abs=1.0)
    assert metres_per_degree(90.0)[1] == pytest.approx(111693.9, abs=1.0)
    assert metres_per_degree(0.0)[0] == pytest.approx(111319.5, abs=1.0)
    assert metres_per_degree(90.0)[0] == pytest.approx(0.0, abs=1e-6)


def test_topobathy_has_negative_heights_and_north_up():
    hm = Heightmap.example("topobathy")
    assert hm.shape == (91, 120)
    assert hm.height_range[0] < 0 < hm.height_range[1]
    assert hm.meta["flipped_rows"] is True


@pytest.mark.parametrize("dtype", [np.int8, np.uint8, np.int16, np.uint16, np.int32, np.uint32, np.int64,
                                   np.float16, np.float32, np.float64])
def test_from_array_any_dtype(dtype):
    a = (np.arange(12).reshape(3, 4) % 7).astype(dtype)
    hm = Heightmap.from_array(a, 2.0, 3.0)
    assert hm.heights.dtype == np.float32
    np.testing.assert_array_equal(hm.heights, a.astype(np.float32))
    assert (hm.dx, hm.dz) == (2.0, 3.0)
    assert hm.shape == (3, 4)


def test_normalised_image_scaled_by_max_height():
    a = np.array([[0, 65535], [32768, 65535]], np.uint16)
    hm = Heightmap.from_array(a, max_height=1000.0)
    assert hm.heights[0, 1] == pytest.approx(1000.0)
    assert hm.heights[1, 0] == pytest.approx(32768 / 65535 * 1000.0, rel=1e-6)
    f = Heightmap.from_array(np.array([[0.0, 0.5]]), max_height=200.0)
    np.testing.assert_array_equal(f.heights, [[0.0, 100.0]])


def test_heights_are_read_only():
    hm = Heightmap.from_array(np.zeros((2, 2)))
    with pytest.raises(ValueError):
        hm.heights[0, 0] = 1.0


@pytest.mark.parametrize("bad,exc,word", [
    (np.array([[1.0, np.nan]]), ValueError, "NaN"),
    (np.array([[1.0, np.inf]]), ValueError, "infinite"),
    (np.zeros((0, 3)), ValueError, "non-empty"),
    (np.zeros(5), ValueError, "2D"),
    (np.array([["a"]]), TypeError, "dtype"),
    (np.array([[1 + 2j]]), TypeError, "dtype"),
    (np.array([[1e39]]), ValueError, "float32"),
])
def test_bad_arrays_raise_clearly(bad, exc, word):
    with pytest.raises(exc, match=word):
        Heightmap.from_array(bad)


@pytest.mark.parametrize("kw", [{"dx": 0.0}, {"dx": -1.0}, {"dx": float("nan")}, {"dz": float("inf")}])
def test_bad_spacing(kw):
    with pytest.raises(ValueError, match="dx|dz"):
        Heightmap.from_array(np.zeros((2, 2)), **kw)


def test_nan_allowed_as_holes():
    hm = Heightmap.from_array(np.array([[1.0, np.nan], [2.0, 3.0]]), allow_nan=True)
    assert np.isnan(hm.heights[0, 1])
    assert hm.height_range == (1.0, 3.0)


# -- file round trips ------------------------------------------------------------------------------
def test_png16_round_trip_bit_exact(tmp_path):
    rng = np.random.default_rng(1)
    a = rng.integers(0, 65536, size=(37, 53)).astype(np.uint16)
    hm = Heightmap.from_array(a)
    p = hm.save(tmp_path / "h.png")
    back = Heightmap.load(p)
    np.testing.assert_array_equal(back.heights, a.astype(np.float32))


def test_png8_loads_and_normalises(tmp_path):
    from terrainwarp.io.files import write_image

    a = np.array([[0, 128, 255]], np.uint8)
    write_image(tmp_path / "h8.png", a)
    raw = Heightmap.load(tmp_path / "h8.png")
    np.testing.assert_array_equal(raw.heights, [[0, 128, 255]])
    norm = Heightmap.load(tmp_path / "h8.png", max_height=510.0)
    np.testing.assert_allclose(norm.heights, [[0, 256, 510]], rtol=1e-6)


def test_tiff16_loads_bit_exact(tmp_path):
    from terrainwarp.io.files import write_image

    a = np.random.default_rng(2).integers(0, 65536, size=(9, 11)).astype(np.uint16)
    write_image(tmp_path / "h16.tif", a)
    np.testing.assert_array_equal(Heightmap.load(tmp_path / "h16.tif").heights, a.astype(np.float32))


@pytest.mark.parametrize("ext", [".tif", ".exr", ".npy"])
def test_float_round_trip_bit_exact(tmp_path, ext):
    a = (np.random.default_rng(3).standard_normal((23, 31)) * 1234.5).astype(np.float32)
    a[0, 0] = np.float32(8848.123)
    a[1, 1] = np.float32(-1e-7)
    hm = Heightmap.from_array(a, 5.0)
    back = Heightmap.load(hm.save(tmp_path / f"h{ext}"), 5.0)
    assert back.heights.tobytes() == a.tobytes()


def test_png_refuses_non_integer_heights(tmp_path):
    with pytest.raises(ValueError, match=".tif or .exr"):
        Heightmap.from_array(np.array([[0.5]])).save(tmp_path / "x.png")
    assert not list(tmp_path.iterdir())  # nothing half-written


def test_load_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="path"):
        Heightmap.load(tmp_path / "missing.png")
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(ValueError, match="empty"):
        Heightmap.load(tmp_path / "empty.png")
    (tmp_path / "junk.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 10)
    with pytest.raises(ValueError, match="path"):
        Heightmap.load(tmp_path / "junk.png")
    # a truncated but otherwise valid PNG
    Heightmap.from_array(np.arange(4096, dtype=np.uint16).reshape(64, 64)).save(tmp_path / "ok.png")
    data = (tmp_path / "ok.png").read_bytes()
    (tmp_path / "trunc.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="path"):
        Heightmap.load(tmp_path / "trunc.png")
    with pytest.raises(ValueError, match="extension|file name"):
        Heightmap.from_array(np.zeros((2, 2))).save(tmp_path / "x.xyz")


# -- procedural ------------------------------------------------------------------------------------
def test_fbm_deterministic_in_range_and_windowable():
    from terrainwarp.kernels.noise import fbm

    a = Heightmap.fbm(65, 80, seed=7, max_height=500.0)
    b = Heightmap.fbm(65, 80, seed=7, max_height=500.0)
    c = Heightmap.fbm(65, 80, seed=8, max_height=500.0)
    assert a.heights.tobytes() == b.heights.tobytes()
    assert a.heights.tobytes() != c.heights.tobytes()
    assert a.heights.min() >= 0.0 and a.heights.max() <= 500.0
    assert a.heights.std() > 10.0  # it is actually terrain, not a constant
    whole = fbm(64, 64, seed=3)
    tile = fbm(16, 24, seed=3, row0=20, col0=30)
    assert tile.tobytes() == whole[20:36, 30:54].tobytes()


# -- designer controls (mrbsp section 1) -----------------------------------------------------------
def test_designer_controls():
    h = np.array([[-10.0, 0.0, 10.0, 100.0]], np.float32)
    hm = Heightmap.from_array(h)
    d = hm.designed(sea_level=5.0, seabed=0.5, height_scale=2.0)
    np.testing.assert_allclose(d.heights, [[-15.0, -5.0, 10.0, 190.0]])


def test_smoothing_spares_mountains():
    rng = np.random.default_rng(0)
    h = rng.uniform(0, 10, (32, 32)).astype(np.float32)
    h[16, 16] = 500.0  # a jagged peak
    hm = Heightmap.from_array(h)
    s = hm.designed(smoothing=3, mountain_height=100.0)
    assert s.heights[16, 16] == 500.0
    assert s.heights[4:12, 4:12].std() < 0.5 * h[4:12, 4:12].std()


@pytest.mark.parametrize("content, arg", [(b"", "path"), (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\x00", "path"),
                                          (b"not an image at all" * 10, "path")])
def test_corrupt_and_truncated_images(tmp_path, content, arg):
    p = tmp_path / "h.png"
    p.write_bytes(content)
    with pytest.raises(ValueError, match=arg):
        Heightmap.load(p)


def test_truncated_valid_png(tmp_path):
    p = tmp_path / "h.png"
    Heightmap.from_array(np.arange(64 * 64, dtype=np.uint16).reshape(64, 64)).save(p)
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="path"):
        Heightmap.load(p)

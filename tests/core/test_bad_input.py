"""Bad input that used to get past the core types (issue 20): each is refused up front with one clear
ValueError naming the argument, instead of failing later inside numpy, Warp or a division."""

import os
import struct
import time
import zlib

import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin
from rasterio.windows import Window

import terrainwarp as tw
from terrainwarp import Camera, Heightmap
from terrainwarp.camera import flyover, orbit
from terrainwarp.io import memory
from terrainwarp.io.files import write_image
from terrainwarp.rendering import rasterize as tw_rasterize
from terrainwarp.scene import Scene

# rasterio 1.4 composes affine transforms with `*`, which affine 3 marks as pending deprecation
pytestmark = pytest.mark.filterwarnings("ignore:Use `@` matmul:PendingDeprecationWarning")


# -- item 7: the constructor validates as from_array does ------------------------------------------
@pytest.mark.parametrize("h,word", [
    (np.full((3, 4), np.nan, np.float32), "every height is NaN"),
    (np.zeros((0, 5), np.float32), "non-empty"),
    (np.zeros((5, 0), np.float32), "non-empty"),
    (np.array([[1.0, np.inf], [0.0, 1.0]], np.float32), "infinite"),
])
def test_constructor_refuses_what_from_array_refuses(h, word):
    with pytest.raises(ValueError, match=f"^heights: .*{word}"):
        Heightmap(heights=h)
    with pytest.raises(ValueError, match=f"^a: .*{word}"):
        Heightmap.from_array(h, allow_nan=True)


def test_constructor_accepts_holes_and_repr_works():
    h = np.array([[1.0, np.nan], [2.0, 3.0]], np.float32)
    hm = Heightmap(heights=h, dx=2.0)
    assert repr(hm) == "Heightmap('heightmap', shape=(2, 2), dx=2, dz=1, heights=[1, 3] m)"
    assert np.array_equal(hm.heights, Heightmap.from_array(h, 2.0, 1.0, allow_nan=True).heights, equal_nan=True)


# -- item 5: a field of view of 0 (or 180, NaN, ...) is refused wherever a camera is made ----------
def _hm():
    return Heightmap.from_array(np.arange(20.0).reshape(4, 5), 10.0)


@pytest.mark.parametrize("fov", [0, 0.0, -10.0, 180.0, float("nan"), float("inf")])
def test_default_camera_refuses_a_bad_field_of_view(fov):
    with pytest.raises(ValueError, match=r"^fov_y_deg: expected a value in \(0, 180\) degrees, got|"
                                         r"^fov_y_deg: expected a finite number, got"):
        Camera.default_for(_hm(), 640, 480, fov)


@pytest.mark.parametrize("kw,msg", [
    ({"width": 0}, r"^width: expected 1\.\.16384 pixels, got 0$"),
    ({"height": 2.5}, r"^height: expected a positive integer number of pixels, got 2\.5$"),
    ({"fov_y_deg": "wide"}, r"^fov_y_deg: expected a number, got 'wide'$"),
])
def test_default_camera_names_the_bad_argument(kw, msg):
    with pytest.raises((ValueError, TypeError), match=msg):
        Camera.default_for(_hm(), **kw)


def test_scene_file_fov_zero_without_a_position(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text('[heightmap]\nfbm = { rows = 17, seed = 1 }\n[camera]\nfov_y_deg = 0\n')
    with pytest.raises(ValueError, match=r"^fov_y_deg: expected a value in \(0, 180\) degrees, got 0$"):
        Scene.load(p)
    p.write_text('[heightmap]\nfbm = { rows = 17, seed = 1 }\n[camera]\nposition = [0, 500, 400]\n'
                 'target = [80, 0, 80]\nfov_y_deg = 0\n')
    with pytest.raises(ValueError, match=r"^fov_y_deg: expected a value in \(0, 180\)"):
        Scene.load(p)
    with pytest.raises(ValueError, match=r"^path.fov_y_deg: expected a finite number > 0.0 and < 180.0, got 0$"):
        Scene.from_dict({"heightmap": {"fbm": {"rows": 17}}, "path": {"fov_y_deg": 0}})  # refused when parsed


def test_camera_paths_refuse_a_bad_field_of_view():
    with pytest.raises(ValueError, match="^fov_y_deg: "):
        orbit((0, 0, 0), 100.0, 50.0, 4, fov_y_deg=0.0)
    with pytest.raises(ValueError, match="^fov_y_deg: "):
        flyover(_hm(), [(0, 0), (40, 30)], 5.0, 3, fov_y_deg=180.0)


# -- item 4: the size guard -------------------------------------------------------------------------
def test_fbm_far_too_big_is_refused_fast():
    t = time.perf_counter()
    with pytest.raises(ValueError, match=r"^rows: a 1000000 x 1000000 heightmap needs about 24\.0 TB; this "
                                         r"machine has [0-9.]+ [kMGTP]?B available \(terrains larger than memory"):
        Heightmap.fbm(10**6)
    with pytest.raises(ValueError, match=r"^cols: a 10 x 10000000000 heightmap needs about 2\.4 TB"):
        Heightmap.fbm(10, 10**10)
    assert time.perf_counter() - t < 1.0


def test_refusal_against_a_small_machine(monkeypatch, tmp_path):
    """available_bytes is looked up at every call, so a test can pretend the machine is small."""
    big = Heightmap.fbm(257, max_height=255.0)
    for ext in ("png", "npy", "exr"):
        Heightmap.from_array(np.round(big.heights)).save(tmp_path / f"big.{ext}")
    monkeypatch.setattr(memory, "available_bytes", lambda: 1_000_000)
    with pytest.raises(ValueError, match=r"^rows: a 257 x 257 heightmap needs about 1\.6 MB; this machine "
                                         r"has 1\.0 MB available"):
        Heightmap.fbm(257)
    assert Heightmap.fbm(129).shape == (129, 129)  # 399 kB
    for ext in ("png", "npy", "exr"):
        with pytest.raises(ValueError, match=rf"^path: a 257 x 257 (image|array in) big\.{ext} needs about "
                                             r"1\.6 MB; this machine has 1\.0 MB available"):
            Heightmap.load(tmp_path / f"big.{ext}")
    monkeypatch.setattr(memory, "available_bytes", lambda: None)  # the machine does not say: no refusal
    assert Heightmap.load(tmp_path / "big.png").shape == (257, 257)


def _png_declaring(path, width, height):
    """A valid 1 x 1 16-bit PNG whose IHDR then declares width x height (CRC fixed), followed by a private
    ancillary chunk of 10 MB of zeros (a hole in a sparse file): OpenImageIO's own check refuses headers
    that claim over ~10000x the file's size, and a real 100000^2 PNG of zeros is about this big."""
    write_image(path, np.zeros((1, 1), np.uint16))
    b = bytearray(path.read_bytes())
    assert b[12:16] == b"IHDR"
    b[16:24] = struct.pack(">II", width, height)
    b[29:33] = struct.pack(">I", zlib.crc32(bytes(b[12:29])))
    pad = 10_000_000
    crc = zlib.crc32(b"\0" * pad, zlib.crc32(b"prVt"))
    with path.open("wb") as f:
        f.write(bytes(b[:33]) + struct.pack(">I", pad) + b"prVt")
        f.seek(pad, os.SEEK_CUR)
        f.write(struct.pack(">I", crc) + bytes(b[33:]))
    return path


def test_png_declaring_100000_squared_is_refused_before_decoding(tmp_path):
    p = _png_declaring(tmp_path / "huge.png", 100_000, 100_000)
    assert p.stat().st_blocks * 512 < 1_000_000  # sparse: no 10 MB on disk
    with pytest.raises(ValueError, match=r"^path: a 100000 x 100000 image huge\.png needs about 240\.0 GB; "
                                         r"this machine has [0-9.]+ [kMGT]?B available"):
        Heightmap.load(p)


def _sparse_geotiff(path, height, width):
    """A tiled GeoTIFF that declares height x width int16 samples and stores one 256 x 256 tile (GDAL
    SPARSE_OK: the others are absent and read as no-data)."""
    with rasterio.open(path, "w", driver="GTiff", width=width, height=height, count=1, dtype="int16",
                       crs="EPSG:32617", transform=from_origin(500000.0, 4000000.0, 1.0, 1.0), nodata=-9999,
                       tiled=True, blockxsize=256, blockysize=256, compress="deflate", SPARSE_OK=True,
                       BIGTIFF="YES") as d:
        d.write(np.arange(256 * 256, dtype=np.int16).reshape(256, 256) % 1000, 1, window=Window(0, 0, 256, 256))
    return path


def test_geotiff_declaring_100000_squared_is_refused_before_decoding(tmp_path):
    p = _sparse_geotiff(tmp_path / "huge.tif", 100_000, 100_000)
    assert p.stat().st_size < 2_000_000
    with pytest.raises(ValueError, match=r"^path: a 100000 x 100000 part of huge\.tif read as heights needs "
                                         r"about 240\.0 GB; this machine has .* available \(.*decimate=k\)$"):
        Heightmap.load(p)
    # what the message suggests works: a window, or decimation
    hm = Heightmap.load(p, window=((0, 64), (0, 96)))
    assert hm.shape == (64, 96) and hm.heights[1, 0] == 256
    hm = Heightmap.load(p, window=((0, 2560), (0, 2560)), decimate=10)
    assert hm.shape == (256, 256) and np.isfinite(hm.heights[:25, :25]).all()


def test_geotiff_window_too_big_blames_the_window(tmp_path, monkeypatch):
    p = _sparse_geotiff(tmp_path / "w.tif", 2000, 2000)
    monkeypatch.setattr(memory, "available_bytes", lambda: 10_000_000)
    with pytest.raises(ValueError, match=r"^window: a 1000 x 1000 part of w\.tif .* 24\.0 MB; this machine has "
                                         r"10\.0 MB available"):
        Heightmap.load(p, window=((0, 1000), (0, 1000)))
    with pytest.raises(ValueError, match=r"^path: a 2000 x 2000 part"):
        Heightmap.load(p)


def test_available_memory_and_formatting():
    avail = memory.available_bytes()
    assert avail is not None and 0 < avail <= os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    assert [memory.format_bytes(v) for v in (512, 1536, 21.3e9, 8e12)] == ["512 B", "1.5 kB", "21.3 GB",
                                                                           "8.0 TB"]


# -- item 12: no native "libpng error:" line beside the one-line ValueError ---------------------------
@pytest.mark.parametrize("cut", ["truncated", "garbage"])
def test_corrupt_png_gives_one_line_and_no_libpng_noise(tmp_path, capfd, cut):
    good = Heightmap.from_array(np.arange(64 * 64).reshape(64, 64) % 1000)
    good.save(tmp_path / "good.png")
    b = (tmp_path / "good.png").read_bytes()
    p = tmp_path / "bad.png"
    p.write_bytes(b[:len(b) // 2] if cut == "truncated" else b[:40] + b"garbage" * 50)
    capfd.readouterr()
    with pytest.raises(ValueError, match=r"^path: .*bad\.png (is corrupt or truncated|as an image): ") as e:
        Heightmap.load(p)
    assert "\n" not in str(e.value)
    out, err = capfd.readouterr()
    assert "libpng" not in err and "PNG" not in err
    assert (out, err) == ("", "")
    # stderr works again afterwards, at the descriptor level too
    os.write(2, b"still here\n")
    assert capfd.readouterr().err == "still here\n"


# -- bad input across the public API ----------------------------------------------------------------
@pytest.mark.parametrize("call, arg", [
    (lambda: tw.Heightmap.from_array(np.array([["a", "b"]])), "a"),
    (lambda: tw.Heightmap.from_array(np.zeros((2, 3, 4))), "a"),
    (lambda: tw.Heightmap.from_array(np.zeros((0, 4))), "a"),
    (lambda: tw.Heightmap.from_array(np.array([[1.0, np.nan]])), "a"),
    (lambda: tw.Heightmap.from_array(np.array([[1.0, np.inf]])), "a"),
    (lambda: tw.Heightmap.from_array(np.ones((3, 3)), -1.0), "dx"),
    (lambda: tw.Heightmap.from_array(np.ones((3, 3)), 1.0, 0.0), "dz"),
    (lambda: tw.Heightmap.from_array(np.ones((3, 3)), float("nan")), "dx"),
    (lambda: tw.Heightmap.fbm(-4), "rows"),
    (lambda: tw.Camera((0, 0, 0), (0, 0, -1), width=-5), "width"),
    (lambda: tw.Camera((0, 0, 0), (0, 0, -1), height=0), "height"),
    (lambda: tw.Camera((np.nan, 0, 0), (0, 0, -1)), "position"),
    (lambda: tw.Camera((0, 0, 0), (0, 0, -1), near=-1.0), "near"),
    (lambda: tw.Camera((0, 0, 0), (0, 0, -1), fov_y_deg=180.0), "fov_y_deg"),
    (lambda: tw.Camera((0, 0, 0), (0, -1, 0)), "up"),
    (lambda: tw.Scene("not a heightmap"), "heightmap"),
    (lambda: tw.Scene(tw.Heightmap.from_array(np.ones((3, 3))), outputs=("image", "bogus")), "outputs"),
    (lambda: tw.render("scene"), "scene"),
    (lambda: tw_rasterize(np.zeros((3, 2), np.float32), np.zeros((1, 3), np.int32), np.eye(4), np.eye(4), 8, 8),
     "positions"),
    (lambda: tw_rasterize(np.full((3, 3), np.inf, np.float32), np.zeros((1, 3), np.int32), np.eye(4), np.eye(4),
                          8, 8), "positions"),
    (lambda: tw.compute_normals(tw.Heightmap.from_array(np.ones((3, 3))), "bogus"), "method"),
    (lambda: tw.compute_normals(np.zeros((0, 3))), "heightmap"),
])
def test_api_bad_input_names_the_argument(call, arg):
    with pytest.raises((ValueError, TypeError)) as ei:
        call()
    assert str(ei.value).startswith(arg) or f"{arg}:" in str(ei.value) or f"{arg} " in str(ei.value), str(ei.value)

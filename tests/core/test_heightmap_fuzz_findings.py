"""What the fuzz suite (tests/fuzz_runner.py, issue 31) found in ``Heightmap.load``, each kept as a small input
made here: damaged ``.npy`` headers (numpy's tokenizer error escaped as ``TokenError``), errors that blamed
``a`` (``from_array``'s argument) instead of the file, a ``channel`` that was not an integer, raster options
on a GeoTIFF GDAL cannot open, overflow warnings; and the size guard, blind to the worker's address-space
limit."""

from __future__ import annotations

import io
import re
import subprocess
import sys
import textwrap
import warnings

import numpy as np
import pytest
import rasterio
from affine import Affine

from terrainwarp import Heightmap
from terrainwarp.io.files import write_image


def from_origin(west, north, xsize, ysize):
    """rasterio.transform.from_origin without its deprecated Affine * Affine."""
    return Affine(xsize, 0.0, west, 0.0, -ysize, north)


def _npy(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a)
    return buf.getvalue()


def _with_header(text: str, body: bytes = b"") -> bytes:
    """A version 1.0 .npy file with this header text (padded as numpy pads it)."""
    h = text.encode("latin1")
    h += b" " * ((64 - (10 + len(h) + 1) % 64) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + len(h).to_bytes(2, "little") + h + body


@pytest.mark.parametrize("header, msg", [
    ("{'descr': '<f4', 'fortran_order': False, 'shape': (3,", r"its header is damaged"),  # tokenize.TokenError
    ("{'descr': 'bogus', 'fortran_order': False, 'shape': (3, 3), }", r"its header is damaged"),
    ("[1, 2]", r"its header is damaged"),
    ("{'descr': '<f4', 'fortran_order': False, 'shape': (12, -10), }", r"shape \(12, -10\)"),
    ("{'descr': '<f4', 'fortran_order': False, 'shape': (1000000000000,), }", r"shape \(1000000000000,\)"),
    ("{'descr': '<f4', 'fortran_order': False, 'shape': (3, 3, 3), }", r"shape \(3, 3, 3\)"),
])
def test_a_damaged_npy_header_is_a_value_error_naming_the_file(tmp_path, header, msg):
    p = tmp_path / "h.npy"
    p.write_bytes(_with_header(header, b"\x00" * 64))
    with pytest.raises(ValueError, match=rf"^path: .*h\.npy.*{msg}"):
        Heightmap.load(p)


def test_a_short_npy_body_names_the_file(tmp_path):
    p = tmp_path / "short.npy"
    p.write_bytes(_npy(np.zeros((12, 10), np.float32))[:-40])
    with pytest.raises(ValueError, match=r"^path: cannot read .*short\.npy as \.npy"):
        Heightmap.load(p)


@pytest.mark.parametrize("a, msg", [
    (np.zeros((0, 5), np.float32), r"expected a non-empty array, got shape \(0, 5\)"),
    (np.zeros((4, 4), bool), r"expected an integer or float array, got dtype bool"),
    (np.zeros((4, 4), "m8[s]"), r"expected an integer or float array, got dtype timedelta64"),
    (np.full((4, 4), np.inf, np.float32), r"expected finite heights, got 16 infinite values"),
    (np.full((4, 4), np.nan, np.float32), r"16 NaN heights"),
    (np.where(np.eye(4) > 0, np.nan, 1.0).astype(np.float32), r"4 NaN heights; pass allow_nan=True"),
])
def test_load_errors_name_the_file_not_from_arrays_argument(tmp_path, a, msg):
    # fuzz finding: "a: expected finite heights, got 100 infinite values" named no file
    p = tmp_path / "bad.npy"
    p.write_bytes(_npy(a))
    with pytest.raises((TypeError, ValueError), match=rf"^path: .*bad\.npy: {msg}"):
        Heightmap.load(p)


def test_an_image_with_nan_names_the_file_and_max_height_overflow_warns_nothing(tmp_path):
    a = np.ones((5, 5), np.float32)
    a[2, 2] = np.nan
    p = write_image(tmp_path / "holes.tif", a)
    with pytest.raises(ValueError, match=r"^path: .*holes\.tif: 1 NaN heights"):
        Heightmap.load(p)
    assert np.isnan(Heightmap.load(p, allow_nan=True).heights[2, 2])
    q = tmp_path / "big.npy"
    q.write_bytes(_npy(np.full((3, 3), 1e300)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the multiply overflowed with a RuntimeWarning before the refusal
        with pytest.raises(ValueError, match=r"^path: .*big\.npy: expected finite heights"):
            Heightmap.load(q, max_height=1e300)


@pytest.mark.parametrize("channel, kind", [(1.5, TypeError), (True, TypeError), ("0", TypeError),
                                           (-1, ValueError), (3, ValueError)])
def test_channel_is_a_non_negative_integer_for_every_reader(tmp_path, channel, kind):
    # fuzz finding: channel=1.5 reached OpenImageIO's read_image ("incompatible function arguments"), and a
    # GeoTIFF's band became int(1.5) + 1 = 2 without a word
    rgb = write_image(tmp_path / "rgb.tif", np.zeros((4, 4, 3), np.uint16))
    geo = tmp_path / "geo.tif"
    with rasterio.open(geo, "w", driver="GTiff", width=4, height=4, count=3, dtype="float32", crs="EPSG:32617",
                       transform=from_origin(0, 40, 10, 10)) as d:
        d.write(np.zeros((3, 4, 4), np.float32))
    for p in (rgb, geo):
        with pytest.raises(kind, match=r"^(channel|band): expected"):
            Heightmap.load(p, channel=channel)
    assert Heightmap.load(rgb, channel=2).shape == (4, 4) and Heightmap.load(geo, channel=2).meta["band"] == 3


def test_raster_options_on_a_tiff_gdal_cannot_open_say_why(tmp_path):
    # fuzz finding: "window: only GeoTIFF / GDAL rasters take window; x.tif is read by OpenImageIO or numpy"
    # for a damaged GeoTIFF, whose damage was the real story
    p = tmp_path / "x.tif"
    p.write_bytes(b"II*\x00" + b"\x00" * 60)
    with pytest.raises(ValueError, match=r"^path: cannot read .*x\.tif as a GDAL raster"):
        Heightmap.load(p, window=((0, 2), (0, 2)))
    plain = write_image(tmp_path / "plain.tif", np.arange(16, dtype=np.uint16).reshape(4, 4))
    hm = Heightmap.load(plain, window=((1, 3), (0, 2)))  # a plain TIFF with a window: read through GDAL
    assert np.array_equal(hm.heights, np.arange(16, dtype=np.float32).reshape(4, 4)[1:3, 0:2])


def test_the_size_guard_counts_an_address_space_limit(tmp_path):
    # the fuzz worker runs under an address-space limit (RLIMIT_AS, as `ulimit -v` sets it), so that a case that
    # allocates without bound fails fast instead of taking the shared machine's memory; the guard did not see
    # the limit and let a heightmap through that the limit then refused with Warp's or numpy's allocation error
    code = textwrap.dedent("""
        import resource
        resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30))
        from terrainwarp import Heightmap
        try:
            Heightmap.fbm(11000)  # about 2.9 GB by the guard's estimate: more than the limit leaves
        except ValueError as e:
            print(e)
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    m = re.match(r"rows: a 11000 x 11000 heightmap needs about 2\.9 GB; this machine has ([0-9.]+) GB available",
                 r.stdout)
    assert m and float(m.group(1)) < 2.15, r.stdout  # what the 2 GiB limit leaves, not what the machine has free

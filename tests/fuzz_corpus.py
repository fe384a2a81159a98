"""What the fuzz suite feeds the loaders (issue 31, "A fuzz suite"): small valid seed files of every format a
heightmap or a scene comes in, and hypothesis strategies that mutate them into cases.

Seeds (built once per process, deterministically, in memory):

* PNG: 8- and 16-bit grey, grey + alpha, RGB, RGBA and a palette image, 1- to 16-bit, written by the
  encoder below (so its header fields can be edited knowingly and its CRCs fixed after an edit);
* TIFF: 8-, 16-bit and float32, one and three channels, strips and tiles, none/deflate/LZW compression
  (OpenImageIO, as a plain TIFF without georeferencing: read by OpenImageIO);
* GeoTIFF: rasterio, tiled and deflate (one file two 256-sample tiles across, as the streamed path reads),
  striped, int16 and float32, projected and geographic CRSs, with nodata, scale/offset and a vertical unit,
  and one with a geotransform but no CRS;
* .npy: float32, float64 (Fortran order), int16, uint8 (H, W, 1), float16, big-endian, version 2 headers;
* scene TOML: every table and key of a scene file, over small heightmap files that travel with the case;
* CLI: argument lists for every command, over those scenes and files.

Mutations: bit flips and byte/word edits (biased toward the header), truncation, deletion, insertion,
duplication and splices of another seed's bytes, and format-aware header edits: PNG IHDR fields (with the
CRC fixed, so libpng reads on), TIFF IFD entries (tag, type, count, values, offsets; GeoTIFF's pixel scale,
tie points and GeoKeys), .npy header fields (shape, dtype, order, version, header length). Scene TOML is
mutated as data (values replaced by other types and edge values, keys deleted, unknown keys added) and, for
some cases, as text. Each case may also carry edge values for the loader's keyword arguments.
"""

from __future__ import annotations

import math
import struct
import tempfile
import zlib
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
from hypothesis import strategies as st

__all__ = ["Case", "FILE_TARGETS", "TARGETS", "case_strategy", "seeds", "scene_seeds", "toml_text", "png_bytes",
           "tiff_entries"]

FILE_TARGETS = ("png", "tiff", "geotiff", "npy")
TARGETS = (*FILE_TARGETS, "toml", "cli")


@dataclass
class Case:
    """One input: the main file (``name``, ``data``) and the files beside it, what to call (``call``: the
    loader's keyword arguments, or ``argv`` for the CLI) and how it was made (``how``)."""

    target: str
    index: int
    name: str
    data: bytes
    files: dict[str, bytes] = field(default_factory=dict)
    call: dict[str, Any] = field(default_factory=dict)
    argv: list[str] | None = None
    how: str = ""


# ------------------------------------------------------------------------------------------------
# PNG: a small encoder (every colour type and bit depth, no interlace)
# ------------------------------------------------------------------------------------------------
def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)


def png_bytes(a: np.ndarray, color_type: int = 0, bit_depth: int = 8, palette: np.ndarray | None = None) -> bytes:
    """A PNG of ``a`` ((H, W) or (H, W, C) unsigned integers already in range for ``bit_depth``)."""
    h, w = a.shape[:2]
    nch = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}[color_type]
    a = a.reshape(h, w, nch)
    rows = []
    for r in range(h):
        if bit_depth == 16:
            line = a[r].astype(">u2").tobytes()
        elif bit_depth == 8:
            line = a[r].astype(np.uint8).tobytes()
        else:  # 1, 2, 4 bits: pack samples big-end first
            bits = np.unpackbits(a[r].astype(np.uint8).reshape(-1, 1), axis=1)[:, 8 - bit_depth:]
            line = np.packbits(bits.reshape(-1)).tobytes()
        rows.append(b"\x00" + line)
    ihdr = struct.pack(">IIBBBBB", w, h, bit_depth, color_type, 0, 0, 0)
    out = b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr)
    if palette is not None:
        out += _chunk(b"PLTE", palette.astype(np.uint8).tobytes())
    out += _chunk(b"IDAT", zlib.compress(b"".join(rows), 9)) + _chunk(b"IEND", b"")
    return out


def _png_fix_crcs(b: bytearray) -> bytearray:
    """Recompute every chunk's CRC that lies inside the file (after an edit, libpng reads on)."""
    pos = 8
    while pos + 12 <= len(b):
        n = struct.unpack(">I", b[pos:pos + 4])[0]
        end = pos + 8 + n
        if end + 4 > len(b):
            break
        b[end:end + 4] = struct.pack(">I", zlib.crc32(bytes(b[pos + 4:end])) & 0xFFFFFFFF)
        pos = end + 4
    return b


# ------------------------------------------------------------------------------------------------
# TIFF: the IFD entries of a classic TIFF (for knowing edits)
# ------------------------------------------------------------------------------------------------
_TIFF_TYPE_SIZE = {1: 1, 2: 1, 3: 2, 4: 4, 5: 8, 6: 1, 7: 1, 8: 2, 9: 4, 10: 8, 11: 4, 12: 8, 16: 8, 17: 8, 18: 8}
_TIFF_TYPE_FMT = {1: "B", 2: "B", 3: "H", 4: "I", 6: "b", 7: "B", 8: "h", 9: "i", 11: "f", 12: "d", 16: "Q",
                  17: "q"}


def tiff_entries(b: bytes) -> tuple[str, list[tuple[int, int, int, int, int]]]:
    """(byte order '<' or '>', [(entry offset, tag, type, count, value offset)]) of every IFD of a classic
    TIFF (at most 8 IFDs, 512 entries each); ([], '<') when the header does not parse."""
    if len(b) < 8 or b[:2] not in (b"II", b"MM"):
        return "<", []
    e = "<" if b[:2] == b"II" else ">"
    if struct.unpack(e + "H", b[2:4])[0] != 42:
        return e, []
    ifd = struct.unpack(e + "I", b[4:8])[0]
    out: list[tuple[int, int, int, int, int]] = []
    for _ in range(8):
        if ifd == 0 or ifd + 2 > len(b):
            break
        n = struct.unpack(e + "H", b[ifd:ifd + 2])[0]
        for k in range(min(n, 512)):
            at = ifd + 2 + 12 * k
            if at + 12 > len(b):
                break
            tag, typ, count = struct.unpack(e + "HHI", b[at:at + 8])
            size = _TIFF_TYPE_SIZE.get(typ, 1) * count
            voff = at + 8 if size <= 4 else struct.unpack(e + "I", b[at + 8:at + 12])[0]
            out.append((at, tag, typ, count, voff))
        nxt = ifd + 2 + 12 * n
        ifd = struct.unpack(e + "I", b[nxt:nxt + 4])[0] if nxt + 4 <= len(b) else 0
    return e, out


# ------------------------------------------------------------------------------------------------
# .npy: header fields
# ------------------------------------------------------------------------------------------------
def _npy_split(b: bytes) -> tuple[bytes, dict | None, bytes]:
    """(the bytes before the header text, the header as a dict or None, the body) of a .npy file."""
    if len(b) < 10 or not b.startswith(b"\x93NUMPY"):
        return b"", None, b
    major = b[6]
    hl_size = 2 if major == 1 else 4
    hl = int.from_bytes(b[8:8 + hl_size], "little")
    start = 8 + hl_size
    text = b[start:start + hl]
    try:
        import ast

        d = ast.literal_eval(text.decode("latin1"))
    except (ValueError, SyntaxError, MemoryError, RecursionError):
        d = None
    return b[:start], d if isinstance(d, dict) else None, b[start + hl:]


def _npy_join(d: dict, body: bytes, version: tuple[int, int] = (1, 0), pad: bool = True) -> bytes:
    text = repr(d).encode("latin1")
    hl_size = 2 if version[0] == 1 else 4
    if pad:
        total = 8 + hl_size + len(text) + 1
        text += b" " * ((64 - total % 64) % 64) + b"\n"
    hl = len(text)
    if hl_size == 2 and hl > 0xFFFF:
        hl_size, version = 4, (2, 0)
    return b"\x93NUMPY" + bytes(version) + hl.to_bytes(hl_size, "little") + text + body


# ------------------------------------------------------------------------------------------------
# seeds
# ------------------------------------------------------------------------------------------------
def _terrain(h: int, w: int, seed: int) -> np.ndarray:
    """A smooth float64 terrain in [0, 1] (compresses well, as real DEMs do)."""
    r = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    z = np.zeros((h, w))
    for k in range(1, 4):
        z += np.sin(x * 0.11 * k + r.random() * 6) * np.cos(y * 0.07 * k + r.random() * 6) / k
    return (z - z.min()) / max(np.ptp(z), 1e-12)


def _png_seeds() -> dict[str, bytes]:
    t = _terrain(13, 11, 1)
    pal = np.stack([np.arange(16) * 16] * 3, axis=1)
    return {
        "gray8.png": png_bytes(np.round(t * 255).astype(np.uint8), 0, 8),
        "gray16.png": png_bytes(np.round(_terrain(9, 17, 2) * 65535).astype(np.uint16), 0, 16),
        "gray4.png": png_bytes(np.round(t * 15).astype(np.uint8), 0, 4),
        "gray1.png": png_bytes((t > 0.5).astype(np.uint8), 0, 1),
        "ga8.png": png_bytes(np.stack([np.round(t * 255), np.full(t.shape, 255)], -1).astype(np.uint8), 4, 8),
        "rgb8.png": png_bytes(np.round(np.stack([t, 1 - t, t * t], -1) * 255).astype(np.uint8), 2, 8),
        "rgba16.png": png_bytes(np.round(np.stack([t, t, t, np.ones_like(t)], -1) * 65535).astype(np.uint16), 6, 16),
        "palette4.png": png_bytes(np.round(t * 15).astype(np.uint8), 3, 4, palette=pal),
    }


def _oiio_tiff(path: Path, a: np.ndarray, fmt: str, compression: str, tile: int = 0) -> bytes:
    import OpenImageIO as oiio  # lazy: heavy optional dependency

    nch = 1 if a.ndim == 2 else a.shape[2]
    spec = oiio.ImageSpec(a.shape[1], a.shape[0], nch, getattr(oiio, fmt))
    spec.attribute("DateTime", "")
    spec.attribute("Software", "")
    spec.attribute("compression", compression)
    if tile:
        spec.tile_width = spec.tile_height = tile
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(np.ascontiguousarray(a).reshape(a.shape[0], a.shape[1], nch))
    out.close()
    return path.read_bytes()


def _tiff_seeds(d: Path) -> dict[str, bytes]:
    t = _terrain(20, 24, 3)
    return {
        "u8_none.tif": _oiio_tiff(d / "a.tif", np.round(t * 255).astype(np.uint8), "UINT8", "none"),
        "u16_zip.tif": _oiio_tiff(d / "b.tif", np.round(t * 65535).astype(np.uint16), "UINT16", "zip"),
        "f32_lzw.tif": _oiio_tiff(d / "c.tif", (t * 800 - 100).astype(np.float32), "FLOAT", "lzw"),
        "f32_tiled.tif": _oiio_tiff(d / "d.tif", _terrain(40, 40, 4).astype(np.float32) * 50, "FLOAT", "zip", 16),
        "u16_rgb.tif": _oiio_tiff(d / "e.tif", np.round(np.stack([t, t, 1 - t], -1) * 65535).astype(np.uint16),
                                  "UINT16", "none"),
    }


def _geotiff(path: Path, a: np.ndarray, **profile: Any) -> bytes:
    import rasterio  # lazy: heavy optional dependency

    scales, offsets, units = profile.pop("scales", None), profile.pop("offsets", None), profile.pop("units", None)
    with rasterio.open(path, "w", driver="GTiff", width=a.shape[1], height=a.shape[0], count=1, dtype=str(a.dtype),
                       **profile) as dst:
        dst.write(a, 1)
        if scales:
            dst.scales, dst.offsets = scales, offsets
        if units:
            dst.units = units
    return path.read_bytes()


def _geotiff_seeds(d: Path) -> dict[str, bytes]:
    from affine import Affine  # lazy: heavy optional dependency (with rasterio)

    def from_origin(west, north, xsize, ysize):  # rasterio's own multiplies Affines with * (deprecated)
        return Affine(xsize, 0.0, west, 0.0, -ysize, north)

    f = (_terrain(64, 48, 5) * 900).astype(np.float32)
    f[3:6, 40:44] = -9999.0
    i = np.round(_terrain(40, 30, 6) * 3000 - 200).astype(np.int16)
    i[0, :5] = -32768
    two = (_terrain(40, 300, 7) * 100).astype(np.float32)  # two 256-sample tiles across: the streamed path
    return {
        "utm_f32_tiled.tif": _geotiff(d / "g1.tif", f, crs="EPSG:32617", transform=from_origin(500000, 4e6, 30, 30),
                                      nodata=-9999.0, tiled=True, blockxsize=16, blockysize=16, compress="deflate"),
        "geo_i16_strips.tif": _geotiff(d / "g2.tif", i, crs="EPSG:4326", transform=from_origin(-84.5, 36.3, 1 / 1200,
                                                                                                1 / 1200),
                                       nodata=-32768),
        "utm_u16_scaled_ft.tif": _geotiff(d / "g3.tif", np.round(_terrain(24, 24, 8) * 60000).astype(np.uint16),
                                          crs="EPSG:32610", transform=from_origin(4e5, 5e6, 10, 10), nodata=0,
                                          scales=(0.1,), offsets=(-50.0,), units=("ft",), compress="lzw"),
        "nocrs_f32.tif": _geotiff(d / "g4.tif", (_terrain(16, 20, 9) * 5).astype(np.float32),
                                  transform=from_origin(0, 100, 2, 2)),
        "merc_f32_256.tif": _geotiff(d / "g5.tif", two, crs="EPSG:3857", transform=from_origin(0, 0, 5, 5),
                                     tiled=True, blockxsize=256, blockysize=256, compress="deflate",
                                     predictor=3),
    }


def _npy(a: np.ndarray, version: tuple[int, int] | None = None) -> bytes:
    import io

    buf = io.BytesIO()
    np.lib.format.write_array(buf, a, version=version, allow_pickle=False)
    return buf.getvalue()


def _npy_seeds() -> dict[str, bytes]:
    t = _terrain(12, 10, 10)
    return {
        "f32.npy": _npy((t * 500).astype(np.float32)),
        "f64_fortran.npy": _npy(np.asfortranarray(t * 3000 - 10)),
        "i16.npy": _npy(np.round(t * 2000).astype(np.int16)),
        "u8_hw1.npy": _npy(np.round(t * 255).astype(np.uint8)[:, :, None]),
        "f16.npy": _npy((t * 100).astype(np.float16)),
        "f4_big.npy": _npy((t * 10).astype(">f4")),
        "f32_v2.npy": _npy((t * 7).astype(np.float32), version=(2, 0)),
    }


@cache
def seeds() -> dict[str, dict[str, bytes]]:
    """target -> {seed file name: bytes}; the same bytes on every call and every run."""
    with tempfile.TemporaryDirectory(prefix="tw-fuzz-seeds-") as tmp:
        d = Path(tmp)
        return {"png": _png_seeds(), "tiff": _tiff_seeds(d), "geotiff": _geotiff_seeds(d), "npy": _npy_seeds()}


def scene_files() -> dict[str, bytes]:
    """The small heightmap files every scene case carries beside its TOML."""
    s = seeds()
    return {"hm.png": s["png"]["gray16.png"], "hm.npy": s["npy"]["f32.npy"],
            "hm.tif": s["geotiff"]["utm_f32_tiled.tif"], "plain.tif": s["tiff"]["f32_lzw.tif"]}


def scene_seeds() -> list[dict[str, Any]]:
    """Valid scene dicts over :func:`scene_files`, between them using every table and key of a scene file."""
    return [
        {"heightmap": {"path": "hm.png", "dx": 10.0, "max_height": 500.0},
         "camera": {"width": 32, "height": 24, "fov_y_deg": 50.0},
         "render": {"outputs": ["image", "depth", "report"], "mesh": "grid"}},
        {"heightmap": {"path": "hm.npy", "dx": 5, "dz": 7.5},
         "camera": {"position": [20.0, 400.0, -60.0], "target": [25.0, 0.0, 45.0], "up": [0.0, 1.0, 0.0],
                    "fov_y_deg": 45.0, "width": 40, "height": 30, "near": 1.0, "far": 100000.0},
         "render": {"mesh": "lod", "shading": "level", "cull_back": True, "light_azimuth_deg": 200.0,
                    "light_elevation_deg": 30.0},
         "lod": {"policy": "sse", "tolerance_px": 2.0, "roots": 1, "tess": 8, "spacing": "fractional_even",
                 "hysteresis": 0.1}},
        {"heightmap": {"path": "hm.tif", "stream": True},
         "camera": {"width": 24, "height": 16},
         "render": {"mesh": "lod", "outputs": ["depth", "report"]},
         "lod": {"policy": "distance", "k": 3.0, "roots": [2, 1], "tess": 4},
         "path": {"kind": "orbit", "radius": 0.5, "elevation": 0.3, "n": 3}},
        {"heightmap": {"fbm": {"rows": 33, "cols": 17, "seed": 3, "max_height": 200.0, "dx": 4.0, "octaves": 3,
                               "gain": 0.5, "lacunarity": 2.0, "ridged": False, "feature_size": 16.0}},
         "camera": {"width": 20, "height": 20},
         "path": {"kind": "flyover", "waypoints": [[0.1, 0.9], [0.9, 0.1]], "clearance": 50.0, "n": 4,
                  "fov_y_deg": 70.0, "units": "fraction"}},
        {"heightmap": {"path": "plain.tif", "dx": 30.0},
         "camera": {"width": 16, "height": 12},
         "render": {"mesh": "lod", "shading": "wireframe", "outputs": ["image", "normals", "curvature"]},
         "lod": {"policy": "continuous", "target_px": 8.0, "level": 2, "tess": 7, "spacing": "fractional_odd",
                 "filter": "bicubic"},
         "path": {"preset": "high", "n": 2}},
        {"heightmap": {"fbm": {"rows": 65, "seed": 1, "octaves": 4}, "stream": True},
         "camera": {"width": 16, "height": 16},
         "path": {"waypoints": [[100.0, 100.0], [500.0, 300.0]], "units": "m", "clearance": 30.0, "n": 2}},
    ]


# ------------------------------------------------------------------------------------------------
# a TOML writer (tomllib only reads)
# ------------------------------------------------------------------------------------------------
def _toml_key(k: str) -> str:
    return k if k and all(c.isalnum() or c in "-_" for c in k) else '"' + _toml_escape(k) + '"'


def _toml_escape(s: str) -> str:
    out = []
    for c in s:
        if c in '"\\':
            out.append("\\" + c)
        elif ord(c) < 0x20 or ord(c) == 0x7F:
            out.append(f"\\u{ord(c):04x}")
        else:
            out.append(c)
    return "".join(out)


def _toml_value(v: object) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return '"' + _toml_escape(v) + '"'
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_toml_key(str(k))} = {_toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(f"no TOML for {type(v).__name__}")


def toml_text(d: dict) -> str:
    """``d`` as TOML: top-level scalars first, then one ``[table]`` per dict (nested dicts inline)."""
    lines = [f"{_toml_key(str(k))} = {_toml_value(v)}" for k, v in d.items() if not isinstance(v, dict)]
    for k, v in d.items():
        if isinstance(v, dict):
            lines.append(f"[{_toml_key(str(k))}]")
            lines += [f"{_toml_key(str(kk))} = {_toml_value(vv)}" for kk, vv in v.items()]
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------------------------
# strategies: byte-level and format-aware mutations
# ------------------------------------------------------------------------------------------------
INTERESTING_BYTES = (0x00, 0x01, 0x7F, 0x80, 0xFE, 0xFF, 0x20, 0x0A)
INTERESTING_INTS = (0, 1, 2, 3, 7, 8, 15, 16, 17, 255, 256, 4096, 4097, 65535, 65536, 0x7FFF, 0x8000, 0x7FFFFFFF,
                    0x80000000, 0xFFFFFFFF, 2**40, 2**63 - 1, -1, -2, -65536)
INTERESTING_FLOATS = (0.0, -0.0, 1.0, -1.0, 0.5, 1e-300, 1e300, -1e300, 1e38, 5e-324, math.inf, -math.inf, math.nan,
                      3.4e38, 91.0, -91.0, 180.0, 1e-9)


@st.composite
def _byte_ops(draw, n: int) -> list[tuple]:
    """1..4 byte-level operations on a file of ``n`` bytes; positions biased toward the first 512."""
    head = max(1, min(n, 512))
    pos = st.one_of(st.integers(0, head - 1), st.integers(0, max(n - 1, 0)))
    op = st.one_of(
        st.tuples(st.just("flip"), pos, st.integers(0, 7)),
        st.tuples(st.just("byte"), pos, st.sampled_from(INTERESTING_BYTES) | st.integers(0, 255)),
        st.tuples(st.just("word"), pos, st.sampled_from((2, 4, 8)), st.sampled_from("<>"),
                  st.sampled_from(INTERESTING_INTS)),
        st.tuples(st.just("truncate"), st.integers(0, max(n - 1, 0))),
        st.tuples(st.just("delete"), pos, st.integers(1, 64)),
        st.tuples(st.just("insert"), pos, st.binary(min_size=1, max_size=32)),
        st.tuples(st.just("dup"), pos, pos, st.integers(1, 256)),
        st.tuples(st.just("fill"), pos, st.integers(1, 4096), st.sampled_from(INTERESTING_BYTES)),
    )
    return draw(st.lists(op, min_size=1, max_size=4))


def _apply_byte_op(b: bytearray, op: tuple) -> bytearray:
    kind, n = op[0], len(b)
    if n == 0:
        return b
    if kind == "flip":
        b[op[1] % n] ^= 1 << op[2]
    elif kind == "byte":
        b[op[1] % n] = op[2]
    elif kind == "word":
        _, p, size, e, v = op
        fmt = {2: "H", 4: "I", 8: "Q"}[size]
        raw = struct.pack(e + fmt, v % (1 << (8 * size)))
        p %= n
        b[p:p + size] = raw[:max(0, min(size, n - p))]
    elif kind == "truncate":
        del b[op[1]:]
    elif kind == "delete":
        del b[op[1] % n:op[1] % n + op[2]]
    elif kind == "insert":
        b[op[1] % n:op[1] % n] = op[2]
    elif kind == "dup":
        src, dst, k = op[1] % n, op[2] % n, op[3]
        b[dst:dst] = b[src:src + k]
    elif kind == "fill":
        p = op[1] % n
        b[p:p + op[2]] = bytes([op[3]]) * len(b[p:p + op[2]])
    return b


@st.composite
def _png_edit(draw) -> tuple:
    fld = draw(st.sampled_from(("width", "height", "bit_depth", "color_type", "compression", "filter", "interlace")))
    if fld in ("width", "height"):
        return ("ihdr", fld, draw(st.sampled_from((0, 1, 2, 3, 100, 65535, 100000, 0x7FFFFFFF, 0x80000000,
                                                   0xFFFFFFFF))))
    return ("ihdr", fld, draw(st.sampled_from((0, 1, 2, 3, 4, 5, 6, 7, 8, 16, 32, 255))))


_IHDR = {"width": (16, ">I"), "height": (20, ">I"), "bit_depth": (24, ">B"), "color_type": (25, ">B"),
         "compression": (26, ">B"), "filter": (27, ">B"), "interlace": (28, ">B")}


@st.composite
def _tiff_edit(draw) -> tuple:
    kind = draw(st.sampled_from(("value", "value", "value", "type", "count", "tag", "ifd")))
    k = draw(st.integers(0, 4095))  # which entry (modulo the number of entries)
    if kind == "value":
        return ("tiff_value", k, draw(st.integers(0, 15)), draw(st.sampled_from(INTERESTING_INTS)),
                draw(st.sampled_from(INTERESTING_FLOATS)))
    if kind == "type":
        return ("tiff_type", k, draw(st.sampled_from((0, 1, 2, 3, 4, 5, 7, 11, 12, 13, 16, 99))))
    if kind == "count":
        return ("tiff_count", k, draw(st.sampled_from((0, 1, 2, 3, 1000, 0xFFFF, 0x7FFFFFFF, 0xFFFFFFFF))))
    if kind == "tag":  # an entry renamed: a required field goes missing, or appears twice
        return ("tiff_tag", k, draw(st.sampled_from((256, 257, 258, 259, 262, 273, 277, 278, 279, 284, 317, 322, 323,
                                                     324, 325, 338, 339, 33550, 33922, 34735, 42113, 0, 65535))))
    return ("tiff_ifd", draw(st.sampled_from((0, 1, 7, 8, 0x7FFFFFFF, 0xFFFFFFFF))))


def _apply_tiff_edit(b: bytearray, op: tuple) -> bytearray:
    e, entries = tiff_entries(bytes(b))
    if op[0] == "tiff_ifd":
        if len(b) >= 8:
            b[4:8] = struct.pack(e + "I", op[1])
        return b
    if not entries:
        return b
    at, tag, typ, count, voff = entries[op[1] % len(entries)]
    if op[0] == "tiff_type":
        b[at + 2:at + 4] = struct.pack(e + "H", op[2])
    elif op[0] == "tiff_count":
        b[at + 4:at + 8] = struct.pack(e + "I", op[2])
    elif op[0] == "tiff_tag":
        b[at:at + 2] = struct.pack(e + "H", op[2])
    elif op[0] == "tiff_value":
        _, _, element, iv, fv = op
        size = _TIFF_TYPE_SIZE.get(typ, 1)
        p = voff + size * (element % max(count, 1))
        if typ in (11, 12):
            raw = struct.pack(e + _TIFF_TYPE_FMT[typ], fv)
        elif typ in (5, 10):  # a rational: numerator, denominator
            raw = struct.pack(e + "II", iv % 2**32, (iv >> 3) % 2**32)
        else:
            raw = struct.pack(e + _TIFF_TYPE_FMT.get(typ, "B").upper(), iv % (1 << (8 * size)))
        if 0 <= p and p + len(raw) <= len(b):
            b[p:p + len(raw)] = raw
    return b


NPY_SHAPES = ((), (0,), (5,), (0, 5), (5, 0), (1, 1), (3, 3, 3), (12, 10, 2), (10, 12), (1, 120), (120, 1),
              (2**31, 2**31), (2**62, 4), (-1, 10), (12, -10), (10**6, 10**6), (12, 10, 1, 1))
NPY_DESCRS = ("<f4", ">f8", "<f2", "<i8", "|u1", "|b1", "<c8", "|O", "<U3", "|V8", "<M8[s]", "<m8[s]", "|S4",
              "<f16", "<i4", "bogus", "", "<f4x")


@st.composite
def _npy_edit(draw) -> tuple:
    kind = draw(st.sampled_from(("shape", "descr", "fortran", "version", "hlen", "text", "keys")))
    if kind == "shape":
        return ("npy_shape", draw(st.sampled_from(NPY_SHAPES)))
    if kind == "descr":
        return ("npy_descr", draw(st.sampled_from(NPY_DESCRS)))
    if kind == "fortran":
        return ("npy_fortran", draw(st.sampled_from((True, False, 1, "yes", None))))
    if kind == "version":
        return ("npy_version", draw(st.sampled_from(((1, 0), (2, 0), (3, 0), (0, 0), (4, 0), (1, 7), (255, 255)))))
    if kind == "hlen":
        return ("npy_hlen", draw(st.sampled_from((0, 1, 10, 70, 118, 127, 128, 1000, 0xFFFF))))
    if kind == "keys":
        return ("npy_keys", draw(st.sampled_from(("drop_shape", "drop_descr", "drop_fortran", "extra", "list_shape",
                                                  "float_shape", "str_shape"))))
    return ("npy_text", draw(st.sampled_from(("{}", "[]", "None", "{'descr': '<f4'}", "1" * 200, "{'shape': (3,)",
                                              "{'descr':'<f4','fortran_order':False,'shape':(2,2),} " + "x" * 40))))


def _apply_npy_edit(b: bytearray, op: tuple) -> bytearray:
    pre, d, body = _npy_split(bytes(b))
    if op[0] == "npy_version":
        if len(b) >= 8:
            b[6:8] = bytes(op[1])
        return b
    if op[0] == "npy_hlen":
        if len(b) >= 10:
            b[8:10] = op[1].to_bytes(2, "little")
        return b
    if op[0] == "npy_text":
        if not pre:
            return b
        text = op[1].encode() + b"\n"
        return bytearray(b"\x93NUMPY\x01\x00" + len(text).to_bytes(2, "little") + text + body)
    if d is None:
        return b
    d = dict(d)
    if op[0] == "npy_shape":
        d["shape"] = op[1]
    elif op[0] == "npy_descr":
        d["descr"] = op[1]
    elif op[0] == "npy_fortran":
        d["fortran_order"] = op[1]
    elif op[0] == "npy_keys":
        k = op[1]
        if k.startswith("drop_"):
            d.pop({"drop_shape": "shape", "drop_descr": "descr", "drop_fortran": "fortran_order"}[k], None)
        elif k == "extra":
            d["extra"] = 1
        elif k in ("list_shape", "float_shape"):
            shape = d.get("shape", ())
            shape = shape if isinstance(shape, tuple | list) and all(isinstance(v, int) for v in shape) else (12, 10)
            d["shape"] = list(shape) if k == "list_shape" else tuple(float(v) for v in shape)
        else:
            d["shape"] = "12, 10"
    version = (b[6], b[7]) if len(b) >= 8 and b[6] in (1, 2, 3) else (1, 0)
    return bytearray(_npy_join(d, body, version))


_GEO_TAGS = {33550: "pixel scale", 33922: "tie point", 34264: "transformation", 34735: "GeoKeys", 42113: "GDAL nodata"}


@st.composite
def _geotiff_edit(draw) -> tuple:
    """An edit of a georeferencing tag's values (pixel scale, tie point, GeoKeys, nodata text)."""
    tag = draw(st.sampled_from(tuple(_GEO_TAGS)))
    return ("geo_value", tag, draw(st.integers(0, 31)), draw(st.sampled_from(INTERESTING_INTS)),
            draw(st.sampled_from(INTERESTING_FLOATS)))


def _apply_geotiff_edit(b: bytearray, op: tuple) -> bytearray:
    _, entries = tiff_entries(bytes(b))
    for k, ent in enumerate(entries):
        if ent[1] == op[1]:
            if ent[2] == 2:  # ASCII nodata: a new text in place
                text = repr(op[4]).encode()[:max(ent[3] - 1, 0)]
                p = ent[4]
                if p + len(text) <= len(b):
                    b[p:p + len(text)] = text
                return b
            return _apply_tiff_edit(b, ("tiff_value", k, op[2], op[3], op[4]))
    return b


def _apply(target: str, data: bytes, ops: list[tuple]) -> bytes:
    b = bytearray(data)
    for op in ops:
        kind = op[0]
        if kind == "ihdr":
            off, fmt = _IHDR[op[1]]
            if len(b) >= off + struct.calcsize(fmt):
                b[off:off + struct.calcsize(fmt)] = struct.pack(fmt, op[2] % (1 << (8 * struct.calcsize(fmt))))
        elif kind == "fixcrc":
            b = _png_fix_crcs(b)
        elif kind.startswith("tiff_"):
            b = _apply_tiff_edit(b, op)
        elif kind == "geo_value":
            b = _apply_geotiff_edit(b, op)
        elif kind.startswith("npy_"):
            b = _apply_npy_edit(b, op)
        elif kind == "splice":
            other = op[1]
            p = op[2] % max(len(b), 1)
            b[p:p + len(other)] = other
        else:
            b = _apply_byte_op(b, op)
    return bytes(b)


# ------------------------------------------------------------------------------------------------
# strategies: the keyword arguments of the loaders
# ------------------------------------------------------------------------------------------------
_SPACING = (None, None, None, 1.0, 30.0, 0, -5.0, math.nan, math.inf, 1e-320, 1e308, "3", True, np.float32(2.5))
_MAX_HEIGHT = (None, None, None, 1000.0, 0.0, -1.0, math.nan, math.inf, 1e308, "100")
_CHANNEL = (0, 0, 0, 1, 2, 3, 4, -1, 1.5, True, 2**40)


@st.composite
def _image_call(draw) -> dict[str, Any]:
    if draw(st.integers(0, 3)):  # mostly the defaults: the file is what is fuzzed
        return {}
    kw = {"dx": draw(st.sampled_from(_SPACING)), "dz": draw(st.sampled_from(_SPACING)),
          "max_height": draw(st.sampled_from(_MAX_HEIGHT)), "channel": draw(st.sampled_from(_CHANNEL)),
          "allow_nan": draw(st.booleans())}
    return {k: v for k, v in kw.items() if v is not None}


_WINDOWS = (((0, 8), (0, 8)), ((2, 5), (1, 9)), ((0, 0), (0, 4)), ((-1, 3), (0, 3)), ((0, 10**6), (0, 3)),
            ((1.5, 3), (0, 2)), "window", ((0, 4),), ((5, 2), (0, 3)))
_BOUNDS = ((500000, 3998600, 501000, 4000000), (0, 0, 1, 1), (1, 2, 1, 2), (math.nan, 0, 1, 1), (1, 2, 3),
           (-84.5, 36.25, -84.49, 36.3))


@st.composite
def _geotiff_call(draw) -> dict[str, Any]:
    how = draw(st.sampled_from(("load", "load", "open", "open", "open_window", "load_kw")))
    kw: dict[str, Any] = {"how": how}
    if how == "load_kw":
        kw.update({"decimate": draw(st.sampled_from((1, 2, 3, 7, 100, 0, -1, 2.0, True))),
                   "resampling": draw(st.sampled_from(("average", "nearest", "cubic", "mode", "bogus", 3))),
                   "channel": draw(st.sampled_from(_CHANNEL))})
        which = draw(st.sampled_from(("window", "bounds", "none", "both")))
        if which in ("window", "both"):
            kw["window"] = draw(st.sampled_from(_WINDOWS))
        if which in ("bounds", "both"):
            kw["bounds"] = draw(st.sampled_from(_BOUNDS))
    if how in ("open", "open_window"):
        kw["band"] = draw(st.sampled_from((1, 1, 1, 2, 0, -1, 1.0, True)))
        kw["cache_mb"] = draw(st.sampled_from((None, None, 1.0, 0.001, 0, -1, math.nan, "8")))
    if how == "open_window":
        kw["window"] = draw(st.sampled_from(((1, 0, 0, 8, 8), (2, 0, 0, 5, 5), (1, 3, 3, 1, 1), (4, 0, 0, 2, 2),
                                             (1, -1, 0, 2, 2), (1, 0, 0, 10**6, 2), (0, 0, 0, 1, 1), (3, 1, 1, 9, 9))))
    if draw(st.integers(0, 4)) == 0:
        kw["dx"], kw["dz"] = draw(st.sampled_from(_SPACING)), draw(st.sampled_from(_SPACING))
    return {k: v for k, v in kw.items() if v is not None}


@st.composite
def file_case(draw, target: str) -> tuple[str, bytes, dict[str, Any], str]:
    """(file name, bytes, call, how) of a mutated seed file of ``target``."""
    pool = seeds()[target]
    name = draw(st.sampled_from(sorted(pool)))
    data = pool[name]
    edits: list[tuple] = []
    aware = {"png": _png_edit(), "tiff": _tiff_edit(), "geotiff": _tiff_edit() | _geotiff_edit(),
             "npy": _npy_edit()}[target]
    kind = draw(st.sampled_from(("none", "bytes", "bytes", "aware", "aware", "both", "splice")))
    if kind in ("aware", "both"):
        edits += draw(st.lists(aware, min_size=1, max_size=3))
    if kind in ("bytes", "both"):
        edits += draw(_byte_ops(len(data)))
    if kind == "splice":  # a chunk of another seed of any format over this one
        others = [(t, n) for t, d in seeds().items() for n in d if (t, n) != (target, name)]
        t, n = draw(st.sampled_from(others))
        od = seeds()[t][n]
        a = draw(st.integers(0, max(len(od) - 1, 0)))
        edits.append(("splice", od[a:a + draw(st.integers(1, 2048))], draw(st.integers(0, 2**20))))
    if target == "png" and edits and draw(st.booleans()):
        edits.append(("fixcrc",))  # libpng reads past the CRC check into the edited data
    call = draw(_geotiff_call() if target == "geotiff" else _image_call())
    return name, _apply(target, data, edits), call, f"{name} {edits!r}"[:2000]


# ------------------------------------------------------------------------------------------------
# strategies: scene TOML
# ------------------------------------------------------------------------------------------------
EDGE_VALUES = (0, 1, -1, 2, 3, 7, 16, 33, 64, 65, 257, 4097, 2**24, 2**24 + 1, 2**31, 2**63 - 1, -2**63, 0.0, -0.0,
               0.5, 1.5, -30.0, 1e-300, 1e300, math.inf, -math.inf, math.nan, True, False, "", "x", "1.0", "nan",
               "jacksboro", "hm.png", "nowhere.png", "hm.tif", ".", "/dev/null", "\x00", "é", [], [1, 2], [1, 2, 3],
               [0.0, 0.0, 0.0], [math.nan, 1.0, 0.0], ["a", "b"], [[0.1, 0.9]], [[0.1]], {}, {"a": 1})
SCENE_KEYS = {
    "": ("heightmap", "camera", "render", "lod", "path"),
    "heightmap": ("example", "path", "dx", "dz", "max_height", "fbm", "stream"),
    "heightmap.fbm": ("rows", "cols", "seed", "max_height", "dx", "dz", "feature_size", "octaves", "gain",
                      "lacunarity", "ridged"),
    "camera": ("position", "target", "up", "fov_y_deg", "width", "height", "near", "far"),
    "render": ("outputs", "mesh", "light_azimuth_deg", "light_elevation_deg", "cull_back", "shading"),
    "lod": ("policy", "tolerance_px", "k", "target_px", "level", "hysteresis", "roots", "tess", "spacing", "filter"),
    "path": ("kind", "waypoints", "clearance", "preset", "n", "radius", "elevation", "units", "fov_y_deg"),
}
# the largest viewport a scene case keeps: the CLI renders what the scene asks for, and a bigger frame is
# work, not a finding (the renderer's own limit, 16384 a side, is tested on its own)
MAX_SCENE_PIXELS = 1 << 16


def _tables(d: dict, prefix: str = "") -> list[tuple[str, dict]]:
    out = [(prefix, d)]
    for k, v in d.items():
        if isinstance(v, dict):
            out += _tables(v, f"{prefix}.{k}" if prefix else k)
    return out


@st.composite
def scene_dict(draw) -> tuple[dict, str]:
    """(a mutated scene dict, how)."""
    import copy

    d = copy.deepcopy(draw(st.sampled_from(scene_seeds())))
    how = []
    for _ in range(draw(st.integers(0, 3))):
        tables = _tables(d)
        where, t = draw(st.sampled_from(tables))
        known = SCENE_KEYS.get(where, ())
        op = draw(st.sampled_from(("set", "set", "set", "set_known", "delete", "unknown", "element")))
        if op == "set" and t:
            k = draw(st.sampled_from(sorted(t)))
            t[k] = copy.deepcopy(draw(st.sampled_from(EDGE_VALUES)))  # EDGE_VALUES' lists stay as they are
        elif op == "set_known" and known:
            k = draw(st.sampled_from(known))
            t[k] = copy.deepcopy(draw(st.sampled_from(EDGE_VALUES)))
        elif op == "delete" and t:
            k = draw(st.sampled_from(sorted(t)))
            del t[k]
        elif op == "unknown":
            t[draw(st.sampled_from(("speed", "Width", "heightmap ", "", "fbm", "camera")))] = 1
        elif op == "element":
            lists = [(k, v) for k, v in t.items() if isinstance(v, list) and v]
            if lists:
                k, v = draw(st.sampled_from(lists))
                v[draw(st.integers(0, len(v) - 1))] = copy.deepcopy(draw(st.sampled_from(EDGE_VALUES)))
        else:
            continue
        how.append(f"{op} in [{where}]")
    cam = d.get("camera")
    if isinstance(cam, dict):
        w, h = cam.get("width", 640), cam.get("height", 480)
        if all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in (w, h)) and w * h > MAX_SCENE_PIXELS:
            cam["width"], cam["height"] = min(w, 256), min(h, 256)
            how.append("viewport capped")
    return d, "; ".join(how)


@st.composite
def toml_case(draw) -> tuple[str, bytes, str]:
    d, how = draw(scene_dict())
    try:
        text = toml_text(d).encode()
    except TypeError:
        text = b"[heightmap]\n"
    if draw(st.integers(0, 4)) == 0:  # and as text: flips, cuts, splices of the TOML
        ops = draw(_byte_ops(len(text)))
        text = _apply("toml", text, ops)
        how += f"; bytes {ops!r}"
    return "scene.toml", text, how


# ------------------------------------------------------------------------------------------------
# strategies: command lines
# ------------------------------------------------------------------------------------------------
CLI_NUMBERS = ("0", "1", "2", "3", "8", "16", "17", "32", "64", "65", "-1", "1.5", "nan", "inf", "-inf", "1e309",
               "2e9", "1e-320", "99999999999999999999", "", " ", "x", "0x10", "1_0", "+4", " 5 ", "٣", "--", "-0")
CLI_WORDS = ("sse", "distance", "continuous", "grid", "lod", "martini", "equal", "fractional_odd", "pow2", "ground",
             "high", "flat", "cliff", "atlantis", "grid,magic", "", "é", "\x00", "-x", "--bogus", "--help")
# benchmark names are never generated: `bench NAME` would run that benchmark (minutes); see cli_case
BENCH_NAMES = ("bintree", "diff", "error_vs_time", "fit", "frame", "fuzz", "lod", "normals_curvature", "outofcore",
               "polytree", "popping", "raster", "schemes", "stability", "sweep", "terrain_frame", "tessellate",
               "threads", "yardstick")
VIEW = ["--width", "16", "--height", "12"]
CLI_BASES = {  # command -> (argument lists the mutations start from)
    "demo": [[*VIEW]],
    "render": [["SCENE", *VIEW], ["SCENE"]],
    "lod": [["SCENE", *VIEW, "--policy", "sse", "--tolerance-px", "4", "--tess", "8", "--roots", "4"],
            [*VIEW, "--policy", "continuous", "--target-px", "16", "--level", "1", "--tess", "5"],
            [*VIEW, "--policy", "distance", "--k", "1", "--hysteresis", "0.2"]],
    "report": [["SCENE", *VIEW, "--frames", "1", "--quick", "--policies", "grid", "--workers", "0", "--no-images",
                "--no-progress"]],
    "fit": [["SCENE", *VIEW, "--frames", "1", "--budget-px", "4", "--no-progress", "--policy", "sse"]],
    "stability": [["--cases", "flat", "--no-progress"], ["--cases", "grid_1x1,tess_nan", "--no-progress"]],
    "tessellate": [["--outer", "3", "5", "1", "2", "--inner", "4", "4"],
                   ["--outer", "1.5", "2", "63.9", "64", "--inner", "7", "0.5", "--spacing", "fractional_odd"]],
    "bench": [["--list"], ["atlantis"]],
    "": [["--version"], ["--help"], []],
}
# options that change what runs and what it costs: a case keeps them (--workers 0: no Dask cluster; the
# frame counts and --quick bound the work of report and fit)
_PINNED = {"report": ("--workers", "0", "--frames", "1", "--quick", "--no-images"), "fit": ("--frames", "1",),
           "stability": ("--cases",)}


@st.composite
def cli_case(draw) -> tuple[list[str], str]:
    """(argv with placeholders SCENE, OUT, FILE for the worker to fill, how)."""
    cmd = draw(st.sampled_from(sorted(CLI_BASES)))
    argv = list(draw(st.sampled_from(CLI_BASES[cmd])))
    how = []
    for _ in range(draw(st.integers(0, 3))):
        op = draw(st.sampled_from(("number", "number", "word", "drop", "dup", "path", "swap")))
        if not argv and op != "path":
            continue
        i = draw(st.integers(0, max(len(argv) - 1, 0)))
        if op == "number" and argv:
            argv[i] = draw(st.sampled_from(CLI_NUMBERS))
        elif op == "word":
            argv[i] = draw(st.sampled_from(CLI_WORDS))
        elif op == "drop":
            del argv[i]
        elif op == "dup":
            argv.insert(i, argv[i])
        elif op == "swap" and len(argv) > 1:
            j = draw(st.integers(0, len(argv) - 1))
            argv[i], argv[j] = argv[j], argv[i]
        elif op == "path":
            argv.insert(i, draw(st.sampled_from(("SCENE", "FILE", "OUT", "/nonexistent/x.toml", "/dev/null", ".",
                                                 "hm.png", "/proc/x"))))
        how.append(op)
    if cmd in _PINNED:  # keep the work small: the pinned options come back with their values
        base = CLI_BASES[cmd][0]
        for opt in _PINNED[cmd]:
            if opt.startswith("--") and opt not in argv and opt in base:
                k = base.index(opt)
                argv += [opt, base[k + 1]] if k + 1 < len(base) and not base[k + 1].startswith("--") else [opt]
    if cmd == "bench" and "--list" not in argv and "--help" not in argv and (
            not [a for a in argv if not a.startswith("-")] or any(a in BENCH_NAMES for a in argv)):
        argv.append("atlantis")  # an unknown name: refused before anything runs
    full = ([cmd] if cmd else []) + argv
    if cmd and cmd not in ("bench", "stability") and "--out" not in full and draw(st.integers(0, 5)):
        full += ["--out", "OUT"]
    if cmd == "stability" and "--out" not in full and draw(st.integers(0, 5)):
        full += ["--out", "OUT"]
    return full, ", ".join(how)


# ------------------------------------------------------------------------------------------------
# the one strategy
# ------------------------------------------------------------------------------------------------
@st.composite
def case_strategy(draw, target: str, index: int = 0) -> Case:
    """A :class:`Case` of ``target`` (one of :data:`TARGETS`)."""
    if target in FILE_TARGETS:
        name, data, call, how = draw(file_case(target))
        ext = Path(name).suffix
        return Case(target, index, f"fz_{target}_{index:05d}{ext}", data, call=call, how=how)
    if target == "toml":
        _, data, how = draw(toml_case())
        return Case(target, index, f"fz_scene_{index:05d}.toml", data, files=scene_files(), how=how)
    argv, how = draw(cli_case())
    d, dhow = draw(scene_dict())
    data = toml_text(d).encode()
    return Case(target, index, f"fz_cli_{index:05d}.toml", data, files=scene_files(), argv=argv,
                how=f"{how}; scene: {dhow}")

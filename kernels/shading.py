"""Resolve and shading: per-pixel interpolation of vertex attributes, one shading kernel for every mode.

Hillshade (the default mode; :func:`hillshade` is :func:`shade` in that mode): Lambert's law with a
directional light (:func:`light_direction`: azimuth/elevation as in GIS hillshading) plus an ambient term,
on a hypsometric tint (colour by height, a fixed 5-stop ramp from low to high over a height range).
Background pixels take a sky colour. :func:`srgb8` encodes the linear colour as the 8-bit sRGB image a
frame saves.

The tint's height range is ``height_range`` when given (the pipeline passes the heightmap's finite height
range, so grid, LOD and every other mesh of the same terrain get the same colour at the same height, and a
flyover's colours do not shift as patches are culled), else the finite heights of the vertices the
triangles use (:func:`height_span`): a vertex no triangle draws (a no-data hole's) never stretches it.

Every frame-sized launch goes through the parallel-launch helper (:mod:`terrainwarp.kernels.parallel`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import warp as wp

from .checks import check_choice
from .noise import hash_u32
from .parallel import empty, launch, view


@wp.func
def _ramp(t: float) -> wp.vec3:
    # green lowlands -> olive -> brown -> grey rock -> snow
    tt = wp.clamp(t, 0.0, 1.0) * 4.0
    k = int(wp.min(wp.floor(tt), 3.0))
    f = tt - float(k)
    c0 = wp.vec3(0.20, 0.42, 0.22)
    c1 = wp.vec3(0.47, 0.55, 0.30)
    c2 = wp.vec3(0.56, 0.45, 0.30)
    c3 = wp.vec3(0.55, 0.52, 0.50)
    c4 = wp.vec3(0.95, 0.95, 0.97)
    a = c0
    b = c1
    if k == 1:
        a = c1
        b = c2
    elif k == 2:
        a = c2
        b = c3
    elif k == 3:
        a = c3
        b = c4
    return a + (b - a) * f


def light_direction(azimuth_deg: float, elevation_deg: float) -> tuple[float, float, float]:
    """The unit vector towards the sun: azimuth clockwise from north (-z), east is +x; elevation above
    the horizon (as in GIS hillshading)."""
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    return (float(np.cos(el) * np.sin(az)), float(np.sin(el)), float(-np.cos(el) * np.cos(az)))


def height_span(heights: np.ndarray, triangles: np.ndarray | None = None,
                height_range: tuple[float, float] | None = None) -> tuple[float, float]:
    """(lowest height, span > 0) of the hypsometric tint's ramp: ``height_range`` (lo, hi) when given, else
    the finite values of ``heights`` ((n,) per vertex, or (H, W) samples) that ``triangles`` ((m, 3)
    indices, when given) use."""
    if height_range is not None:
        lo, hi = (float(v) for v in height_range)
        if not (np.isfinite(lo) and np.isfinite(hi) and hi >= lo):
            raise ValueError(f"height_range: expected finite (lo, hi) with lo <= hi, got {height_range!r}")
        return lo, max(hi - lo, 1e-6)
    h = np.asarray(heights).reshape(-1)
    if triangles is not None:  # only the vertices drawn
        used = np.zeros(h.size, bool)
        used[np.asarray(triangles).reshape(-1)] = True
        h = h[used]
    fin = h[np.isfinite(h)]
    lo = float(fin.min()) if fin.size else 0.0
    span = max(float(fin.max()) - lo, 1e-6) if fin.size else 1.0
    return lo, span


def _srgb_encode(c: float) -> float:
    """The sRGB transfer function (IEC 61966-2-1) of linear ``c`` in [0, 1], in float64."""
    return 12.92 * c if c <= 0.0031308 else 1.055 * c ** (1.0 / 2.4) - 0.055


def _srgb8_thresholds() -> np.ndarray:
    """(255,) float32: entry k-1 is the least float32 linear value that encodes to 8-bit k or more, found by
    bisection over float32 bit patterns with the transfer function in float64 (exact to the float32 input:
    the code is the correctly rounded encoding, the same on every machine, whatever its libm or SIMD)."""
    out = np.empty(255, np.float32)
    for k in range(1, 256):
        lo, hi = 0, int(np.float32(1.0).view(np.uint32))  # bit patterns of non-negative floats are ordered
        while lo < hi:  # least pattern whose value encodes to >= k - 0.5
            mid = (lo + hi) // 2
            if _srgb_encode(float(np.uint32(mid).view(np.float32))) * 255.0 >= k - 0.5:
                hi = mid
            else:
                lo = mid + 1
        out[k - 1] = np.uint32(lo).view(np.float32)
    return out


SRGB8_THRESHOLDS = _srgb8_thresholds()
_T_BITS = SRGB8_THRESHOLDS.view(np.uint32)
_ONE_BITS = 0x3F800000  # 1.0f; non-negative floats order as their bit patterns
# the code of the least float of each 2^16-pattern bucket below 1.0: a bucket spans at most one threshold
_SRGB8_START = np.searchsorted(_T_BITS, np.arange(_ONE_BITS >> 16, dtype=np.uint32) << np.uint32(16),
                               side="right").astype(np.int32)


@wp.func_native("""
uint32_t u;
memcpy(&u, &x, sizeof(u));
return u;
""")
def _float_bits(x: float) -> wp.uint32: ...


@wp.func
def _srgb8_code(u: wp.uint32, t: wp.array(dtype=wp.uint32), start: wp.array(dtype=wp.int32)) -> wp.uint8:
    """The sRGB code of the float32 whose bit pattern is ``u`` (see :func:`srgb8`)."""
    code = int(0)  # negative, -0.0 and NaN encode to 0
    if u >= wp.uint32(0x3F800000) and u <= wp.uint32(0x7F800000):  # [1, +inf]
        code = 255
    elif u < wp.uint32(0x3F800000):
        code = start[int(u >> wp.uint32(16))]
        while code < 255 and t[code] <= u:  # at most one step
            code += 1
    return wp.uint8(code)


@wp.kernel(enable_backward=False)
def _srgb8_kernel(offset: int, bits: wp.array(dtype=wp.uint32), t: wp.array(dtype=wp.uint32),
                  start: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.uint8)):
    i = wp.tid() + offset
    out[i] = _srgb8_code(bits[i], t, start)


def srgb8(rgb: np.ndarray, device: str = "cpu") -> np.ndarray:
    """(..., 3) float linear colour in [0, 1] -> uint8 sRGB (the image a frame saves), correctly rounded:
    each channel is the 8-bit code nearest the exact transfer function of its float32 value (clamped to
    [0, 1]; NaN encodes to 0), looked up in :data:`SRGB8_THRESHOLDS` by the value's bit pattern, so the
    bytes do not depend on the machine's ``pow``. One launch over every channel, split across threads."""
    a = np.ascontiguousarray(rgb, np.float32)
    flat = a.reshape(-1).view(np.uint32)
    out = empty(max(flat.size, 1), wp.uint8, device)
    if flat.size:
        launch(_srgb8_kernel, flat.size, [view(flat, wp.uint32, device), view(_T_BITS, wp.uint32, device),
                                          view(_SRGB8_START, wp.int32, device)], [out], device)
    return out.numpy()[: flat.size].reshape(a.shape)


def hillshade(triangle_id: np.ndarray, barycentrics: np.ndarray, triangles: np.ndarray, normals: np.ndarray,
              heights: np.ndarray, *, azimuth_deg: float = 315.0, elevation_deg: float = 45.0,
              ambient: float = 0.25, sky: tuple[float, float, float] = (0.62, 0.75, 0.90),
              height_range: tuple[float, float] | None = None, device: str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """Shade a frame: :func:`shade` in its ``"hillshade"`` mode (one kernel for every mode).

    Args:
        triangle_id: (H, W) int32 from the visibility pass; barycentrics: (H, W, 2) float32.
        triangles: (m, 3) int32; normals: (n, 3) float32 unit vertex normals; heights: (n,) float32
            world heights per vertex (for the tint).
        azimuth_deg: light azimuth clockwise from north (-z); elevation_deg: above the horizon.
        height_range: (lo, hi) metres the tint's ramp spans; None: the drawn vertices' finite heights
            (:func:`height_span`).

    Returns:
        rgb (H, W, 3) float32 linear in [0, 1], and per-pixel normals (H, W, 3) float32 (0 on background).
    """
    rgb, nrm, _ = shade(triangle_id, barycentrics, triangles, normals, heights, mode="hillshade",
                        azimuth_deg=azimuth_deg, elevation_deg=elevation_deg, ambient=ambient, sky=sky,
                        height_range=height_range, device=device)
    return rgb, nrm


# ------------------------------------------------------------------------------------------------
# shading modes: level / patch colours, wireframe overlay, splat-map multi-texturing, cracks
# ------------------------------------------------------------------------------------------------

SHADING_MODES = ("hillshade", "level", "patch", "wireframe", "splat", "cracks")
CRACK_COLOUR = (1.0, 0.0, 1.0)  # loud magenta: background seen through the terrain
WIRE_COLOUR = (0.05, 0.05, 0.05)

# eight well-separated colours for LOD levels (level % 8)
_LEVEL_COLOURS = np.array([[0.12, 0.47, 0.71], [1.00, 0.50, 0.05], [0.17, 0.63, 0.17], [0.84, 0.15, 0.16],
                           [0.58, 0.40, 0.74], [0.55, 0.34, 0.29], [0.89, 0.47, 0.76], [0.74, 0.74, 0.13]],
                          np.float32)


class SplatRule(NamedTuple):
    """One texture of the splat map (deaconu2021 "Multi-texturing"): where it applies and what it looks like.

    The weight is 1 inside [h_lo, h_hi] x [slope_lo_deg, slope_hi_deg] and falls off smoothly over
    ``blend`` (height, as a fraction of the height range) and ``blend_deg`` (slope) outside.
    The texture is procedural: ``colour`` modulated by value noise of ``scale`` metres and ``contrast``.
    """

    colour: tuple[float, float, float]
    h_lo: float = 0.0
    h_hi: float = 1.0
    slope_lo_deg: float = 0.0
    slope_hi_deg: float = 90.0
    blend: float = 0.05
    blend_deg: float = 5.0
    scale: float = 20.0
    contrast: float = 0.25


# height as a fraction of the terrain's range, slope in degrees: grass, forest, rock, snow, sand
DEFAULT_SPLAT_RULES = (
    SplatRule((0.30, 0.50, 0.20), 0.00, 0.45, 0.0, 25.0, scale=15.0),
    SplatRule((0.16, 0.30, 0.14), 0.20, 0.65, 0.0, 35.0, scale=40.0, contrast=0.35),
    SplatRule((0.45, 0.42, 0.40), 0.00, 1.00, 30.0, 90.0, scale=8.0, contrast=0.3),
    SplatRule((0.93, 0.94, 0.97), 0.70, 1.00, 0.0, 45.0, scale=60.0, contrast=0.08),
    SplatRule((0.76, 0.70, 0.50), 0.00, 0.08, 0.0, 15.0, scale=5.0, contrast=0.15),
)


@wp.func
def _smooth_band(x: float, lo: float, hi: float, band: float) -> float:
    """1 inside [lo, hi], smoothstep down to 0 over ``band`` outside."""
    b = wp.max(band, 1.0e-6)
    a = wp.clamp((x - (lo - b)) / b, 0.0, 1.0)
    c = wp.clamp(((hi + b) - x) / b, 0.0, 1.0)
    return a * a * (3.0 - 2.0 * a) * c * c * (3.0 - 2.0 * c)


@wp.func
def _hash2(ix: int, iz: int, seed: int) -> float:
    """A lattice value in [0, 1]: the terrain noise's integer hash (kernels/noise.py), 24 bits of it."""
    h = hash_u32(wp.uint32(ix), wp.uint32(iz), wp.uint32(seed))
    return float(h & wp.uint32(0xFFFFFF)) / 16777215.0


@wp.func
def _value_noise(x: float, z: float, seed: int) -> float:
    fx = wp.floor(x)
    fz = wp.floor(z)
    ix = int(fx)
    iz = int(fz)
    u = x - fx
    v = z - fz
    u = u * u * (3.0 - 2.0 * u)
    v = v * v * (3.0 - 2.0 * v)
    a = _hash2(ix, iz, seed)
    b = _hash2(ix + 1, iz, seed)
    c = _hash2(ix, iz + 1, seed)
    d = _hash2(ix + 1, iz + 1, seed)
    return (a * (1.0 - u) + b * u) * (1.0 - v) + (c * (1.0 - u) + d * u) * v


@wp.kernel(enable_backward=False)
def _splat_map_kernel(
    offset: int,
    heights: wp.array2d(dtype=wp.float32),
    normals: wp.array2d(dtype=wp.vec3),
    rules: wp.array2d(dtype=wp.float32),
    n_rules: int,
    grid: int,
    h_lo: float,
    h_span: float,
    # outputs
    out_atlas: wp.array3d(dtype=wp.float32),
):
    """Per heightmap sample: the weight of every texture, texture k in atlas cell k // 4 (row-major in a
    grid x grid atlas), channel k % 4 (deaconu2021 figure 9)."""
    i, j = wp.tid()
    i += offset
    hh = heights.shape[0]
    ww = heights.shape[1]
    h = (heights[i, j] - h_lo) / h_span
    slope = wp.acos(wp.clamp(normals[i, j][1], -1.0, 1.0)) * (180.0 / wp.pi)
    for k in range(n_rules):
        w = _smooth_band(h, rules[k, 0], rules[k, 1], rules[k, 4]) * _smooth_band(
            slope, rules[k, 2], rules[k, 3], rules[k, 5])
        cell = k / 4
        cr = cell / grid
        cc = cell - cr * grid
        out_atlas[cr * hh + i, cc * ww + j, k - cell * 4] = w


@wp.func
def _atlas_sample(atlas: wp.array3d(dtype=wp.float32), k: int, grid: int, hh: int, ww: int, uv: wp.vec2) -> float:
    """Bilinear sample of texture k's weight at heightmap uv in [0, 1] (u along columns, v along rows),
    clamped to its own atlas cell."""
    cell = k / 4
    cr = cell / grid
    cc = cell - cr * grid
    x = wp.clamp(uv[0], 0.0, 1.0) * float(ww - 1)
    y = wp.clamp(uv[1], 0.0, 1.0) * float(hh - 1)
    x0 = wp.min(int(wp.floor(x)), ww - 2)
    y0 = wp.min(int(wp.floor(y)), hh - 2)
    x0 = wp.max(x0, 0)
    y0 = wp.max(y0, 0)
    x1 = wp.min(x0 + 1, ww - 1)
    y1 = wp.min(y0 + 1, hh - 1)
    fx = wp.clamp(x - float(x0), 0.0, 1.0)
    fy = wp.clamp(y - float(y0), 0.0, 1.0)
    ch = k - cell * 4
    a = atlas[cr * hh + y0, cc * ww + x0, ch]
    b = atlas[cr * hh + y0, cc * ww + x1, ch]
    c = atlas[cr * hh + y1, cc * ww + x0, ch]
    d = atlas[cr * hh + y1, cc * ww + x1, ch]
    return (a * (1.0 - fx) + b * fx) * (1.0 - fy) + (c * (1.0 - fx) + d * fx) * fy


@wp.func
def _edge_distance_px(c0: wp.vec4, c1: wp.vec4, c2: wp.vec4, px: float, py: float, hw: float, hh: float) -> float:
    """Distance in pixels from window point (px, py) to the nearest edge of the projected triangle
    (infinite when a vertex lies behind the eye, where the projection is not a triangle)."""
    if c0[3] <= 0.0 or c1[3] <= 0.0 or c2[3] <= 0.0:
        return 1.0e30
    a = wp.vec2((c0[0] / c0[3] + 1.0) * hw, (c0[1] / c0[3] + 1.0) * hh)
    b = wp.vec2((c1[0] / c1[3] + 1.0) * hw, (c1[1] / c1[3] + 1.0) * hh)
    c = wp.vec2((c2[0] / c2[3] + 1.0) * hw, (c2[1] / c2[3] + 1.0) * hh)
    p = wp.vec2(px, py)
    d = float(1.0e30)
    e = b - a
    d = wp.min(d, wp.abs(e[0] * (p[1] - a[1]) - e[1] * (p[0] - a[0])) / wp.max(wp.length(e), 1.0e-12))
    e = c - b
    d = wp.min(d, wp.abs(e[0] * (p[1] - b[1]) - e[1] * (p[0] - b[0])) / wp.max(wp.length(e), 1.0e-12))
    e = a - c
    d = wp.min(d, wp.abs(e[0] * (p[1] - c[1]) - e[1] * (p[0] - c[0])) / wp.max(wp.length(e), 1.0e-12))
    return d


@wp.func
def _put(i: int, j: int, rgb: wp.vec3, n: wp.vec3, write: wp.vec3i, t_bits: wp.array(dtype=wp.uint32),
         t_start: wp.array(dtype=wp.int32), out_rgb: wp.array2d(dtype=wp.vec3), out_n: wp.array2d(dtype=wp.vec3),
         out_8: wp.array3d(dtype=wp.uint8)):
    if write[0] != 0:
        out_rgb[i, j] = rgb
    if write[1] != 0:
        out_n[i, j] = n
    if write[2] != 0:  # the bytes srgb8 gives for this float colour
        for c in range(3):
            out_8[i, j, c] = _srgb8_code(_float_bits(rgb[c]), t_bits, t_start)


@wp.kernel(enable_backward=False)
def _shade_kernel(
    offset: int,
    tri_id: wp.array2d(dtype=wp.int32),
    bary: wp.array2d(dtype=wp.vec2),
    tris: wp.array2d(dtype=wp.int32),
    normals: wp.array(dtype=wp.vec3),
    heights: wp.array(dtype=wp.float32),
    vlevel: wp.array(dtype=wp.int32),
    vpatch: wp.array(dtype=wp.int32),
    uv: wp.array(dtype=wp.vec2),
    world_xz: wp.array(dtype=wp.vec2),
    clip: wp.array(dtype=wp.vec4),
    level_colours: wp.array(dtype=wp.vec3),
    atlas: wp.array3d(dtype=wp.float32),
    rules: wp.array2d(dtype=wp.float32),
    n_rules: int,
    grid: int,
    hm_h: int,
    hm_w: int,
    mode: int,
    wire_px: float,
    h_lo: float,
    h_span: float,
    light: wp.vec3,
    ambient: float,
    sky: wp.vec3,
    wire: wp.vec3,
    write: wp.vec3i,  # (float rgb, per-pixel normals, sRGB codes): which outputs this frame needs
    t_bits: wp.array(dtype=wp.uint32),
    t_start: wp.array(dtype=wp.int32),
    # outputs
    out_rgb: wp.array2d(dtype=wp.vec3),
    out_n: wp.array2d(dtype=wp.vec3),
    out_8: wp.array3d(dtype=wp.uint8),
):
    """mode: 0 hillshade, 1 level, 2 patch, 3 wireframe (hillshade + edges), 4 splat. ``write`` says which
    outputs are written (an output not written is a 1 x 1 placeholder)."""
    i, j = wp.tid()
    i += offset
    t = tri_id[i, j]
    if t < 0:
        _put(i, j, sky, wp.vec3(0.0, 0.0, 0.0), write, t_bits, t_start, out_rgb, out_n, out_8)
        return
    b = bary[i, j]
    b2 = 1.0 - b[0] - b[1]
    i0 = tris[t, 0]
    i1 = tris[t, 1]
    i2 = tris[t, 2]
    n = wp.normalize(b[0] * normals[i0] + b[1] * normals[i1] + b2 * normals[i2])
    hgt = b[0] * heights[i0] + b[1] * heights[i1] + b2 * heights[i2]
    shade = ambient + (1.0 - ambient) * wp.max(wp.dot(n, light), 0.0)
    base = _ramp((hgt - h_lo) / h_span)
    if mode == 1:
        base = level_colours[vlevel[i0] % level_colours.shape[0]]
    elif mode == 2:
        base = wp.vec3(0.35 + 0.6 * _hash2(vpatch[i0], 17, 1), 0.35 + 0.6 * _hash2(vpatch[i0], 29, 2),
                       0.35 + 0.6 * _hash2(vpatch[i0], 41, 3))
    elif mode == 4:
        tuv = b[0] * uv[i0] + b[1] * uv[i1] + b2 * uv[i2]
        xz = b[0] * world_xz[i0] + b[1] * world_xz[i1] + b2 * world_xz[i2]
        acc = wp.vec3(0.0, 0.0, 0.0)
        wsum = float(0.0)
        for k in range(n_rules):
            w = _atlas_sample(atlas, k, grid, hm_h, hm_w, tuv)
            if w > 0.0:
                s = rules[k, 9]
                tex = 1.0 + rules[k, 10] * (2.0 * _value_noise(xz[0] / s, xz[1] / s, k) - 1.0)
                acc = acc + w * tex * wp.vec3(rules[k, 6], rules[k, 7], rules[k, 8])
                wsum += w
        if wsum > 0.0:
            base = acc / wsum
    rgb = base * shade
    if mode == 3:
        hh = 0.5 * float(tri_id.shape[0])
        hw = 0.5 * float(tri_id.shape[1])
        d = _edge_distance_px(clip[i0], clip[i1], clip[i2], float(j) + 0.5,
                              float(tri_id.shape[0] - 1 - i) + 0.5, hw, hh)
        if d < wire_px:
            rgb = wire
    _put(i, j, rgb, n, write, t_bits, t_start, out_rgb, out_n, out_8)


@wp.kernel(enable_backward=False)
def _cracks_kernel(
    offset: int,
    tri_id: wp.array2d(dtype=wp.int32),
    reach: int,
    # outputs
    out_crack: wp.array2d(dtype=wp.int32),
):
    """A background pixel is a crack when terrain lies within ``reach`` pixels on both sides of it,
    left and right or above and below: background seen through the surface, not around it."""
    i, j = wp.tid()
    i += offset
    out_crack[i, j] = 0
    if tri_id[i, j] >= 0:
        return
    h = tri_id.shape[0]
    w = tri_id.shape[1]
    left = wp.bool(False)
    right = wp.bool(False)
    up = wp.bool(False)
    down = wp.bool(False)
    for k in range(1, reach + 1):
        if j - k >= 0 and tri_id[i, j - k] >= 0:
            left = True
        if j + k < w and tri_id[i, j + k] >= 0:
            right = True
        if i - k >= 0 and tri_id[i - k, j] >= 0:
            up = True
        if i + k < h and tri_id[i + k, j] >= 0:
            down = True
    if (left and right) or (up and down):
        out_crack[i, j] = 1


def splat_map(heights: np.ndarray, normals: np.ndarray, rules=DEFAULT_SPLAT_RULES, *,
              device: str = "cpu") -> tuple[np.ndarray, int]:
    """The splat map of deaconu2021 "Multi-texturing": texture weights from height and slope rules.

    Args:
        heights: (H, W) float32 heightmap; normals: (H, W, 3) float32 unit normals.
        rules: a sequence of :class:`SplatRule` (heights as fractions of the terrain's range).

    Returns:
        (atlas, grid): atlas (grid*H, grid*W, 4) float32 weights in [0, 1]; texture k lives in cell
        k // 4 (row-major), channel k % 4. ``grid`` is the smallest power of two with
        4 * grid**2 >= len(rules) (5 textures: a 2 x 2 atlas of 4-channel images, as in the paper).
    """
    h = np.asarray(heights, np.float32)
    nrm = np.asarray(normals, np.float32)
    if h.ndim != 2:
        raise ValueError(f"heights: expected shape (H, W), got {h.shape}")
    if nrm.shape != h.shape + (3,):
        raise ValueError(f"normals: expected shape {h.shape + (3,)}, got {nrm.shape}")
    rules = [r if isinstance(r, SplatRule) else SplatRule(*r) for r in rules]
    if not rules:
        raise ValueError("rules: expected at least one SplatRule")
    grid = 1
    while 4 * grid * grid < len(rules):
        grid *= 2
    lo, span = height_span(h)
    atlas = wp.zeros((grid * h.shape[0], grid * h.shape[1], 4), dtype=wp.float32, device=device)
    launch(_splat_map_kernel, h.shape, [
        wp.array(np.nan_to_num(h, nan=lo), dtype=wp.float32, device=device),
        wp.array(np.nan_to_num(nrm), dtype=wp.vec3, device=device),
        wp.array(_rules_table(rules), dtype=wp.float32, device=device), len(rules), grid, lo, span],
        [atlas], device)
    return atlas.numpy(), grid


def _rules_table(rules) -> np.ndarray:
    return np.array([[r.h_lo, r.h_hi, r.slope_lo_deg, r.slope_hi_deg, r.blend, r.blend_deg, *r.colour, r.scale,
                      r.contrast] for r in rules], np.float32).reshape(-1, 11)


def find_cracks(triangle_id: np.ndarray, reach: int = 3, *, device: str = "cpu") -> np.ndarray:
    """(H, W) bool: background pixels with terrain within ``reach`` px on both sides (see _cracks_kernel)."""
    ids = np.ascontiguousarray(triangle_id, dtype=np.int32)
    if ids.ndim != 2:
        raise ValueError(f"triangle_id: expected shape (H, W), got {ids.shape}")
    out = empty(ids.shape, wp.int32, device)
    launch(_cracks_kernel, ids.shape, [wp.array(ids, dtype=wp.int32, device=device), int(reach)], [out], device)
    return out.numpy().astype(bool)


def shade(triangle_id: np.ndarray, barycentrics: np.ndarray, triangles: np.ndarray, normals: np.ndarray,
          heights: np.ndarray, *, mode: str = "hillshade", level: np.ndarray | None = None,
          patch_id: np.ndarray | None = None, uv: np.ndarray | None = None, world_xz: np.ndarray | None = None,
          clip: np.ndarray | None = None, splat: tuple[np.ndarray, int] | None = None,
          rules=DEFAULT_SPLAT_RULES, wire_px: float = 0.6, crack_reach: int = 3,
          azimuth_deg: float = 315.0, elevation_deg: float = 45.0, ambient: float = 0.25,
          sky: tuple[float, float, float] = (0.62, 0.75, 0.90), height_range: tuple[float, float] | None = None,
          encode: bool = False, want_normals: bool = True,
          device: str = "cpu") -> tuple[np.ndarray, np.ndarray | None, dict]:
    """Shade a frame in one of :data:`SHADING_MODES`.

    Args:
        triangle_id (H, W) int32, barycentrics (H, W, 2) float32: the visibility pass.
        triangles (m, 3) int32; normals (n, 3) float32 unit; heights (n,) float32 world heights.
        mode: ``"hillshade"`` (hypsometric tint x Lambert), ``"level"`` (colour by ``level`` (n,) int32),
            ``"patch"`` (colour by ``patch_id`` (n,) int32), ``"wireframe"`` (hillshade with triangle
            edges within ``wire_px`` pixels drawn dark; needs ``clip`` (n, 4) float32, deaconu2021
            figure 10), ``"splat"`` (splat-map multi-texturing; needs ``uv`` (n, 2) heightmap coordinates
            in [0, 1], ``world_xz`` (n, 2) and ``splat`` = :func:`splat_map`'s (atlas, grid) built with
            the same ``rules``), ``"cracks"`` (hillshade; background pixels seen through the terrain in
            magenta, :data:`CRACK_COLOUR`).
        height_range: (lo, hi) metres the hypsometric tint spans (the pipeline gives the heightmap's finite
            height range); None: the finite heights of the vertices ``triangles`` use (:func:`height_span`),
            so a vertex no triangle draws (a no-data hole's) never moves the colours.
        encode: return the 8-bit sRGB image (:func:`srgb8` of the float colour, the same bytes) instead of
            the float colour; the shading kernel encodes each pixel as it shades it (modes "cracks" and
            "wireframe", which post-process the float colour, encode afterwards).
        want_normals: also return the per-pixel normals (False: None, and they are not written).

    Returns:
        rgb (H, W, 3) float32 linear in [0, 1] (uint8 sRGB with ``encode``), per-pixel normals (H, W, 3)
        float32 (or None), and counters (``crack_pixels`` in "cracks" mode, ``edge_pixels`` in "wireframe").
    """
    check_choice("mode", mode, SHADING_MODES)
    ids = np.ascontiguousarray(triangle_id, dtype=np.int32)
    hh, ww = ids.shape
    need = {"level": ("level", level), "patch": ("patch_id", patch_id), "wireframe": ("clip", clip),
            "splat": ("uv", uv)}
    if mode in need and need[mode][1] is None:
        raise ValueError(f"{need[mode][0]}: required by shading mode {mode!r}")
    if mode == "splat" and (world_xz is None or splat is None):
        raise ValueError("splat: mode 'splat' needs world_xz and splat=(atlas, grid) from splat_map")

    def varr(a, shape, dtype, wdt):
        if a is None:
            a = np.zeros((1,) + shape, dtype)
        a = np.ascontiguousarray(a, dtype=dtype)
        if len(a) == 0:
            a = np.zeros((1,) + shape, dtype)
        return view(a, wdt, device)  # a frame's vertices: not copied on the CPU

    light = light_direction(azimuth_deg, elevation_deg)
    lo, span = height_span(heights, triangles, height_range)
    if splat is not None:
        atlas, grid = splat
        atlas = np.ascontiguousarray(atlas, np.float32)
        hm_h, hm_w = atlas.shape[0] // grid, atlas.shape[1] // grid
    else:
        atlas, grid, hm_h, hm_w = np.zeros((2, 2, 4), np.float32), 1, 2, 2
    rtab = _rules_table([r if isinstance(r, SplatRule) else SplatRule(*r) for r in rules])
    code = {"hillshade": 0, "cracks": 0, "level": 1, "patch": 2, "wireframe": 3, "splat": 4}[mode]
    fused = bool(encode) and mode not in ("cracks", "wireframe")
    want_normals = bool(want_normals)
    rgb = empty((1, 1) if fused else (hh, ww), wp.vec3, device)  # outputs not written: 1 x 1 placeholders
    nrm = empty((hh, ww) if want_normals else (1, 1), wp.vec3, device)
    out8 = empty((hh, ww, 3) if fused else (1, 1, 1), wp.uint8, device)
    tri = np.ascontiguousarray(triangles, np.int32).reshape(-1, 3) if len(triangles) else np.zeros((1, 3), np.int32)
    launch(_shade_kernel, (hh, ww), [
        view(ids, wp.int32, device), view(barycentrics, wp.vec2, device), view(tri, wp.int32, device),
        varr(normals, (3,), np.float32, wp.vec3), varr(heights, (), np.float32, wp.float32),
        varr(level, (), np.int32, wp.int32), varr(patch_id, (), np.int32, wp.int32),
        varr(uv, (2,), np.float32, wp.vec2), varr(world_xz, (2,), np.float32, wp.vec2),
        varr(clip, (4,), np.float32, wp.vec4), wp.array(_LEVEL_COLOURS, dtype=wp.vec3, device=device),
        wp.array(atlas, dtype=wp.float32, device=device), wp.array(rtab, dtype=wp.float32, device=device),
        len(rtab), int(grid), int(hm_h), int(hm_w), code, float(wire_px), lo, span, wp.vec3(*light),
        float(ambient), wp.vec3(*sky), wp.vec3(*WIRE_COLOUR), wp.vec3i(int(not fused), int(want_normals), int(fused)),
        view(_T_BITS, wp.uint32, device), view(_SRGB8_START, wp.int32, device)], [rgb, nrm, out8], device)
    normals_px = nrm.numpy() if want_normals else None
    counters: dict = {"mode": mode}
    if fused:
        return out8.numpy(), normals_px, counters
    out = rgb.numpy()
    if mode == "cracks":
        cr = find_cracks(ids, crack_reach, device=device)
        out[cr] = CRACK_COLOUR
        counters["crack_pixels"] = int(cr.sum())
    if mode == "wireframe":
        counters["edge_pixels"] = int(np.all(out == np.float32(WIRE_COLOUR), axis=-1).sum())
    return (srgb8(out, device) if encode else out), normals_px, counters

"""The rasterizer: a visibility pass (coverage and depth test, screen tile by screen tile) and the lazy
barycentric resolve, as Warp kernels.

The rules are OpenGL's as Mesa's llvmpipe implements them (checked pixel for pixel against llvmpipe through EGL in
tests/kernels/test_raster.py, with the same clip-space vertices):

1. Vertices go to clip space in one kernel (``clip = (proj @ view) @ (p, 1)``, the matrix product rounded to
   float32 first, like a uniform); :func:`rasterize_clip` starts from clip coordinates.
2. A triangle is trivially rejected when all three vertices lie outside one clip plane. When a vertex lies outside
   the viewport's x or y planes (llvmpipe here has no guard band: matching its pixels needs the viewport planes),
   or outside near ``z >= -w`` or far ``z <= w``, the triangle is clipped (Sutherland-Hodgman, x and y planes
   first, then near, then far, interpolating from the outside vertex to the inside one, as Mesa's clipper does)
   and drawn as a fan of triangles, each on its own. Clipping far as well as near matters: a vertex with
   ``-w <= z`` but ``z > w`` may have w < 0.
3. Window coordinates are ``x / w * (W / 2) + W / 2`` (fused multiply-add, as llvmpipe's vertex stage), snapped to
   8 sub-pixel bits by rounding half to even (``lrintf``). Zero-area triangles (in fixed point) are dropped, and
   clockwise ones too with ``cull_back``; the others are made counter-clockwise.
4. Coverage: 64-bit integer edge functions at pixel centres with llvmpipe's fill convention for an OpenGL
   framebuffer (lower-left origin): a centre exactly on an edge belongs to the triangle for which the edge is a
   *left* edge or a *bottom* edge in the image (interior above it, window y up). A centre on an edge shared by two
   triangles is covered by exactly one of them.
5. Depth: the plane through the unsnapped window positions (x, y, z_window) of each (fan) triangle, anchored at a
   pixel centre and stepped from it in float32, clamped to [0, 1]. The anchor is the first pixel (lowest x and y)
   of the triangle's pixel box; a large triangle (pixel box of ``SMALL_PX`` or more either way) is anchored again
   in each ``DEPTH_TILE`` x ``DEPTH_TILE`` cell of the screen (its first pixel in the cell). The depth test is
   ``GL_LESS`` against a buffer cleared to 1.0, in submission order (triangle by triangle in index order, a clipped
   triangle's fan in order): a fragment at depth exactly 1.0 is never drawn, and of two at the same depth the
   lower triangle id stays.

How it runs (binning, then one thread per screen tile):

* **vertices** (:func:`_vertex_kernel`): clip coordinates, and per vertex its window position and outcode.
* **bin** (:func:`_bin_kernel`; on the CPU one launch index per chunk of the triangles, on CUDA one per triangle):
  clipping and setup. On the CPU the triangles that lie inside every clip plane and span under ``SMALL_PX`` - 1
  pixels (most terrain triangles) are set up 16 at a time in SIMD lanes (:func:`_bin_lanes`, from the vertices'
  window positions; all three beyond one clip plane: dropped there too): a box of at most 4x4 pixel centres
  becomes a *mask entry* (its 16-bit coverage mask, counted here) when it covers a centre, and is dropped when it
  covers none; a larger box becomes a *record* (its fixed-point vertices); both carry their depth plane
  (:class:`Record`, 32 bytes). Every other triangle (on CUDA, every triangle) goes through :func:`_bin_one`: a
  small unclipped one as a record (or dropped: a box of at most 4 centres covering none), any other drawn one as
  an entry set up again where drawn. Each entry goes into the list of every ``TILE`` x ``TILE`` screen tile its
  pixel box meets (a large one only those its edges do not exclude), one list per tile and launch chunk
  (:class:`Bins`). A chunk's triangles are consecutive and its thread writes them in order, so a tile's lists,
  chunk after chunk, are in submission order (on CUDA the tile sorts its list). The lists are written as they are
  counted when the room kept from the last frame of the same kind holds them; otherwise the counts give exact room
  and the batch is binned again.
* **draw** (:func:`_tile_kernel`): each tile is drawn by one thread (CPU threads take tiles from a shared counter)
  in a scratch tile that fits the cache, which starts as the background and is copied into the images at the
  end (a tile with nothing to draw gets the background straight in the images): mask entries as one 16-lane SIMD
  block each (:func:`_draw_masks`), records row by row, 8 pixel centres at a time in SIMD (edge functions,
  coverage mask, depth, test and write, :func:`_draw_records`), the others in 4x4 blocks rejected or accepted
  whole by their corners, else given a 16-bit mask (:func:`_cover`); CUDA draws every entry in 4x4 blocks, in the
  images themselves. The depth test and the writes need no atomics, and the pipeline statistics are counted on
  the way (samples passed as the test passes in submission order, quads and blocks from the masks).
  Frames of more than ``BATCH`` triangles go through bin and draw in batches, in order.

The barycentrics of :class:`Fragments` are computed on first access from the clip-space vertices: with
``a_i = x_i - px*w_i`` and ``c_i = y_i - py*w_i`` (px, py the centre in NDC) they are
``cross(a, c) / sum(cross(a, c))``, exact for clipped triangles too. Interpolation of attributes is the
differentiable path's (``terrainwarp.diff.interpolate``, ``kernels/gradients.py``).

Output images have row 0 at the top (window y is flipped once, here).
"""

import functools
from collections.abc import Callable

import numpy as np
import warp as wp

from .checks import check_bool, check_triangles, check_viewport
from .counters import (
    T_BINNED,
    T_BLOCKS,
    T_CLIPPED,
    T_COVERED,
    T_INSIDE,
    T_PASSED,
    T_QUADS,
    T_RASTERIZED,
    T_TESTED,
    T_TILE16,
    TALLIES,
    raster_counters,
    raster_stats,
)
from .device import device_named
from .parallel import atomic_add_i32, chunks, launch, launch_one, max_parts
from .parallel import view as as_warp  # 'view' is a view matrix here
from .pool import filled_array, pooled_arrays, pooled_rows_array, take

__all__ = ["Fragments", "rasterize", "rasterize_clip", "clip_coordinates", "clip_barycentrics", "pixel_ndc",
           "SUBPIXEL", "TILE"]

SUBPIXEL_BITS = 8
SUBPIXEL = 1 << SUBPIXEL_BITS
SUBPIXEL_HALF = SUBPIXEL // 2
GUARD_BAND_PX = 0.0  # x and y are clipped at the viewport itself, as llvmpipe does (its pixels match then)
TILE = 64  # screen tile edge in pixels: one thread draws a tile
DEPTH_TILE = 16  # the screen cells in which a large triangle's depth plane is anchored again
SMALL_PX = 16  # a triangle whose pixel box spans fewer pixels than this each way is small
BATCH = 1 << 22  # triangles binned and drawn at a time (bounds the lists' memory)
MARGIN = 4  # pixels of a CPU thread's scratch tile left of and below the tile (a mask entry's 4x4 from any pixel)
PITCH = MARGIN + TILE + 16  # pixels per row of a scratch tile: a row's 16 lanes from any pixel of the tile
SCRATCH_ROWS = MARGIN + TILE + MARGIN
# the fewest items worth a CPU thread of their own, per launch (see parallel.launch)
_MIN_TRIANGLES = 2048
_MIN_VERTICES = 1 << 16  # a vertex costs ~2 ns: fewer per thread are not worth the hand-off
_MIN_PIXELS = 32768
_BACKGROUND_BITS = 0x3F800000  # 1.0f

poly9 = wp.types.matrix(shape=(9, 4), dtype=wp.float32)
vec9l = wp.types.vector(length=9, dtype=wp.int64)
vec9f = wp.types.vector(length=9, dtype=wp.float32)
vec8l = wp.types.vector(length=8, dtype=wp.int64)


@wp.struct
class Record:
    """A small unclipped triangle in a tile's list (32 bytes): its depth plane (``plane``: the depth at the first
    centre of its pixel box, dz/dx, dz/dy), its index ``t`` and in ``xy`` either its CCW fixed-point vertices (a
    record: a, then b - a and c - a as int16 pairs; ``xy[3]`` is not 0, c differing from a) or (a mask entry,
    ``xy[3]`` 0) the first centre of its box (x | y << 16) and the coverage of the 4x4 centres from it (``xy[1]``,
    bit 4 j + i for centre (x + i, y + j)). ``t`` < 0: triangle ``-1 - t``, set up again where drawn (nothing else
    is set)."""

    xy: wp.vec4i
    plane: wp.vec3
    t: int


@wp.struct
class Bins:
    """The screen tiles' lists of a batch. Cell ``tile * nparts + part`` (a tile and a chunk of the binning launch,
    whose triangles are consecutive) lists the chunk's triangles that the tile draws, in order, at
    ``entries[start[cell]:start[cell] + count[cell]]``: ``t`` for a record, ``-1 - t`` for a triangle set up again
    where drawn. ``emit`` 0: the binning only counts (``count``); 1: it also writes the entries, each cell holding
    at most ``room[cell]`` (past that ``overflow[0]`` is set and the batch is binned again with exact room)."""

    tiles_x: int
    nparts: int
    emit: int
    start: wp.array(dtype=wp.int32)
    room: wp.array(dtype=wp.int32)
    count: wp.array(dtype=wp.int32)
    entries: wp.array(dtype=Record)
    overflow: wp.array(dtype=wp.int32)


# ------------------------------------------------------------------------------------------------
# functions: clipping and setup
# ------------------------------------------------------------------------------------------------


@wp.func
def _clip_poly(poly: poly9, n: int, plane: wp.vec4) -> tuple[poly9, int]:
    """Sutherland-Hodgman clip of an n-gon (rows of poly) against dot(plane, v) >= 0."""
    out = poly9()
    m = int(0)  # noqa: UP018 -- a mutable Warp int
    for k in range(n):
        a = poly[k]
        b = poly[(k + 1) % n]
        da = wp.dot(plane, a)
        db = wp.dot(plane, b)
        if da >= 0.0:
            out[m] = a
            m += 1
        if (da >= 0.0) != (db >= 0.0):
            # from the outside vertex towards the inside one, as Mesa's clipper interpolates
            if da < 0.0:
                out[m] = a + (da / (da - db)) * (b - a)
            else:
                out[m] = b + (db / (db - da)) * (a - b)
            m += 1
    return out, m


@wp.func_native("""return fmaf(a, b, c);""")
def _fma(a: float, b: float, c: float) -> float: ...


@wp.func
def _pixel_lo(v: wp.int64) -> int:
    """Smallest pixel index whose centre (k * 256 + 128) is >= the fixed-point coordinate v."""
    return int((v - wp.int64(SUBPIXEL_HALF) + wp.int64(SUBPIXEL - 1)) >> wp.int64(SUBPIXEL_BITS))


@wp.func
def _pixel_hi(v: wp.int64) -> int:
    """Largest pixel index whose centre is <= v (arithmetic shift = floor division by 256)."""
    return int((v - wp.int64(SUBPIXEL_HALF)) >> wp.int64(SUBPIXEL_BITS))


@wp.func
def _snap(v: float) -> wp.int64:
    """A window coordinate in fixed point: rounded half to even, as llvmpipe's util_iround (lrintf)."""
    return wp.int64(wp.rint(v * float(SUBPIXEL)))


@wp.func
def _inside(c: wp.vec4, gb: wp.vec2) -> wp.bool:
    return wp.abs(c[0]) <= gb[0] * c[3] and wp.abs(c[1]) <= gb[1] * c[3] and wp.abs(c[2]) <= c[3]


@wp.func
def _window(c: wp.vec4, hw: float, hh: float) -> wp.vec3:
    """Window (x, y, depth) of a clip-space vertex with w > 0, as llvmpipe's vertex stage computes it:
    x / w * scale + translate, fused."""
    iw = 1.0 / c[3]
    return wp.vec3(_fma(c[0] * iw, hw, hw), _fma(c[1] * iw, hh, hh), _fma(c[2] * iw, 0.5, 0.5))


@wp.func
def _same(a: wp.vec4, b: wp.vec4) -> wp.bool:
    return a[0] == b[0] and a[1] == b[1] and a[2] == b[2] and a[3] == b[3]


@wp.func
def _window_unfused(c: wp.vec4, hw: float, hh: float) -> wp.vec3:
    iw = 1.0 / c[3]
    return wp.vec3(c[0] * iw * hw + hw, c[1] * iw * hh + hh, c[2] * iw * 0.5 + 0.5)


@wp.func
def _rejected(c0: wp.vec4, c1: wp.vec4, c2: wp.vec4) -> wp.bool:
    """All three vertices outside one clip plane."""
    reject = wp.bool(False)
    if c0[0] > c0[3] and c1[0] > c1[3] and c2[0] > c2[3]:
        reject = True
    if c0[0] < -c0[3] and c1[0] < -c1[3] and c2[0] < -c2[3]:
        reject = True
    if c0[1] > c0[3] and c1[1] > c1[3] and c2[1] > c2[3]:
        reject = True
    if c0[1] < -c0[3] and c1[1] < -c1[3] and c2[1] < -c2[3]:
        reject = True
    if c0[2] > c0[3] and c1[2] > c1[3] and c2[2] > c2[3]:
        reject = True
    if c0[2] < -c0[3] and c1[2] < -c1[3] and c2[2] < -c2[3]:
        reject = True
    return reject


@wp.func
def _clipped(c0: wp.vec4, c1: wp.vec4, c2: wp.vec4, gb: wp.vec2):
    """The triangle clipped by the guard-band x and y planes (when a vertex lies outside them), then near, then far
    (Mesa's clipper order): (polygon, vertex count)."""
    poly = poly9()
    poly[0] = c0
    poly[1] = c1
    poly[2] = c2
    n = int(3)
    outside = wp.bool(False)
    for k in range(n):
        v = poly[k]
        if wp.abs(v[0]) > gb[0] * v[3] or wp.abs(v[1]) > gb[1] * v[3]:
            outside = True
    if outside:
        poly, n = _clip_poly(poly, n, wp.vec4(-1.0, 0.0, 0.0, gb[0]))
        poly, n = _clip_poly(poly, n, wp.vec4(1.0, 0.0, 0.0, gb[0]))
        poly, n = _clip_poly(poly, n, wp.vec4(0.0, -1.0, 0.0, gb[1]))
        poly, n = _clip_poly(poly, n, wp.vec4(0.0, 1.0, 0.0, gb[1]))
    if c0[2] < -c0[3] or c1[2] < -c1[3] or c2[2] < -c2[3]:
        poly, n = _clip_poly(poly, n, wp.vec4(0.0, 0.0, 1.0, 1.0))
    # the far plane too, geometrically, when a vertex lies beyond it: such a vertex may have w < 0
    # (-w <= z and z > w), and only after both clips is w >= |z| >= 0 for every vertex
    if c0[2] > c0[3] or c1[2] > c1[3] or c2[2] > c2[3]:
        poly, n = _clip_poly(poly, n, wp.vec4(0.0, 0.0, -1.0, 1.0))
    return poly, n


@wp.func
def _setup(c0: wp.vec4, c1: wp.vec4, c2: wp.vec4, width: int, height: int, gb: wp.vec2):
    """Trivial reject, clipping (:func:`_clipped`), viewport transform and snapping.

    Returns (n, xs, ys, fxs, fys, zs): the clipped convex polygon with n vertices (0 when rejected), window x and y
    in fixed point (8 sub-pixel bits, pixel centres at k * 256 + 128), the same in float before snapping, and
    window depth.
    """
    xs = vec9l()
    ys = vec9l()
    fxs = vec9f()
    fys = vec9f()
    zs = vec9f()
    n = int(0)  # noqa: UP018 -- a mutable Warp int
    hw = 0.5 * float(width)
    hh = 0.5 * float(height)
    if _inside(c0, gb) and _inside(c1, gb) and _inside(c2, gb) and c0[3] > 0.0 and c1[3] > 0.0 and c2[3] > 0.0:
        # nothing to reject or clip: the polygon is the triangle, each vertex on llvmpipe's fused path
        n = 3
        fa = _window(c0, hw, hh)
        fb = _window(c1, hw, hh)
        fc = _window(c2, hw, hh)
        fxs = vec9f(fa[0], fb[0], fc[0], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        fys = vec9f(fa[1], fb[1], fc[1], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        zs = vec9f(fa[2], fb[2], fc[2], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        for k in range(3):
            xs[k] = _snap(fxs[k])
            ys[k] = _snap(fys[k])
        return n, xs, ys, fxs, fys, zs
    if _rejected(c0, c1, c2):
        return n, xs, ys, fxs, fys, zs
    poly, m = _clipped(c0, c1, c2, gb)
    if m < 3:
        return n, xs, ys, fxs, fys, zs
    for k in range(m):
        if poly[k][3] <= 0.0:
            return n, xs, ys, fxs, fys, zs
    n = m
    for k in range(n):
        v = poly[k]
        f = _window(v, hw, hh)
        if not (_same(v, c0) or _same(v, c1) or _same(v, c2)):
            # a vertex made by the clipper: Mesa computes its window position in C, x * (1 / w) * scale
            # + translate with separate roundings (the original vertices come from its fused JIT path)
            f = _window_unfused(v, hw, hh)
        fxs[k] = f[0]
        fys[k] = f[1]
        zs[k] = f[2]
        xs[k] = _snap(f[0])
        ys[k] = _snap(f[1])
    return n, xs, ys, fxs, fys, zs


@wp.func
def _poly_pixels(n: int, xs: vec9l, ys: vec9l, width: int, height: int) -> wp.vec4i:
    """Pixel index range (x0, x1, y0, y1) whose centres may be covered, clamped to the viewport."""
    xmin = xs[0]
    xmax = xs[0]
    ymin = ys[0]
    ymax = ys[0]
    for k in range(1, n):
        xmin = wp.min(xmin, xs[k])
        xmax = wp.max(xmax, xs[k])
        ymin = wp.min(ymin, ys[k])
        ymax = wp.max(ymax, ys[k])
    return wp.vec4i(wp.max(0, _pixel_lo(xmin)), wp.min(width - 1, _pixel_hi(xmax)),
                    wp.max(0, _pixel_lo(ymin)), wp.min(height - 1, _pixel_hi(ymax)))


@wp.func
def _tri_box(ax: wp.int64, ay: wp.int64, bx: wp.int64, by: wp.int64, cx: wp.int64, cy: wp.int64, width: int,
             height: int) -> wp.vec4i:
    """The pixel box (x0, x1, y0, y1) of a triangle's possibly covered centres, clamped to the viewport."""
    xmin = wp.min(ax, wp.min(bx, cx))
    xmax = wp.max(ax, wp.max(bx, cx))
    ymin = wp.min(ay, wp.min(by, cy))
    ymax = wp.max(ay, wp.max(by, cy))
    return wp.vec4i(wp.max(0, _pixel_lo(xmin)), wp.min(width - 1, _pixel_hi(xmax)),
                    wp.max(0, _pixel_lo(ymin)), wp.min(height - 1, _pixel_hi(ymax)))


@wp.func
def _fan_tri(xs: vec9l, ys: vec9l, k: int, cull_back: int):
    """Fan triangle (0, k, k+1) made counter-clockwise; returns (ok, order) with order 0 = as is,
    1 = vertices k and k+1 swapped; ok is False for zero area or a culled back face."""
    area = (xs[k] - xs[0]) * (ys[k + 1] - ys[0]) - (xs[k + 1] - xs[0]) * (ys[k] - ys[0])
    ok = area != wp.int64(0)
    if cull_back != 0 and area < wp.int64(0):
        ok = False
    swap = int(0)  # noqa: UP018 -- a mutable Warp int
    if area < wp.int64(0):
        swap = 1
    return ok, swap


@wp.func
def _edge_bias(dx: wp.int64, dy: wp.int64) -> wp.int64:
    """0 for an edge a->b (of a CCW triangle, window y up) whose centres are covered, -1 for one whose are not:
    llvmpipe's convention for GL framebuffers includes a left edge (it runs downwards, dy < 0, interior at +x)
    and a horizontal edge with the interior above it (dx > 0), the triangle's bottom edge in the image."""
    if dy < wp.int64(0) or (dy == wp.int64(0) and dx > wp.int64(0)):
        return wp.int64(0)
    return wp.int64(-1)


@wp.func
def _edge_misses_rect(ax: wp.int64, ay: wp.int64, bx: wp.int64, by: wp.int64, x0: wp.int64, y0: wp.int64,
                      x1: wp.int64, y1: wp.int64) -> wp.bool:
    """Whether edge a->b's function (with its fill-rule bias) is negative at every pixel centre of the
    rectangle: tested at the corner where the edge function is largest."""
    ex = x0
    ey = y0
    if ay - by > wp.int64(0):
        ex = x1
    if bx - ax > wp.int64(0):
        ey = y1
    return (bx - ax) * (ey - ay) - (by - ay) * (ex - ax) + _edge_bias(bx - ax, by - ay) < wp.int64(0)


@wp.func
def _tri_rect(ax: wp.int64, ay: wp.int64, bx: wp.int64, by: wp.int64, cx: wp.int64, cy: wp.int64,
              r: wp.vec4i) -> wp.bool:
    """Whether the CCW triangle may cover a pixel centre of the pixel rectangle r = (x0, x1, y0, y1)."""
    half = wp.int64(SUBPIXEL_HALF)
    one = wp.int64(SUBPIXEL)
    x0 = wp.int64(r[0]) * one + half
    x1 = wp.int64(r[1]) * one + half
    y0 = wp.int64(r[2]) * one + half
    y1 = wp.int64(r[3]) * one + half
    if _edge_misses_rect(bx, by, cx, cy, x0, y0, x1, y1):
        return False
    if _edge_misses_rect(cx, cy, ax, ay, x0, y0, x1, y1):
        return False
    if _edge_misses_rect(ax, ay, bx, by, x0, y0, x1, y1):
        return False
    return True


@wp.func
def _poly_rect(n: int, xs: vec9l, ys: vec9l, r: wp.vec4i, cull_back: int) -> wp.bool:
    """Whether some drawable fan triangle of the polygon may cover a pixel centre of rectangle r."""
    hit = wp.bool(False)
    for k in range(1, n - 1):
        ok, swap = _fan_tri(xs, ys, k, cull_back)
        if ok and not hit:
            kb = k + swap
            kc = k + 1 - swap
            if _tri_rect(xs[0], ys[0], xs[kb], ys[kb], xs[kc], ys[kc], r):
                hit = True
    return hit


@wp.func
def _cell_rect(x: int, y: int, size: int, width: int, height: int) -> wp.vec4i:
    """The pixels (x0, x1, y0, y1) of screen cell (x, y) of a grid of ``size``-pixel cells, inside the viewport."""
    return wp.vec4i(x * size, wp.min(x * size + size - 1, width - 1), y * size, wp.min(y * size + size - 1, height - 1))


@wp.func
def _front_facing(c0: wp.vec4, c1: wp.vec4, c2: wp.vec4) -> wp.bool:
    """Counter-clockwise in homogeneous coordinates: det[(x, y, w) of the three vertices] > 0 (the sign of the
    window-space area when every w > 0, and defined for any w), in float64."""
    a = wp.vec3d(wp.float64(c0[0]), wp.float64(c0[1]), wp.float64(c0[3]))
    b = wp.vec3d(wp.float64(c1[0]), wp.float64(c1[1]), wp.float64(c1[3]))
    c = wp.vec3d(wp.float64(c2[0]), wp.float64(c2[1]), wp.float64(c2[3]))
    return wp.dot(a, wp.cross(b, c)) > wp.float64(0.0)


@wp.func
def _fast_setup(c0: wp.vec4, c1: wp.vec4, c2: wp.vec4, width: int, height: int, cull_back: int):
    """The setup of a triangle inside every clip plane (no clipping, no polygon arrays). Returns (drawn: not
    zero-area nor a culled back face, small: a fixed-point extent below SMALL_PX - 1 pixels each way, the CCW
    vertices in fixed point (ax, ay, bx, by, cx, cy) and in float (fa, fb, fc), its pixel box (:func:`_tri_box`))."""
    hw = 0.5 * float(width)
    hh = 0.5 * float(height)
    fa = _window(c0, hw, hh)
    fb = _window(c1, hw, hh)
    fc = _window(c2, hw, hh)
    ax = _snap(fa[0])
    ay = _snap(fa[1])
    bx = _snap(fb[0])
    by = _snap(fb[1])
    cx = _snap(fc[0])
    cy = _snap(fc[1])
    area = (bx - ax) * (cy - ay) - (cx - ax) * (by - ay)
    drawn = not (area == wp.int64(0) or (cull_back != 0 and area < wp.int64(0)))
    if area < wp.int64(0):
        qx = bx
        qy = by
        qf = fb
        bx = cx
        by = cy
        fb = fc
        cx = qx
        cy = qy
        fc = qf
    xmin = wp.min(ax, wp.min(bx, cx))
    xmax = wp.max(ax, wp.max(bx, cx))
    ymin = wp.min(ay, wp.min(by, cy))
    ymax = wp.max(ay, wp.max(by, cy))
    small = xmax - xmin < wp.int64((SMALL_PX - 1) * SUBPIXEL) and ymax - ymin < wp.int64((SMALL_PX - 1) * SUBPIXEL)
    return drawn, small, ax, ay, bx, by, cx, cy, fa, fb, fc, _tri_box(ax, ay, bx, by, cx, cy, width, height)


@wp.func
def _prepared(c0: wp.vec4, c1: wp.vec4, c2: wp.vec4, width: int, height: int, cull_back: int, gb: wp.vec2):
    """A triangle set up for drawing: (n, xs, ys, fxs, fys, zs, box, mode, fast, inside3). A triangle inside every
    clip plane that is small (:func:`_fast_setup`) is ``fast``: its CCW vertices are the polygon (n = 3); the
    others go through :func:`_setup`. ``box``: the polygon's pixel box; ``mode`` 0: nothing to draw (rejected,
    zero-area or culled, an empty box, no drawable fan triangle), 1: small (depth anchored once per fan triangle),
    2: large (anchored per DEPTH_TILE cell); ``inside3``: every vertex inside every clip plane."""
    xs = vec9l()
    ys = vec9l()
    fxs = vec9f()
    fys = vec9f()
    zs = vec9f()
    inside3 = _inside(c0, gb) and _inside(c1, gb) and _inside(c2, gb)
    box = wp.vec4i(0, -1, 0, -1)
    if inside3:
        drawn, small, ax, ay, bx, by, cx, cy, fa, fb, fc, box = _fast_setup(c0, c1, c2, width, height, cull_back)
        if not drawn:
            return 0, xs, ys, fxs, fys, zs, box, 0, True, inside3
        if small:
            xs = vec9l(ax, bx, cx, wp.int64(0), wp.int64(0), wp.int64(0), wp.int64(0), wp.int64(0), wp.int64(0))
            ys = vec9l(ay, by, cy, wp.int64(0), wp.int64(0), wp.int64(0), wp.int64(0), wp.int64(0), wp.int64(0))
            fxs = vec9f(fa[0], fb[0], fc[0], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
            fys = vec9f(fa[1], fb[1], fc[1], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
            zs = vec9f(fa[2], fb[2], fc[2], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
            return 3, xs, ys, fxs, fys, zs, box, wp.where(box[0] <= box[1] and box[2] <= box[3], 1, 0), True, inside3
    n, xs, ys, fxs, fys, zs = _setup(c0, c1, c2, width, height, gb)
    mode = int(0)
    if n > 0:
        box = _poly_pixels(n, xs, ys, width, height)
        if box[0] <= box[1] and box[2] <= box[3]:
            for k in range(1, n - 1):
                ok, swap = _fan_tri(xs, ys, k, cull_back)
                if ok:
                    mode = 1
            if mode == 1 and not (box[1] - box[0] < SMALL_PX and box[3] - box[2] < SMALL_PX):
                mode = 2
    return n, xs, ys, fxs, fys, zs, box, mode, False, inside3


@wp.func
def _depth_plane(fa: wp.vec3, fb: wp.vec3, fc: wp.vec3):
    """(dz/dx, dz/dy) of the plane through the window positions (x, y, depth) of a triangle's vertices, as
    llvmpipe's triangle setup computes it from the unsnapped coordinates."""
    dx01 = fa[0] - fb[0]
    dy01 = fa[1] - fb[1]
    dx20 = fc[0] - fa[0]
    dy20 = fc[1] - fa[1]
    ooa = 1.0 / (dx01 * dy20 - dx20 * dy01)
    dz01 = fa[2] - fb[2]
    dz20 = fc[2] - fa[2]
    dzdx = (dz01 * dy20 - dz20 * dy01) * ooa
    dzdy = (dx01 * dz20 - dx20 * dz01) * ooa
    return dzdx, dzdy


@wp.func
def _depth_at(fa: wp.vec3, dzdx: float, dzdy: float, px: int, py: int) -> float:
    """The depth plane at the centre of pixel (px, py): the anchor the pixels around it step from."""
    return fa[2] - (dzdx * (fa[0] - (float(px) + 0.5)) + dzdy * (fa[1] - (float(py) + 0.5)))


# ------------------------------------------------------------------------------------------------
# functions: coverage and depth into a tile's buffer
# ------------------------------------------------------------------------------------------------
# A tile is drawn into a buffer of ids and depth bits (the images' own on CUDA; on the CPU a scratch tile of
# TILE rows of PITCH pixels per thread, copied into the images when the tile is done): pixel (x, y) of the window
# is element ``bb + (y - oy) * stride + (x - ox)`` of it.


@wp.func_native("""
#if defined(__CUDA_ARCH__)
#define RZ_POPC(x) __popc(x)
#define RZ_CTZ(x) (__ffs(x) - 1)
#else
#define RZ_POPC(x) __builtin_popcount(x)
#define RZ_CTZ(x) __builtin_ctz(x)
#endif
#if !defined(__CUDA_ARCH__)
#pragma clang fp contract(off)
#endif
wp::vec_t<8, wp::int64> acc;
for (int k = 0; k < 8; ++k) acc[k] = 0;
if (x0 > x1 || y0 > y1) return acc;
int32_t* ids = (int32_t*)buf_id.data;
uint32_t* dep = (uint32_t*)buf_depth.data;
const int64_t S = 256, HALF = 128;
// edge k from vertex k + 1 to k + 2 (a, b, c): at centre (sx, sy) (qx - px) (sy - py) - (qy - py) (sx - px) + bias,
// its steps per pixel, and the most and the least it adds over a 4x4 block to its value at the first centre
const int64_t vx[3] = {ax, bx, cx}, vy[3] = {ay, by, cy};
int64_t px[3], py[3], dx[3], dy[3], bias[3], hi[3], lo[3];
for (int k = 0; k < 3; ++k) {
    px[k] = vx[(k + 1) % 3], py[k] = vy[(k + 1) % 3], dx[k] = vx[(k + 2) % 3] - px[k], dy[k] = vy[(k + 2) % 3] - py[k];
    bias[k] = (dy[k] < 0 || (dy[k] == 0 && dx[k] > 0)) ? 0 : -1;
    hi[k] = 3 * S * ((dy[k] < 0 ? -dy[k] : 0) + (dx[k] > 0 ? dx[k] : 0));
    lo[k] = 3 * S * ((dy[k] > 0 ? -dy[k] : 0) + (dx[k] < 0 ? dx[k] : 0));
}
int64_t tested = 0, inside = 0, passed = 0, covered = 0, quads = 0, blocks = 0;
for (int qy = y0 & ~3; qy <= y1; qy += 4) {
    const int r0 = y0 > qy ? y0 - qy : 0, r1 = y1 < qy + 3 ? y1 - qy : 3;
    const uint32_t rows = ((1u << (4 * r1 + 4)) - 1u) & ~((1u << (4 * r0)) - 1u);
    const int64_t sy = (int64_t)qy * S + HALF;
    for (int qx = x0 & ~3; qx <= x1; qx += 4) {
        const int k0 = x0 > qx ? x0 - qx : 0, k1 = x1 < qx + 3 ? x1 - qx : 3;
        const uint32_t rect = rows & ((((1u << (k1 + 1)) - 1u) & ~((1u << k0) - 1u)) * 0x1111u);
        const int64_t sx = (int64_t)qx * S + HALF;
        int64_t e[3];
        bool out = false, all = true;
        for (int k = 0; k < 3; ++k) {
            e[k] = dx[k] * (sy - py[k]) - dy[k] * (sx - px[k]) + bias[k];
            out = out || e[k] + hi[k] < 0;
            all = all && e[k] + lo[k] >= 0;
        }
        if (out) continue;  // no centre of the block inside
        tested += RZ_POPC(rect);
        uint32_t m = 0xFFFFu;
        for (int j = 0; j < 4 && !all; ++j) {  // not every centre inside: the block's mask
            for (int i = 0; i < 4; ++i) {
                const int64_t v = (e[0] + S * (j * dx[0] - i * dy[0])) | (e[1] + S * (j * dx[1] - i * dy[1]))
                                  | (e[2] + S * (j * dx[2] - i * dy[2]));
                m = (m & ~(1u << (4 * j + i))) | ((uint32_t)(v >= 0) << (4 * j + i));
            }
        }
        m &= rect;
        if (m == 0) continue;
        inside += RZ_POPC(m);
        quads += RZ_POPC((m | (m >> 1) | (m >> 4) | (m >> 5)) & 0x0505u);
        blocks += 1;
        while (m != 0) {
            const int i = RZ_CTZ(m);
            m &= m - 1u;
            const int x = qx + (i & 3), y = qy + (i >> 2);
            // the anchor's depth stepped to the centre: two roundings per axis, rows first
            const float ty = dzdy * (float)(y - ry);
            const float zr = z00 + ty;
            const float tx = dzdx * (float)(x - rx);
            const float d = wp::clamp(zr + tx, 0.0f, 1.0f);
            if (!(d < 1.0f)) continue;  // GL_LESS against the cleared 1.0
            union { float f; uint32_t u; } b;
            b.f = d;
            const int64_t p = (int64_t)bb + (int64_t)(y - oy) * stride + (x - ox);
            const bool first = ids[p] < 0;
            if (first || b.u < dep[p]) {  // non-negative floats order as their bits
                ids[p] = tid;
                dep[p] = b.u;
                passed += 1;
                covered += first ? 1 : 0;
            }
        }
    }
}
acc[0] = tested, acc[1] = inside, acc[2] = passed, acc[3] = covered, acc[4] = quads, acc[5] = blocks;
return acc;
#undef RZ_POPC
#undef RZ_CTZ
""")
def _cover(ax: wp.int64, ay: wp.int64, bx: wp.int64, by: wp.int64, cx: wp.int64, cy: wp.int64, x0: int, x1: int,
           y0: int, y1: int, rx: int, ry: int, z00: float, dzdx: float, dzdy: float, tid: int, ox: int, oy: int,
           bb: int, stride: int, buf_id: wp.array(dtype=wp.int32), buf_depth: wp.array(dtype=wp.float32)) -> vec8l:
    """The CCW fixed-point triangle a, b, c over pixels (x0..x1, y0..y1) of a tile's buffer (``bb``, ``stride``,
    origin (ox, oy)) in window-aligned 4x4 blocks: skipped or covered whole by their corners, else a 16-bit mask
    from their centres' int64 edge functions. A covered centre's depth is ``z00`` (at pixel (rx, ry)) stepped by
    ``dzdy`` rows then ``dzdx`` columns, clamped to [0, 1]; passing ``GL_LESS`` it writes ``tid`` and its depth.
    Returns (centres tested, covered, passed, pixels covered anew, 2x2 quads and 4x4 blocks covered, 0, 0)."""
    ...


@wp.func_native("""
wp::vec_t<8, wp::int64> acc;
for (int k = 0; k < 8; ++k) acc[k] = k == 6 ? j0 : 0;
#if !defined(__CUDA_ARCH__)
if (simd != 0) {
#pragma clang fp contract(off)
typedef int32_t v8 __attribute__((vector_size(32))); typedef uint32_t v8u __attribute__((vector_size(32)));
typedef float v8f __attribute__((vector_size(32))); typedef bool b8 __attribute__((ext_vector_type(8)));
typedef int32_t v8_ld __attribute__((vector_size(32), aligned(4)));  // loads and stores at any pixel
typedef uint32_t v8u_ld __attribute__((vector_size(32), aligned(4)));
auto signs = [](v8 v) { return (uint32_t)__builtin_bit_cast(uint8_t, __builtin_convertvector(v < 0, b8)); };
// a record's pixel box: its first centre at or after the least coordinate, its last at or before the largest
auto lo = [](const int64_t* v) { return wp::max(0, (int)((wp::min(v[0], wp::min(v[1], v[2])) + 127) >> 8)); };
auto hi = [](const int64_t* v) { return (int)((wp::max(v[0], wp::max(v[1], v[2])) - 128) >> 8); };
const v8 lane = {0, 1, 2, 3, 4, 5, 6, 7};
int32_t* __restrict ids = (int32_t*)buf_id.data;
uint32_t* __restrict dep = (uint32_t*)buf_depth.data;
int64_t j = j0;
for (; j < j1 && entries.data[j].t >= 0 && entries.data[j].xy[3] != 0; ++j) {
    const auto& r = entries.data[j];  // a record: the vertices a (x[0]), b, c
    const int64_t x[3] = {r.xy[0], r.xy[0] + (int16_t)(r.xy[2] & 0xFFFF), r.xy[0] + (int16_t)(r.xy[3] & 0xFFFF)};
    const int64_t y[3] = {r.xy[1], r.xy[1] + (r.xy[2] >> 16), r.xy[1] + (r.xy[3] >> 16)};
    const int rx = lo(x), ry = lo(y), x0 = wp::max(rx, tx0), x1 = wp::min(hi(x), tx1);
    const int y0 = wp::max(ry, ty0), y1 = wp::min(hi(y), ty1);
    if (x0 > x1 || y0 > y1) continue;
    // edge k from vertex k + 1 to k + 2 at the first centre of the rows, and per pixel down a row: a record's
    // triangle spans under SMALL_PX pixels, so over 16 centres of a row its edge functions fit in int32
    v8 ra[2][3], dy[3];
    for (int k = 0; k < 3; ++k) {
        const int64_t px = x[(k + 1) % 3], py = y[(k + 1) % 3], dx = x[(k + 2) % 3] - px, ey = y[(k + 2) % 3] - py;
        const int64_t e = dx * ((int64_t)y0 * 256 + 128 - py) - ey * ((int64_t)x0 * 256 + 128 - px)
                          + ((ey < 0 || (ey == 0 && dx > 0)) ? 0 : -1);
        ra[0][k] = (int32_t)e + lane * (int32_t)(-ey * 256);
        ra[1][k] = ra[0][k] + 8 * (int32_t)(-ey * 256);
        dy[k] = lane - lane + (int32_t)(dx * 256);
    }
    const v8f tx[2] = {r.plane[1] * __builtin_convertvector(lane + (x0 - rx), v8f),
                       r.plane[1] * __builtin_convertvector(lane + (x0 + 8 - rx), v8f)};
    const uint32_t cols = (uint32_t)((1u << (x1 - x0 + 1)) - 1u);
    const int nch = x1 - x0 >= 8 ? 2 : 1;  // a row in chunks of 8 centres: two when it is wider
    uint32_t qrow = 0, brow = 0;
    acc[0] += (int64_t)(x1 - x0 + 1) * (y1 - y0 + 1);
    for (int yy = y0; yy <= y1; ++yy) {
        uint32_t mc[2] = {0, 0};
        for (int c = 0; c < nch; ++c) {
            mc[c] = ~signs(ra[c][0] | ra[c][1] | ra[c][2]) & (cols >> (8 * c)) & 0xFFu;
            for (int k = 0; k < 3; ++k) ra[c][k] += dy[k];
        }
        const uint32_t m = mc[0] | (mc[1] << 8);
        qrow |= m << (x0 & 3);  // the row's centres from the first 4-aligned column: quads, then blocks, done
        brow |= m << (x0 & 3);
        if ((yy & 1) == 1 || yy == y1) acc[4] += __builtin_popcount((qrow | qrow >> 1) & 0x55555u), qrow = 0;
        const uint32_t bm = brow | brow >> 1 | brow >> 2 | brow >> 3;
        if ((yy & 3) == 3 || yy == y1) acc[5] += __builtin_popcount(bm & 0x11111u), brow = 0;
        acc[1] += __builtin_popcount(m);
        // the anchor's depth stepped to the row, then to each centre: two roundings per axis, as set up
        const float zr = r.plane[0] + r.plane[2] * (float)(yy - ry);
        const int64_t p0 = (int64_t)bb + (int64_t)(yy - ty0) * stride + (x0 - tx0);
        for (int c = 0; c < nch; ++c) {
            if (mc[c] == 0) continue;
            const v8f d0 = zr + tx[c];
            const v8f d1 = d0 > 0.0f ? d0 : 0.0f;  // wp::clamp(d, 0, 1) on the host: NaN and -0.0 become 0.0
            const v8f d = d1 <= 1.0f ? d1 : 1.0f;
            const v8u bits = (v8u)d;
            int32_t* pi = ids + p0 + 8 * c;
            uint32_t* pd = dep + p0 + 8 * c;
            const v8 oid = *(const v8_ld*)pi;
            const v8u od = *(const v8u_ld*)pd;
            const v8 first = oid < 0;
            // GL_LESS (depth bits order as depths) at a covered centre
            const v8 win = ((((lane - lane + (int32_t)mc[c]) >> lane) & 1) != 0) & (d < 1.0f) & (first | (bits < od));
            const uint32_t wm = signs(win);
            if (wm != 0) {
                *(v8_ld*)pi = win ? (v8)(lane - lane + r.t) : oid;
                *(v8u_ld*)pd = win ? bits : od;
                acc[2] += __builtin_popcount(wm), acc[3] += __builtin_popcount(wm & signs(first));
            }
        }
    }
}
acc[6] = j;
}
#endif
return acc;
""")
def _draw_records(simd: int, entries: wp.array(dtype=Record), j0: int, j1: int, tx0: int, tx1: int, ty0: int,
                  ty1: int, width: int, height: int, bb: int, stride: int, buf_id: wp.array(dtype=wp.int32),
                  buf_depth: wp.array(dtype=wp.float32)) -> vec8l:
    """With ``simd`` (a CPU scratch tile), list entries from ``j0`` while they are records, over the tile's pixels
    (tx0..tx1, ty0..ty1; buffer origin (tx0, ty0)), row by row in chunks of 8 centres (SIMD, int32 lanes): mask,
    depths, tests, writes. The same pixels, depths and counts as :func:`_cover`; returns them, the entry it stopped
    at in slot 6 (``j0`` without ``simd`` and on CUDA)."""
    ...


@wp.func_native("""
wp::vec_t<8, wp::int64> acc;
for (int k = 0; k < 8; ++k) acc[k] = k == 6 ? j0 : 0;
#if !defined(__CUDA_ARCH__)
if (simd != 0) {
#pragma clang fp contract(off)
typedef int32_t v16 __attribute__((vector_size(64))); typedef uint32_t v16u __attribute__((vector_size(64)));
typedef float v16f __attribute__((vector_size(64))); typedef bool b16 __attribute__((ext_vector_type(16)));
auto bits = [](v16 c) { return (uint32_t)__builtin_bit_cast(uint16_t, __builtin_convertvector(c, b16)); };
const v16 lane = {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15};
const v16f col = __builtin_convertvector(lane & 3, v16f), row = __builtin_convertvector(lane >> 2, v16f);
int32_t* __restrict ids = (int32_t*)buf_id.data;
int32_t* __restrict dep = (int32_t*)buf_depth.data;
int64_t j = j0;
for (; j < j1 && entries.data[j].t >= 0 && entries.data[j].xy[3] == 0; ++j) {
    const auto& r = entries.data[j];
    const int rx = r.xy[0] & 0xFFFF, ry = r.xy[0] >> 16;
    // its centres in this tile; of those, 2x2 quads (the mask in 6-bit rows from an even pixel) and 4x4 blocks
    // (the mask's part in each block) with a covered one
    const uint32_t cols = (0xFu << wp::max(0, tx0 - rx)) & (0xFu >> wp::max(0, rx + 3 - tx1));
    const uint32_t m = (uint32_t)r.xy[1] & (cols & 0xFu) * 0x1111u & (0xFFFFu << 4 * wp::max(0, ty0 - ry))
                       & (0xFFFFu >> 4 * wp::max(0, ry + 3 - ty1));
    const uint32_t m6 = ((m & 0xFu) | (m & 0xF0u) << 2 | (m & 0xF00u) << 4 | (m & 0xF000u) << 6)
                        << ((rx & 1) + 6 * (ry & 1));
    const uint32_t cl = ((1u << (4 - (rx & 3))) - 1u) * 0x1111u, rb = (1u << (4 * (4 - (ry & 3)))) - 1u;
    acc[1] += __builtin_popcount(m), acc[4] += __builtin_popcount((m6 | m6 >> 1 | m6 >> 6 | m6 >> 7) & 0x15015015u);
    acc[5] += ((m & cl & rb) != 0) + ((m & ~cl & rb) != 0) + ((m & cl & ~rb) != 0) + ((m & ~cl & ~rb) != 0);
    // the anchor's depth stepped to the row, then to each centre (as a record's), clamped as wp::clamp
    const v16f d0 = (r.plane[0] + r.plane[2] * row) + r.plane[1] * col;
    const v16f d1 = d0 > 0.0f ? d0 : 0.0f;
    const v16f d = d1 <= 1.0f ? d1 : 1.0f;
    // the 4x4 pixels from (rx, ry) in the buffer (its margin holds those past the tile), tested and written
    const int64_t p = (int64_t)bb + (int64_t)(ry - ty0) * stride + (rx - tx0);
    int32_t oi[16], od[16];
    for (int k = 0; k < 4; ++k) __builtin_memcpy(oi + 4 * k, ids + p + k * stride, 16);
    for (int k = 0; k < 4; ++k) __builtin_memcpy(od + 4 * k, dep + p + k * stride, 16);
    v16 vi, vd;
    __builtin_memcpy(&vi, oi, 64), __builtin_memcpy(&vd, od, 64);
    const v16 first = vi < 0;
    const v16 win = ((((v16u)(lane - lane) + m) >> (v16u)lane & 1) != 0) & (d < 1.0f) & (first | ((v16u)d < (v16u)vd));
    vi = win ? lane - lane + r.t : vi, vd = win ? (v16)d : vd;
    __builtin_memcpy(oi, &vi, 64), __builtin_memcpy(od, &vd, 64);
    for (int k = 0; k < 4; ++k) __builtin_memcpy(ids + p + k * stride, oi + 4 * k, 16);
    for (int k = 0; k < 4; ++k) __builtin_memcpy(dep + p + k * stride, od + 4 * k, 16);
    acc[2] += __builtin_popcount(bits(win)), acc[3] += __builtin_popcount(bits(win & first));
}
acc[6] = j;
}
#endif
return acc;
""")
def _draw_masks(simd: int, entries: wp.array(dtype=Record), j0: int, j1: int, tx0: int, tx1: int, ty0: int,
                ty1: int, bb: int, stride: int, buf_id: wp.array(dtype=wp.int32),
                buf_depth: wp.array(dtype=wp.float32)) -> vec8l:
    """With ``simd`` (a CPU scratch tile, with a margin of MARGIN pixels around it), list entries from ``j0`` while
    they are mask entries (:func:`_bin_lanes`), over the tile's pixels (tx0..tx1, ty0..ty1; buffer origin (tx0,
    ty0)), each as one 16-lane SIMD block of its 4x4 centres: mask, depths, tests, writes. The same pixels, depths
    and counts as :func:`_draw_records` would give; returns them (0 centres tested: they were counted as it was
    binned), the entry it stopped at in slot 6 (``j0`` without ``simd`` and on CUDA)."""
    ...


@wp.func
def _record(ax: wp.int64, ay: wp.int64, bx: wp.int64, by: wp.int64, cx: wp.int64, cy: wp.int64, z00: float,
            dzdx: float, dzdy: float, t: int) -> Record:
    """Triangle ``t``'s :class:`Record`, or, when its vertices do not fit one, its entry as a triangle set up again
    where drawn."""
    r = Record()
    r.t = -1 - t
    lim = wp.int64(1) << wp.int64(31)
    fits = ax >= -lim and ax < lim and ay >= -lim and ay < lim
    d = wp.vec4l(bx - ax, by - ay, cx - ax, cy - ay)
    for k in range(4):
        if d[k] < wp.int64(-32768) or d[k] > wp.int64(32767):
            fits = False
    if fits:
        r.xy = wp.vec4i(int(ax), int(ay), (int(bx - ax) & 0xFFFF) | (int(by - ay) << 16),
                        (int(cx - ax) & 0xFFFF) | (int(cy - ay) << 16))
        r.plane = wp.vec3(z00, dzdx, dzdy)
        r.t = t
    return r


@wp.func
def _lo16(v: int) -> int:
    """The signed 16-bit number in the low half of ``v``."""
    return ((v & 0xFFFF) ^ 0x8000) - 0x8000


@wp.func_native("""
#if defined(__x86_64__) && !defined(__CUDA_ARCH__)
typedef int32_t v4 __attribute__((vector_size(16)));
// a row of n values from s (or all c) to d: non-temporal stores, 16 bytes at a time where d is aligned
auto row = [](int32_t* d, const int32_t* s, int32_t c, int n) {
    int x = 0;
    for (; x < n && (reinterpret_cast<unsigned long long>(d + x) & 15) != 0; ++x)
        __builtin_nontemporal_store(s ? s[x] : c, d + x);
    for (; x + 4 <= n; x += 4) {
        v4 v = (v4){c, c, c, c};
        if (s) __builtin_memcpy(&v, s + x, 16);
        __builtin_nontemporal_store(v, (v4*)(d + x));
    }
    for (; x < n; ++x) __builtin_nontemporal_store(s ? s[x] : c, d + x);
};
#endif
for (int y = 0; y < h; ++y) {
    const int64_t p = (int64_t)sb + (int64_t)y * sstride, q = (int64_t)db + (int64_t)y * dstride;
    const int32_t* si = src ? (const int32_t*)src_id.data + p : nullptr;
    const int32_t* sd = src ? (const int32_t*)src_depth.data + p : nullptr;
    int32_t* di = (int32_t*)dst_id.data + q;
    int32_t* dd = (int32_t*)dst_depth.data + q;
#if defined(__x86_64__) && !defined(__CUDA_ARCH__)
    if (nt) {  // the images: written once here and not read again by the pass
        row(di, si, -1, w), row(dd, sd, 0x3F800000, w);
        continue;
    }
#endif
    for (int x = 0; x < w; ++x) di[x] = si ? si[x] : -1;
    for (int x = 0; x < w; ++x) dd[x] = sd ? sd[x] : 0x3F800000;
}
#if defined(__x86_64__) && !defined(__CUDA_ARCH__)
if (nt) __builtin_ia32_sfence();  // the non-temporal stores visible before anything later
#endif
""")
def _copy(src: int, sb: int, sstride: int, db: int, dstride: int, w: int, h: int, nt: int,
          src_id: wp.array(dtype=wp.int32), src_depth: wp.array(dtype=wp.float32), dst_id: wp.array(dtype=wp.int32),
          dst_depth: wp.array(dtype=wp.float32)):
    """``h`` rows of ``w`` pixels (ids and depth) from one buffer to another, or with ``src`` 0 the background (id
    -1, depth 1.0); with ``nt`` (on the CPU, into the images) in non-temporal stores, a fence after them."""
    ...


@wp.func
def _draw_fan(ax: wp.int64, ay: wp.int64, bx: wp.int64, by: wp.int64, cx: wp.int64, cy: wp.int64, fa: wp.vec3,
              fb: wp.vec3, fc: wp.vec3, t: int, mode: int, tile: wp.vec4i, width: int, height: int, bb: int,
              stride: int, buf_id: wp.array(dtype=wp.int32), buf_depth: wp.array(dtype=wp.float32)) -> vec8l:
    """One CCW (fan) triangle over one screen tile (:func:`_cover`): small (``mode`` 1), its depth anchored at its
    box's first pixel; large (2), anchored again in each DEPTH_TILE cell (at the triangle's first pixel there)."""
    box = _tri_box(ax, ay, bx, by, cx, cy, width, height)
    x0 = wp.max(box[0], tile[0])
    x1 = wp.min(box[1], tile[1])
    y0 = wp.max(box[2], tile[2])
    y1 = wp.min(box[3], tile[3])
    acc = vec8l()
    if x0 > x1 or y0 > y1:
        return acc
    dzdx, dzdy = _depth_plane(fa, fb, fc)
    if mode == 1:
        z00 = _depth_at(fa, dzdx, dzdy, box[0], box[2])
        return _cover(ax, ay, bx, by, cx, cy, x0, x1, y0, y1, box[0], box[2], z00, dzdx, dzdy, t, tile[0], tile[2],
                      bb, stride, buf_id, buf_depth)
    for gy in range(y0 / DEPTH_TILE, y1 / DEPTH_TILE + 1):
        for gx in range(x0 / DEPTH_TILE, x1 / DEPTH_TILE + 1):
            sx = wp.max(x0, gx * DEPTH_TILE)
            sy = wp.max(y0, gy * DEPTH_TILE)
            z00 = _depth_at(fa, dzdx, dzdy, sx, sy)
            acc = acc + _cover(ax, ay, bx, by, cx, cy, sx, wp.min(x1, gx * DEPTH_TILE + DEPTH_TILE - 1), sy,
                               wp.min(y1, gy * DEPTH_TILE + DEPTH_TILE - 1), sx, sy, z00, dzdx, dzdy, t, tile[0],
                               tile[2], bb, stride, buf_id, buf_depth)
    return acc


@wp.func
def _draw_prepared(t: int, c0: wp.vec4, c1: wp.vec4, c2: wp.vec4, tile: wp.vec4i, width: int, height: int,
                   cull_back: int, gb: wp.vec2, bb: int, stride: int, buf_id: wp.array(dtype=wp.int32),
                   buf_depth: wp.array(dtype=wp.float32)) -> vec8l:
    """Triangle ``t`` set up again (:func:`_prepared`) and drawn over one screen tile: its fan in order."""
    n, xs, ys, fxs, fys, zs, box, mode, fast, inside3 = _prepared(c0, c1, c2, width, height, cull_back, gb)
    acc = vec8l()
    if mode == 0:
        return acc
    if fast:
        return _draw_fan(xs[0], ys[0], xs[1], ys[1], xs[2], ys[2], wp.vec3(fxs[0], fys[0], zs[0]),
                         wp.vec3(fxs[1], fys[1], zs[1]), wp.vec3(fxs[2], fys[2], zs[2]), t, 1, tile, width, height,
                         bb, stride, buf_id, buf_depth)
    for k in range(1, n - 1):
        ok, swap = _fan_tri(xs, ys, k, cull_back)
        if ok:
            kb = k + swap
            kc = k + 1 - swap
            acc = acc + _draw_fan(xs[0], ys[0], xs[kb], ys[kb], xs[kc], ys[kc], wp.vec3(fxs[0], fys[0], zs[0]),
                                  wp.vec3(fxs[kb], fys[kb], zs[kb]), wp.vec3(fxs[kc], fys[kc], zs[kc]), t, mode,
                                  tile, width, height, bb, stride, buf_id, buf_depth)
    return acc


@wp.func
def _tile16_count(n: int, xs: vec9l, ys: vec9l, box: wp.vec4i, cull_back: int, width: int, height: int) -> int:
    """The DEPTH_TILE cells of ``box`` that some drawable fan triangle may cover (by their corners)."""
    cells = int(0)  # noqa: UP018 -- a mutable Warp int
    for gy in range(box[2] / DEPTH_TILE, box[3] / DEPTH_TILE + 1):
        for gx in range(box[0] / DEPTH_TILE, box[1] / DEPTH_TILE + 1):
            if _poly_rect(n, xs, ys, _cell_rect(gx, gy, DEPTH_TILE, width, height), cull_back):
                cells += 1
    return cells


@wp.func
def _bin(entry: Record, n: int, xs: vec9l, ys: vec9l, box: wp.vec4i, large: wp.bool, cull_back: int, width: int,
         height: int, part: int, bins: Bins):
    """``entry`` into the lists (:class:`Bins`) of the screen tiles of ``box`` (of a large triangle, those its
    edges do not exclude), for chunk ``part``."""
    for ty in range(box[2] / TILE, box[3] / TILE + 1):
        for tx in range(box[0] / TILE, box[1] / TILE + 1):
            if not large or _poly_rect(n, xs, ys, _cell_rect(tx, ty, TILE, width, height), cull_back):
                cell = (ty * bins.tiles_x + tx) * bins.nparts + part
                slot = wp.atomic_add(bins.count, cell, 1)  # one chunk per part: a plain add on the CPU
                if bins.emit != 0:
                    if slot < bins.room[cell]:
                        bins.entries[bins.start[cell] + slot] = entry
                    else:
                        bins.overflow[0] = 1


# ------------------------------------------------------------------------------------------------
# kernels
# ------------------------------------------------------------------------------------------------


@wp.func_native("""
#if defined(__CUDA_ARCH__)
const float x = c[0], y = c[1], z = c[2], w = c[3];
const int code = (x > w) | (x < -w) << 1 | (y > w) << 2 | (y < -w) << 3 | (z > w) << 4 | (z < -w) << 5;
const bool inside = wp::abs(x) <= gb[0] * w && wp::abs(y) <= gb[1] * w && wp::abs(z) <= w;
#else
typedef float v4f __attribute__((vector_size(16))); typedef int32_t v4i __attribute__((vector_size(16)));
const v4f v = {c[0], c[1], c[2], 0.0f}, w = {c[3], c[3], c[3], 0.0f}, lim = {gb[0] * c[3], gb[1] * c[3], c[3], 0.0f};
const v4i above = {1, 4, 16, 0}, below = {2, 8, 32, 0};
const int code = __builtin_reduce_or(((v > w) & above) | ((v < -w) & below));
const bool inside = __builtin_reduce_and(__builtin_elementwise_abs(v) <= lim) != 0;
#endif
return (float)(code | (inside ? 0 : 64));
""")
def _outcode(c: wp.vec4, gb: wp.vec2) -> float:
    """A clip-space vertex's outcode: 1, 2, 4, 8, 16, 32 for x > w, x < -w, y > w, y < -w, z > w, z < -w
    (:func:`_rejected`'s tests), 64 when it is not :func:`_inside` (as a float)."""
    ...


@wp.kernel(enable_backward=False)
def _vertex_kernel(
    offset: int,
    pos: wp.array(dtype=wp.vec3),
    mvp: wp.mat44,
    transform: int,
    width: int,
    height: int,
    gb: wp.vec2,
    # outputs
    out_clip: wp.array(dtype=wp.vec4),
    out_win: wp.array(dtype=wp.vec4),
):
    """Per vertex: its clip coordinates (with ``transform`` ``mvp @ (p, 1)``, written to ``out_clip``; else read from
    it) and its window position (:func:`_window`) in ``out_win``, whose w holds its :func:`_outcode`."""
    k = wp.tid() + offset
    c = wp.vec4()
    if transform != 0:
        p = pos[k]
        c = mvp * wp.vec4(p[0], p[1], p[2], 1.0)
        out_clip[k] = c
    else:
        c = out_clip[k]
    f = _window(c, 0.5 * float(width), 0.5 * float(height))
    out_win[k] = wp.vec4(f[0], f[1], f[2], _outcode(c, gb))


@wp.func
def _covers_none(ax: wp.int64, ay: wp.int64, bx: wp.int64, by: wp.int64, cx: wp.int64, cy: wp.int64,
                 box: wp.vec4i) -> wp.bool:
    """Whether a CCW triangle whose pixel box holds at most 4 centres covers none of them (tested one by one; a
    larger box: False)."""
    if (box[1] - box[0] + 1) * (box[3] - box[2] + 1) > 4:
        return False
    for y in range(box[2], box[3] + 1):
        for x in range(box[0], box[1] + 1):
            sx = wp.int64(x) * wp.int64(SUBPIXEL) + wp.int64(SUBPIXEL_HALF)
            sy = wp.int64(y) * wp.int64(SUBPIXEL) + wp.int64(SUBPIXEL_HALF)
            e0 = (cx - bx) * (sy - by) - (cy - by) * (sx - bx) + _edge_bias(cx - bx, cy - by)
            e1 = (ax - cx) * (sy - cy) - (ay - cy) * (sx - cx) + _edge_bias(ax - cx, ay - cy)
            e2 = (bx - ax) * (sy - ay) - (by - ay) * (sx - ax) + _edge_bias(bx - ax, by - ay)
            if (e0 | e1 | e2) >= wp.int64(0):
                return False
    return True


@wp.func
def _small_entry(t: int, c0: wp.vec4, c1: wp.vec4, c2: wp.vec4, width: int, height: int, cull_back: int):
    """A triangle inside every clip plane (:func:`_fast_setup`): (drawn, small, its pixel box, what to bin: 0
    nothing, 1 its record, 2 nothing but a centre was tested; the record). A small one with a centre in its box
    is drawn from its record, unless its box holds at most 4 centres and it covers none of them."""
    drawn, small, ax, ay, bx, by, cx, cy, fa, fb, fc, box = _fast_setup(c0, c1, c2, width, height, cull_back)
    what = int(0)
    rec = Record()
    if drawn and small and box[0] <= box[1] and box[2] <= box[3]:
        what = 2
        if not _covers_none(ax, ay, bx, by, cx, cy, box):
            dzdx, dzdy = _depth_plane(fa, fb, fc)
            rec = _record(ax, ay, bx, by, cx, cy, _depth_at(fa, dzdx, dzdy, box[0], box[2]), dzdx, dzdy, t)
            what = 1
    return drawn, small, box, what, rec


@wp.func
def _tally(tally: wp.array2d(dtype=wp.int64), part: int, column: int, v: int, on: int):
    if on != 0:
        wp.atomic_add(tally, part, column, wp.int64(v))


@wp.func_native("""
wp::vec_t<8, wp::int64> acc;
for (int k = 0; k < 8; ++k) acc[k] = k == 7 ? t0 : k == 5 ? 1 : 0;
#if !defined(__CUDA_ARCH__)
if (simd != 0) {
#pragma clang fp contract(off)
typedef int32_t vi __attribute__((vector_size(64))); typedef float vf __attribute__((vector_size(64)));
typedef bool vb __attribute__((ext_vector_type(16)));
auto mn = [](auto a, auto b) { return a < b ? a : b; };  // lane by lane (NaN: b)
auto mx = [](auto a, auto b) { return a > b ? a : b; };
auto bits = [](vi c) { return (uint32_t)__builtin_bit_cast(uint16_t, __builtin_convertvector(c, vb)); };
const vi lane = {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15}, zero = lane - lane, one = zero + 1;
const vf big = __builtin_convertvector(zero, vf) + 1e9f;
const int n = wp::min(16, t1 - t0);
float g[4][3][16];  // the vertices' window positions and outcodes by component, vertex, lane
for (int i = 0; i < 48; ++i) {  // lanes past the last triangle read the first one's
    const auto& w = win.data[*wp::address(tris, t0 + (i < 3 * n ? i / 3 : 0), i % 3)];
    for (int c = 0; c < 4; ++c) g[c][i % 3][i / 3] = w[c];
}
vf f[4][3];
__builtin_memcpy(f, g, sizeof g);
vi X[3], Y[3], ok = lane < n, codes = ok;  // codes: the outcodes' common bits (a plane all three lie beyond)
for (int k = 0; k < 3; ++k) {  // fixed point as lrintf (others limited first: their conversion is undefined)
    const vi code = __builtin_convertvector(f[3][k], vi);
    codes &= code, ok &= (code == 0) & (f[0][k] >= -1e6f) & (f[0][k] <= 1e6f) & (f[1][k] >= -1e6f) & (f[1][k] <= 1e6f);
    X[k] = __builtin_convertvector(__builtin_elementwise_roundeven(mn(mx(f[0][k] * 256.0f, -big), big)), vi);
    Y[k] = __builtin_convertvector(__builtin_elementwise_roundeven(mn(mx(f[1][k] * 256.0f, -big), big)), vi);
}
const vi xmin = mn(X[0], mn(X[1], X[2])), xmax = mx(X[0], mx(X[1], X[2]));
const vi ymin = mn(Y[0], mn(Y[1], Y[2])), ymax = mx(Y[0], mx(Y[1], Y[2]));
ok &= (xmax - xmin < 15 * 256) & (ymax - ymin < 15 * 256);
const uint32_t bad = ~bits(ok | ((codes & 63) != 0)) & ((1u << n) - 1u);  // rejected: nothing to draw or count
const int stop = bad != 0 ? __builtin_ctz(bad) : n;  // the first to be clipped or large: the Warp path's
const vi live = ok & (lane < stop);  // no overflow in the others
for (int k = 0; k < 3; ++k) X[k] = live ? X[k] : zero, Y[k] = live ? Y[k] : zero;
const vi area = (X[1] - X[0]) * (Y[2] - Y[0]) - (X[2] - X[0]) * (Y[1] - Y[0]), sw = area < 0;
vi px[3], py[3];  // counter-clockwise (b and c swapped where the area is negative): fixed point, window x, y, z
vf q[3][3];
for (int k = 0; k < 3; ++k) {
    const int o = k == 0 ? 0 : 3 - k;
    px[k] = sw ? X[o] : X[k], py[k] = sw ? Y[o] : Y[k];
    for (int c = 0; c < 3; ++c) q[c][k] = sw ? f[c][o] : f[c][k];
}
const vi x0 = mx(zero, (xmin + 127) >> 8), x1 = mn(zero + (width - 1), (xmax - 128) >> 8);
const vi y0 = mx(zero, (ymin + 127) >> 8), y1 = mn(zero + (height - 1), (ymax - 128) >> 8);
const vi valid = live & (area != 0) & ~(sw & (cull_back != 0 ? -1 : 0)) & (x0 <= x1) & (y0 <= y1);
const vi rec = (x1 - x0 > 3) | (y1 - y0 > 3);
const vi bw = mn(mx(x1 - x0 + 1, zero), zero + 4), bh = mn(mx(y1 - y0 + 1, zero), zero + 4);
const vi box = valid & ~rec & (((one << bw) - 1) * (0x1111 & ((one << (4 * bh)) - 1)));
vi e[3], ex[3], ey[3], mask = zero;  // edge k from vertex k + 1 to k + 2 at the box's first centre
for (int k = 0; k < 3; ++k) {
    const int a = (k + 1) % 3, b = (k + 2) % 3;
    const vi dx = px[b] - px[a], dy = py[b] - py[a];
    e[k] = dx * (y0 * 256 + 128 - py[a]) - dy * (x0 * 256 + 128 - px[a]) + ~((dy < 0) | ((dy == 0) & (dx > 0)));
    ex[k] = -dy * 256, ey[k] = dx * 256;
}
for (int i = 0; i < 16; ++i)
    mask |= (((e[0] + (i & 3) * ex[0] + (i >> 2) * ey[0]) | (e[1] + (i & 3) * ex[1] + (i >> 2) * ey[1])
              | (e[2] + (i & 3) * ex[2] + (i >> 2) * ey[2])) >= 0) & (zero + (1 << i));
mask &= box;
acc[0] = -__builtin_reduce_add(live), acc[1] = -__builtin_reduce_add(valid);
acc[2] = __builtin_reduce_add(box != 0 ? bw * bh : zero), acc[5] = stop < n, acc[7] = t0 + stop;
// the depth plane through the unsnapped vertices, at the box's first centre
const vf dx01 = q[0][0] - q[0][1], dy01 = q[1][0] - q[1][1], dx20 = q[0][2] - q[0][0], dy20 = q[1][2] - q[1][0];
const vf ooa = 1.0f / (dx01 * dy20 - dx20 * dy01), dz01 = q[2][0] - q[2][1], dz20 = q[2][2] - q[2][0];
const vf dzdx = (dz01 * dy20 - dz20 * dy01) * ooa, dzdy = (dx01 * dz20 - dx20 * dz01) * ooa;
const vf z00 = q[2][0] - (dzdx * (q[0][0] - (__builtin_convertvector(x0, vf) + 0.5f))
                          + dzdy * (q[1][0] - (__builtin_convertvector(y0, vf) + 0.5f)));
// a record (box over 4x4) or a mask entry per lane, and its box's tiles, by field (see _emit_lanes)
const vi field[12] = {rec ? px[0] : x0 | y0 << 16, rec ? py[0] : mask,
                      rec ? ((px[1] - px[0]) & 0xFFFF) | (py[1] - py[0]) << 16 : zero,
                      rec ? ((px[2] - px[0]) & 0xFFFF) | (py[2] - py[0]) << 16 : zero, (vi)z00, (vi)dzdx, (vi)dzdy,
                      t0 + lane, x0 >> 6, x1 >> 6, y0 >> 6, y1 >> 6};
__builtin_memcpy(stage.data + 192 * part, field, sizeof field);
acc[6] = bits((rec & valid) | (mask != 0));
}
#endif
return acc;
""")
def _bin_lanes(simd: int, t0: int, t1: int, tris: wp.array2d(dtype=wp.int32), win: wp.array(dtype=wp.vec4),
               width: int, height: int, cull_back: int, part: int, stage: wp.array(dtype=wp.int32)) -> vec8l:
    """With ``simd`` (the CPU), triangles ``t0``.. (16 at most) of chunk ``part`` set up in SIMD lanes up to the
    first to be clipped or large (window positions and outcodes ``win``; :func:`_bin_one`'s rules, counts and
    depth): each that is drawn a mask entry (:class:`Record`) when its box holds at most 4x4 centres and covers
    one, else a record, into row ``part`` of ``stage`` (12 fields of 16 lanes). Returns (clipper output,
    rasterized, mask entries' centres tested, 0, 0, 1 when it stopped at one to clip or large, the lanes to bin,
    the triangle after the last set up); without ``simd`` and on CUDA (0, 0, 0, 0, 0, 1, 0, ``t0``)."""
    ...


@wp.func_native("""
#if !defined(__CUDA_ARCH__)
int32_t* count = (int32_t*)bins.count.data;
const int32_t* o = stage.data + 192 * part;  // field f of lane l at o[16 f + l]
for (uint32_t km = (uint32_t)keep; km != 0; km &= km - 1u) {
    const int l = __builtin_ctz(km);
    const int32_t r[8] = {o[l], o[16 + l], o[32 + l], o[48 + l], o[64 + l], o[80 + l], o[96 + l], o[112 + l]};
    for (int ty = o[160 + l]; ty <= o[176 + l]; ++ty)
        for (int tx = o[128 + l]; tx <= o[144 + l]; ++tx) {
            const int64_t cell = ((int64_t)ty * bins.tiles_x + tx) * bins.nparts + part;
            const int32_t slot = count[cell]++;  // one launch chunk per part
            if (bins.emit != 0 && slot < bins.room.data[cell])
                __builtin_memcpy(&bins.entries.data[bins.start.data[cell] + slot], r, 32);
            else if (bins.emit != 0) bins.overflow.data[0] = 1;
        }
}
#endif
""")
def _emit_lanes(keep: int, part: int, stage: wp.array(dtype=wp.int32), bins: Bins):
    """The lanes ``keep`` (bits) of row ``part`` of ``stage`` (:func:`_bin_lanes`), in order, into the lists of
    their tiles (:class:`Bins`; one launch chunk per part). CPU only (on CUDA ``keep`` is 0)."""
    ...


@wp.func
def _bin_one(t: int, part: int, clip: wp.array(dtype=wp.vec4), tris: wp.array2d(dtype=wp.int32), width: int,
             height: int, cull_back: int, gb: wp.vec2, tallying: int, out_bins: Bins,
             out_tally: wp.array2d(dtype=wp.int64)):
    """Triangle ``t`` set up and binned (:func:`_bin`) into the tiles it will be drawn in: a small unclipped one as its
    record (:func:`_small_entry`), the others (clipped, large) to be set up again there (:func:`_prepared`). With
    ``tallying``, tallies (row ``part``) the clipper's output, the triangles rasterized, the centres of tiny boxes
    tested here and, for large triangles, the DEPTH_TILE cells they may cover."""
    c0 = clip[tris[t, 0]]
    c1 = clip[tris[t, 1]]
    c2 = clip[tris[t, 2]]
    xs = vec9l()
    if _inside(c0, gb) and _inside(c1, gb) and _inside(c2, gb):  # the clipper passes it on as it is
        _tally(out_tally, part, T_CLIPPED, 1, tallying)
        drawn, small, box, what, rec = _small_entry(t, c0, c1, c2, width, height, cull_back)
        if what != 0:  # most triangles
            _tally(out_tally, part, T_RASTERIZED, 1, tallying)
            if what == 1:
                _bin(rec, 0, xs, xs, box, False, cull_back, width, height, part, out_bins)
            else:
                _tally(out_tally, part, T_TESTED, (box[1] - box[0] + 1) * (box[3] - box[2] + 1), tallying)
            return
        if not drawn:
            return
    n, xs, ys, fxs, fys, zs, box, mode, fast, inside3 = _prepared(c0, c1, c2, width, height, cull_back, gb)
    if not inside3 and n >= 3 and (cull_back == 0 or _front_facing(c0, c1, c2)):
        # a clipped polygon goes on as a fan of n - 2 triangles; with culling, llvmpipe's draw pipeline culls a
        # triangle it must clip before the clipper (the others after it, in triangle setup)
        _tally(out_tally, part, T_CLIPPED, n - 2, tallying)
    cells = int(1)
    if mode == 2:
        cells = _tile16_count(n, xs, ys, box, cull_back, width, height)
        if cells > 0:
            _tally(out_tally, part, T_BINNED, 1, tallying)
            _tally(out_tally, part, T_TILE16, cells, tallying)
    if mode != 0 and cells > 0:
        _tally(out_tally, part, T_RASTERIZED, 1, tallying)
        again = Record()
        again.t = -1 - t
        _bin(again, n, xs, ys, box, mode == 2, cull_back, width, height, part, out_bins)



@wp.kernel(enable_backward=False)
def _bin_kernel(
    offset: int,
    part: int,
    base: int,
    span: int,
    last: int,
    simd: int,
    clip: wp.array(dtype=wp.vec4),
    win: wp.array(dtype=wp.vec4),
    tris: wp.array2d(dtype=wp.int32),
    width: int,
    height: int,
    cull_back: int,
    gb: wp.vec2,
    tallying: int,
    # outputs
    out_stage: wp.array(dtype=wp.int32),
    out_bins: Bins,
    out_tally: wp.array2d(dtype=wp.int64),
):
    """Triangles ``base + i * span`` .. (below ``last``) of launch index i (on the CPU one index per chunk, on CUDA
    ``span`` 1), in order: with ``simd`` runs of unclipped small ones 16 at a time (:func:`_bin_lanes`,
    :func:`_emit_lanes`), each other one (without ``simd``, each one) by :func:`_bin_one`; with ``tallying`` their
    tallies added into row ``part``."""
    lo = base + (wp.tid() + offset) * span
    hi = wp.min(lo + span, last)
    acc = wp.vec3l()
    t = lo
    while t < hi:
        c = _bin_lanes(simd, t, hi, tris, win, width, height, cull_back, part, out_stage)
        if c[6] != wp.int64(0):
            _emit_lanes(int(c[6]), part, out_stage, out_bins)
        t = int(c[7])
        acc = acc + wp.vec3l(c[0], c[1], c[2])
        if c[5] != wp.int64(0):
            _bin_one(t, part, clip, tris, width, height, cull_back, gb, tallying, out_bins, out_tally)
            t += 1
    if tallying != 0 and acc[0] > wp.int64(0):
        wp.atomic_add(out_tally, part, T_CLIPPED, acc[0])
        wp.atomic_add(out_tally, part, T_RASTERIZED, acc[1])
        wp.atomic_add(out_tally, part, T_TESTED, acc[2])


@wp.func
def _sort_list(entries: wp.array(dtype=Record), s: int, e: int):
    """Shell sort of entries[s:e] by triangle, in place (on CUDA, where the lists are written in no order)."""
    gap = (e - s) / 2
    while gap > 0:
        for i in range(s + gap, e):
            v = entries[i]
            t = wp.where(v.t >= 0, v.t, -1 - v.t)
            j = i
            while j >= s + gap:
                u = entries[j - gap].t
                if wp.where(u >= 0, u, -1 - u) <= t:
                    break
                entries[j] = entries[j - gap]
                j -= gap
            entries[j] = v
        gap = gap / 2


@wp.func
def _draw_entry(r: Record, tile: wp.vec4i, clip: wp.array(dtype=wp.vec4), tris: wp.array2d(dtype=wp.int32), width: int,
                height: int, cull_back: int, gb: wp.vec2, bb: int, stride: int, buf_id: wp.array(dtype=wp.int32),
                buf_depth: wp.array(dtype=wp.float32)) -> vec8l:
    """One list entry over one tile: a record in 4x4 blocks (:func:`_cover`), another triangle set up again
    (:func:`_draw_prepared`)."""
    if r.t < 0:
        t = -1 - r.t
        return _draw_prepared(t, clip[tris[t, 0]], clip[tris[t, 1]], clip[tris[t, 2]], tile, width, height, cull_back,
                              gb, bb, stride, buf_id, buf_depth)
    ax = wp.int64(r.xy[0])
    ay = wp.int64(r.xy[1])
    bx = ax + wp.int64(_lo16(r.xy[2]))
    by = ay + wp.int64(r.xy[2] >> 16)
    cx = ax + wp.int64(_lo16(r.xy[3]))
    cy = ay + wp.int64(r.xy[3] >> 16)
    box = _tri_box(ax, ay, bx, by, cx, cy, width, height)
    return _cover(ax, ay, bx, by, cx, cy, wp.max(box[0], tile[0]), wp.min(box[1], tile[1]), wp.max(box[2], tile[2]),
                  wp.min(box[3], tile[3]), box[0], box[2], r.plane[0], r.plane[1], r.plane[2], r.t, tile[0], tile[2],
                  bb, stride, buf_id, buf_depth)


@wp.func
def _draw_list(simd: int, s: int, e: int, r: wp.vec4i, clip: wp.array(dtype=wp.vec4), tris: wp.array2d(dtype=wp.int32),
               entries: wp.array(dtype=Record), width: int, height: int, cull_back: int, gb: wp.vec2, bb: int,
               stride: int, buf_id: wp.array(dtype=wp.int32), buf_depth: wp.array(dtype=wp.float32)) -> vec8l:
    """A tile's list entries[s:e], in order: with ``simd`` runs of mask entries (:func:`_draw_masks`) and of records
    (:func:`_draw_records`), every other entry (without, every entry) by :func:`_draw_entry`."""
    acc = vec8l()
    j = s
    while j < e:
        j0 = j
        c = _draw_masks(simd, entries, j, e, r[0], r[1], r[2], r[3], bb, stride, buf_id, buf_depth)
        j = int(c[6])
        c[6] = wp.int64(0)
        acc = acc + c
        c = _draw_records(simd, entries, j, e, r[0], r[1], r[2], r[3], width, height, bb, stride, buf_id, buf_depth)
        j = int(c[6])
        c[6] = wp.int64(0)
        acc = acc + c
        if j == j0:  # an entry to set up again (or, without simd, any entry)
            acc = acc + _draw_entry(entries[j], r, clip, tris, width, height, cull_back, gb, bb, stride, buf_id,
                                    buf_depth)
            j += 1
    return acc


@wp.func
def _listed(bins: Bins, tile: int) -> int:
    """The entries in a tile's lists."""
    n = int(0)
    for p in range(bins.nparts):
        n += bins.count[tile * bins.nparts + p]
    return n


@wp.kernel(enable_backward=False)
def _tile_kernel(
    offset: int,
    part: int,
    scratch: int,
    queue: wp.array(dtype=wp.int32),
    ntiles: int,
    first: int,
    clip: wp.array(dtype=wp.vec4),
    tris: wp.array2d(dtype=wp.int32),
    bins: Bins,
    width: int,
    height: int,
    cull_back: int,
    gb: wp.vec2,
    # outputs
    out_buf_id: wp.array(dtype=wp.int32),
    out_buf_depth: wp.array(dtype=wp.float32),
    out_id: wp.array(dtype=wp.int32),
    out_depth: wp.array(dtype=wp.float32),
    out_dirty: wp.array(dtype=wp.int32),
    out_tally: wp.array2d(dtype=wp.int64),
):
    """Screen tiles, one thread each: the background (``first`` batch) or the images' pixels so far, the tile's
    lists (:class:`Bins`) drawn in order (:func:`_draw_list`), a tile with a pixel covered flagged in ``out_dirty``,
    the tallies into row ``part``. With ``scratch`` (the CPU, one launch index per thread) each thread takes the
    next tile from the shared counter ``queue`` until none is left and draws it in its own TILE x PITCH tile of
    ``out_buf_*``, then copies it into the images; without (CUDA), tile ``offset + tid`` is drawn in the images
    themselves (``out_buf_*`` are the images, a tile's sorted list first)."""
    tile = wp.tid() + offset
    slot = tile
    if scratch != 0:
        tile = atomic_add_i32(queue, 0, 1)
    while tile < ntiles:
        if first == 0 and _listed(bins, tile) == 0:  # a later batch that draws nothing here: the images stand
            if scratch == 0:
                break
            tile = atomic_add_i32(queue, 0, 1)
            continue
        ty = tile / bins.tiles_x
        r = _cell_rect(tile - ty * bins.tiles_x, ty, TILE, width, height)
        w = r[1] - r[0] + 1
        h = r[3] - r[2] + 1
        ib = (height - 1 - r[2]) * width + r[0]  # the tile's first pixel in the images (rows run down)
        bb = ib
        stride = -width
        if scratch != 0:
            bb = (slot * SCRATCH_ROWS + MARGIN) * PITCH + MARGIN
            stride = PITCH
            if first == 0:
                _copy(1, ib, -width, bb, PITCH, w, h, 0, out_id, out_depth, out_buf_id, out_buf_depth)
            elif _listed(bins, tile) == 0:  # nothing to draw: the background straight into the images
                _copy(0, 0, 0, ib, -width, w, h, 1, out_id, out_depth, out_id, out_depth)
                tile = atomic_add_i32(queue, 0, 1)
                continue
        if first != 0:
            _copy(0, 0, 0, bb, stride, w, h, 0, out_buf_id, out_buf_depth, out_buf_id, out_buf_depth)
        acc = vec8l()
        for p in range(bins.nparts):  # the chunks' lists in order: submission order
            cell = tile * bins.nparts + p
            s = bins.start[cell]
            e = s + bins.count[cell]
            if scratch == 0:
                _sort_list(bins.entries, s, e)
            acc = acc + _draw_list(scratch, s, e, r, clip, tris, bins.entries, width, height, cull_back, gb, bb, stride,
                                   out_buf_id, out_buf_depth)
        if scratch != 0:
            _copy(1, bb, PITCH, ib, -width, w, h, 1, out_buf_id, out_buf_depth, out_id, out_depth)
        if acc[3] > wp.int64(0):
            out_dirty[tile] = 1
        if acc[0] + acc[1] > wp.int64(0):  # centres tested (a mask entry's were as it was binned) or covered
            wp.atomic_add(out_tally, part, T_TESTED, acc[0])
            wp.atomic_add(out_tally, part, T_INSIDE, acc[1])
            wp.atomic_add(out_tally, part, T_PASSED, acc[2])
            wp.atomic_add(out_tally, part, T_COVERED, acc[3])
            wp.atomic_add(out_tally, part, T_QUADS, acc[4])
            wp.atomic_add(out_tally, part, T_BLOCKS, acc[5])
        if scratch == 0:
            break
        tile = atomic_add_i32(queue, 0, 1)


@wp.func
def pixel_ndc(i: int, j: int, h: int, w: int) -> wp.vec2:
    """NDC of the centre of image pixel (row i from the top, column j)."""
    return wp.vec2((float(j) + 0.5) / float(w) * 2.0 - 1.0, (float(h - 1 - i) + 0.5) / float(h) * 2.0 - 1.0)


@wp.func
def clip_barycentrics(c0: wp.vec4, c1: wp.vec4, c2: wp.vec4, p: wp.vec2) -> wp.vec3:
    """Perspective-correct barycentrics of the point on the triangle (clip-space vertices) seen at NDC p:
    with a_k = x_k - px w_k and c_k = y_k - py w_k, b = cross(a, c) / sum(cross(a, c)). Differentiable."""
    a = wp.vec3(c0[0] - p[0] * c0[3], c1[0] - p[0] * c1[3], c2[0] - p[0] * c2[3])
    c = wp.vec3(c0[1] - p[1] * c0[3], c1[1] - p[1] * c1[3], c2[1] - p[1] * c2[3])
    b = wp.cross(a, c)
    return b * (1.0 / (b[0] + b[1] + b[2]))


@wp.kernel(enable_backward=False)
def _ndc_x_kernel(
    offset: int,
    width: int,
    # outputs
    out_x: wp.array(dtype=float),
):
    """NDC x of the centre of each image column: pixel_ndc's own arithmetic, once per column."""
    j = wp.tid() + offset
    out_x[j] = pixel_ndc(0, j, 1, width)[0]


@wp.kernel(enable_backward=False)
def _barycentrics_kernel(
    offset: int,
    bands: wp.array(dtype=wp.int32),
    dirty: wp.array(dtype=wp.int32),
    ndc_x: wp.array(dtype=float),
    tri_id: wp.array2d(dtype=wp.int32),
    clip: wp.array(dtype=wp.vec4),
    tris: wp.array2d(dtype=wp.int32),
    # outputs
    out_bary: wp.array2d(dtype=wp.vec2),
):
    """Perspective-correct barycentrics (b0, b1) of each covered pixel centre on its visible triangle, over
    the flagged screen tiles (``dirty``, the only ones with covered pixels) of one band of TILE window rows
    (``bands``), row by row; background pixels are not written (the output starts as zeros). The
    triangle's clip vertices are fetched again only when the id changes along a row; the centre's NDC
    (pixel_ndc, whose x and y do not depend on each other) comes from ``ndc_x`` and once per row: its two
    divisions were ~40% of the kernel."""
    hh = tri_id.shape[0]
    ww = tri_id.shape[1]
    ty = bands[wp.tid() + offset]
    tiles_x = (ww + TILE - 1) / TILE
    c0 = wp.vec4()
    c1 = wp.vec4()
    c2 = wp.vec4()
    for y in range(ty * TILE, wp.min(ty * TILE + TILE, hh)):
        i = hh - 1 - y
        py = pixel_ndc(i, 0, hh, ww)[1]
        last = int(-1)  # noqa: UP018 -- a mutable Warp int
        for tx in range(tiles_x):
            if dirty[ty * tiles_x + tx] != 0:
                for j in range(tx * TILE, wp.min(tx * TILE + TILE, ww)):
                    t = tri_id[i, j]
                    if t >= 0:
                        if t != last:
                            c0 = clip[tris[t, 0]]
                            c1 = clip[tris[t, 1]]
                            c2 = clip[tris[t, 2]]
                            last = t
                        b = clip_barycentrics(c0, c1, c2, wp.vec2(ndc_x[j], py))
                        if wp.isfinite(b):
                            out_bary[i, j] = wp.vec2(b[0], b[1])
                        else:  # a triangle seen edge-on through this centre (not drawn by the coverage test)
                            out_bary[i, j] = wp.vec2(1.0 / 3.0, 1.0 / 3.0)


# ------------------------------------------------------------------------------------------------
# host
# ------------------------------------------------------------------------------------------------


class Fragments:
    """The visibility pass's output; images have row 0 at the top.

    Attributes:
        triangle_id: (H, W) int32, the visible triangle per pixel, -1 for background.
        depth: (H, W) float32 window depth in [0, 1] (1.0 for background).
        barycentrics: (H, W, 2) float32 perspective-correct weights (b0, b1) of the triangle's
            vertices 0 and 1 at the pixel centre (b2 = 1 - b0 - b1); 0 for background. Computed from
            the clip-space vertices on first access (the resolve half of a visibility buffer: the
            visibility pass itself produces ids and depth, as a GPU's depth pre-pass would).
        stats: per-frame counts, the same on every run and for any thread count: triangles_in;
            triangles_rasterized (that reached the coverage test after trivial rejection, clipping, zero-area and
            back-face culling); triangles_binned (large triangles: a pixel box of SMALL_PX or more) and
            tile_entries (the DEPTH_TILE x DEPTH_TILE cells their edges do not exclude); fragments_tested (the pixel
            centres whose edge functions were evaluated: on the CPU every centre of a small unclipped triangle's
            pixel box, row by row, and for the others those of the 4x4 blocks their corners did not reject; on
            CUDA 4x4 blocks for every triangle), fragments_inside (centres covered),
            pixels_written (depth tests passed, in submission order) and pixels_covered (non-background pixels in
            the end). All but fragments_tested are the same on every device.
        counters: the pipeline statistics of the draw, as OpenGL's ARB_pipeline_statistics_query names them,
            when asked for (``counters=True``; None otherwise) (:func:`terrainwarp.kernels.counters.raster_counters`):
            ``clipping_input_primitives`` (the triangles), ``clipping_output_primitives`` (1 per triangle
            inside every clip plane, n - 2 per clipped n-gon, 0 rejected; zero-area and back faces included,
            as they are culled after the clipper), ``fragment_shader_invocations`` (4 per 2x2 quad with a
            covered pixel centre, per triangle, helper lanes included: model ``quad2x2``, as desktop GPUs
            shade), ``fragment_shader_invocations_llvmpipe`` (16 per 4x4 block with a covered centre, per
            triangle: llvmpipe's count), ``samples_passed`` (fragments that pass ``GL_LESS`` against a depth
            buffer cleared to 1.0 in submission order: triangle by triangle in index order, a clipped
            triangle's fan in order, as an occlusion query counts them), ``samples_covered`` (covered pixel
            centres, every triangle's) and ``pixels_covered``. Triangles are counted as drawn after clipping:
            each fan triangle of a clipped one on its own, as llvmpipe draws them; quads and blocks are
            aligned in window coordinates (origin at the bottom left).

    Iterating yields (triangle_id, depth, barycentrics, stats).
    """

    __slots__ = ("triangle_id", "depth", "stats", "counters", "_bary", "_clip", "_tris", "_device", "_ids",
                 "_tiles")

    def __init__(self, triangle_id, depth, barycentrics, stats, *, clip=None, tris=None, device="cpu", ids=None,
                 tiles=None):
        self.triangle_id = triangle_id
        self.depth = depth
        self.stats = stats
        self.counters: dict[str, int] | None = None
        self._bary = barycentrics
        self._clip, self._tris, self._device = clip, tris, device
        self._ids = ids  # the triangle ids as a device array (on the CPU: triangle_id's own memory)
        self._tiles = tiles  # int32 flag per screen tile (window order), 0: every pixel in it is background

    @property
    def barycentrics(self) -> np.ndarray:
        if self._bary is None:
            hh, ww = self.triangle_id.shape
            dirty = np.ones(_tiles_x(ww) * _tiles_x(hh), np.int32) if self._tiles is None else self._tiles
            bands = _bands(dirty, ww)
            ids = self._ids
            if ids is None or ids.device.is_cuda:  # the host image, as the caller may have changed it
                ids = wp.array(self.triangle_id, dtype=wp.int32, device=self._device)
            out = filled_array((hh, ww), wp.vec2, 0.0, self._device)  # background; the kernel writes covered pixels
            if len(bands):
                ndc_x = wp.empty(ww, dtype=float, device=self._device)
                launch_one(_ndc_x_kernel, ww, [0, ww], [ndc_x], device=self._device)
                launch(_barycentrics_kernel, len(bands),
                       [as_warp(bands, wp.int32, self._device), as_warp(dirty, wp.int32, self._device), ndc_x,
                        ids.reshape((hh, ww)), self._clip, self._tris], [out], self._device,
                       min_items=_MIN_PIXELS // (TILE * ww) + 1)
            self._bary = out.numpy().reshape(hh, ww, 2)
            self._clip = self._tris = self._ids = None
        return self._bary

    def __iter__(self):
        return iter((self.triangle_id, self.depth, self.barycentrics, self.stats))

    def __repr__(self) -> str:
        return f"Fragments(shape={self.triangle_id.shape}, stats={self.stats})"


def _as_matrix(name: str, m: object) -> np.ndarray:
    a = np.asarray(m, dtype=np.float64)
    if a.shape != (4, 4):
        raise ValueError(f"{name}: expected a (4, 4) matrix, got shape {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name}: expected finite entries")
    return a


def _tiles_x(width: int) -> int:
    return (width + TILE - 1) // TILE


def _bands(dirty: np.ndarray, width: int) -> np.ndarray:
    """The rows of screen tiles (int32, from window row 0 up) with a flagged tile."""
    return np.flatnonzero(dirty.reshape(-1, _tiles_x(width)).any(axis=1)).astype(np.int32)


_SCRATCH = True  # on the CPU: scratch tiles, records drawn in SIMD (False: the way CUDA draws, for the tests)
_IMAGES_KEPT = 3  # output images kept per shape: the frame being made, the one before it and one its caller holds
_IMAGES_MAX_BYTES = 64 << 20  # larger images (each) are not kept


class _Work:
    """What a rasterize call of one kind (device, viewport, chunks per launch) works in besides its outputs, leased
    from the pool (:func:`.pool.take`) and given back when the call is done (a call that fails keeps its lease and
    the work is dropped): the tile flags, the tallies, the lists' counts, the tile queue, the CPU's scratch tiles,
    the lists' storage (grown as frames need), and per batch the lists' room. The room is the counts of the last
    frame binned here and a quarter more, so that a frame like it writes its entries as it counts them (one binning
    pass); a frame that needs more is binned again with exact room, and leaves its counts for the next."""

    def __init__(self, device: str, width: int, height: int, nparts: int, scratch: bool) -> None:
        self.device, self.cpu, self.simd = device, wp.get_device(device).is_cpu, int(scratch)
        self.tiles_x = _tiles_x(width)
        self.ntiles = self.tiles_x * _tiles_x(height)
        self.nparts, ncells = nparts, self.tiles_x * _tiles_x(height) * nparts
        zeros = lambda *shape, dt=wp.int32: wp.zeros(shape, dtype=dt, device=device)  # noqa: E731
        self.dirty, self.queue, self.overflow, self.stage = zeros(self.ntiles), zeros(1), zeros(1), zeros(nparts * 192)
        self.count, self.cursor, self.tally = zeros(ncells), zeros(ncells), zeros(nparts, TALLIES, dt=wp.int64)
        self.cleared = [self.dirty, self.tally, self.queue, self.count, self.cursor, self.overflow]
        self.views = [a.numpy() for a in self.cleared] if self.cpu else None  # the CPU clears them in numpy
        self.workers = min(nparts, self.ntiles) if scratch else self.ntiles
        n = self.workers * SCRATCH_ROWS * PITCH if scratch else 1
        self.buf_id, self.buf_depth = zeros(n), zeros(n, dt=wp.float32)
        self.room: dict[int, tuple] = {}  # per batch: the room the next frame bins into, and the other kept
        self.entries = wp.empty(1, dtype=Record, device=device)

    def clear(self, first: int = 0) -> None:
        """Zero the arrays from ``cleared[first]`` on: all of them for a frame, the lists' for a batch."""
        for k in range(first, len(self.cleared)):
            if self.views is not None:
                self.views[k].fill(0)
            else:
                self.cleared[k].zero_()

    def bins(self, counting: wp.array, room: tuple | None) -> Bins:
        """Lists counted into ``counting`` with ``room`` (:meth:`_room`: the lists' start and room per cell, their
        device arrays and their Bins), or counted only (None)."""
        if room is None:
            b = Bins()
            b.tiles_x, b.nparts, b.emit, b.count, b.overflow = self.tiles_x, self.nparts, 0, counting, self.overflow
            b.start = b.room = counting
            b.entries = self.entries
            return b
        start, slots, b = room[0], room[1], room[4]
        need = int(start[-1] + slots[-1])
        if self.entries.shape[0] < need:  # grown by half again: a slowly denser flyover does not grow it each frame
            self.entries = wp.empty(need + need // 2, dtype=Record, device=self.device)
        if b.entries.ptr != self.entries.ptr:
            b.entries = self.entries
        return b

    def bin_batch(self, base: int, mb: int, args: list) -> Bins:
        """Bin a batch (:func:`_bin_kernel`, on the CPU one launch index per chunk of the triangles, on CUDA one per
        triangle): one pass when this batch's room holds it, else counting then binning again with exact room."""
        if base:
            self.clear(2)  # the queue and the lists' counts, for this batch
        ranges = chunks(mb, 1, _MIN_TRIANGLES) if self.cpu else [(0, 1)] * mb
        head = [base, ranges[0][1] - ranges[0][0] if ranges else 1, base + mb, self.simd]
        rooms = self.room.get(base, (None, None))
        bins = self.bins(self.count, rooms[0])
        launch(_bin_kernel, len(ranges), [*head, *args, 1], [self.stage, bins, self.tally], self.device, parts=True,
               min_items=1)
        counts = self.views[3] if self.cpu else self.count.numpy()
        if not bins.emit or int(self.views[5][0] if self.cpu else self.overflow.numpy()[0]):
            bins = self.bins(self.cursor, self._room(counts, False, self.cursor))
            launch(_bin_kernel, len(ranges), [*head, *args, 0], [self.stage, bins, self.tally], self.device,
                   parts=True, min_items=1)
        # the next frame's room, in the other of this batch's two on the CPU (the lists drawn now use this one)
        self.room[base] = (self._room(counts, True, self.count, rooms[1] if self.cpu else None), rooms[0])
        return bins

    def _room(self, counts: np.ndarray, spare: bool, counting: wp.array, reuse: tuple | None = None) -> tuple:
        """(start, room, their device arrays, their Bins counting into ``counting``) of lists holding ``counts``
        (exactly, or with a quarter more and 8 spare per cell); written into ``reuse``'s arrays when given (the
        CPU's device arrays are views of the numpy ones)."""
        if reuse is not None:  # in place: int32 counts + a quarter + 8 (or the counts), then their exclusive sum
            slots = reuse[1]
            if spare:
                np.floor_divide(counts, 4, out=slots)
                slots += counts
                slots += 8
            else:
                slots[:] = counts
            reuse[0][0] = 0
            np.cumsum(slots[:-1], out=reuse[0][1:])
            return reuse
        slots = (counts + counts // 4 + 8 if spare else counts).astype(np.int32)
        start = np.zeros(len(slots), np.int32)
        np.cumsum(slots[:-1], out=start[1:])
        b = Bins()
        b.tiles_x, b.nparts, b.emit, b.count, b.overflow = self.tiles_x, self.nparts, 1, counting, self.overflow
        b.start, b.room = as_warp(start, wp.int32, self.device), as_warp(slots, wp.int32, self.device)
        b.entries = self.entries
        return start, slots, b.start, b.room, b


_WORK_KEPT = 2  # per kind: a call, and another on another thread


def _targets(width: int, height: int, device: str) -> tuple:
    """What a draw writes and works in, taken before its launches: (ids, depth (frame-sized pool arrays), on the CPU
    the two images as numpy arrays over the same memory (else None), the :class:`_Work` lease (cleared), scratch
    tiles or not). :func:`rasterize` takes them before the vertex launch, beside the vertices' own pool arrays: the
    host code between two launches runs with the caches the launch before it emptied, so the pool's is run there."""
    npx = width * height
    (out_id, out_depth), images = pooled_arrays([(npx, wp.int32), (npx, wp.float32)], device, tag="images", rows=False,
                                                keep=_IMAGES_KEPT, max_bytes=2 * _IMAGES_MAX_BYTES, host=True)
    nparts = max_parts()
    dev = device_named(device)
    scratch = dev.is_cpu and _SCRATCH
    lease = take(("raster_work", dev.alias, width, height, nparts, scratch),
                 lambda: _Work(device, width, height, nparts, scratch), keep=_WORK_KEPT)
    lease.buffer.clear()
    return out_id, out_depth, images, lease, scratch


def _draw(clip: wp.array, win: wp.array, tri_wp: wp.array, m: int, width: int, height: int, cull_back: bool,
          device: str, targets: tuple):
    """Bin and draw the triangles (vertices' clip coordinates ``clip``, window positions ``win``), BATCH at a time,
    into ``targets`` (:func:`_targets`). -> (ids, depth (device arrays, every pixel written), the tile flags (int32,
    window order), the tallies summed (TALLIES,) int64, on the CPU the two images as numpy arrays over the same
    memory (else None))."""
    out_id, out_depth, images, lease, scratch = targets
    work = lease.buffer
    gb = _guard_band(width, height)
    cb = int(bool(cull_back))
    buf_id, buf_depth = (work.buf_id, work.buf_depth) if scratch else (out_id, out_depth)
    for base in range(0, max(m, 1), BATCH):
        bins = work.bin_batch(base, max(min(BATCH, m - base), 0), [clip, win, tri_wp, width, height, cb, gb])
        launch(_tile_kernel, work.workers, [int(scratch), work.queue, work.ntiles, int(base == 0), clip, tri_wp, bins,
                                            width, height, cb, gb],
               [buf_id, buf_depth, out_id, out_depth, work.dirty, work.tally], device, parts=True, min_items=1)
    tiles, tally = (work.views[0].copy(), work.views[1].sum(axis=0)) if work.cpu else \
        (work.dirty.numpy().copy(), work.tally.numpy().sum(axis=0))
    lease.give_back()
    return out_id, out_depth, tiles, tally, images


@functools.lru_cache(maxsize=64)
def _guard_band(width: int, height: int) -> wp.vec2:
    """The guard band as a launch argument, made once per viewport (never written: launches copy it)."""
    return wp.vec2(1.0 + 2.0 * GUARD_BAND_PX / width, 1.0 + 2.0 * GUARD_BAND_PX / height)


def _tri_array(tri: np.ndarray, device: str) -> wp.array:
    """The (m, 3) int32 triangles as a Warp array (one dummy row when there are none); not copied on the CPU."""
    return as_warp(tri if len(tri) else np.zeros((1, 3), np.int32), wp.int32, device)


def _rasterize_clip(clip: wp.array, win: wp.array, tri: np.ndarray, width: int, height: int, cull_back: bool,
                    device: str, counters: bool = False, prepared: tuple | None = None) -> Fragments:
    """Draw ``tri`` over the vertices (``clip``, ``win``); ``prepared``: (:func:`_tri_array`, :func:`_targets`) taken
    already."""
    m = int(tri.shape[0])
    tri_wp, targets = prepared if prepared is not None else (_tri_array(tri, device), _targets(width, height, device))
    out_id, out_depth, tiles, tally, images = _draw(clip, win, tri_wp, m, width, height, cull_back, device, targets)
    ids, depth = (a.reshape(height, width) for a in (images or (out_id.numpy(), out_depth.numpy())))
    if not device_named(device).is_cpu:  # numpy() copied: the device arrays keep the kernel's values only
        out_id = None
    frag = Fragments(ids, depth, None, raster_stats(tally, m), clip=clip, tris=tri_wp, device=device, ids=out_id,
                     tiles=tiles)
    if counters:
        frag.counters = raster_counters(tally, m)
    return frag


def _points(name: str, a: object, k: int) -> np.ndarray:
    """``a`` as an (n, k) float array, checked."""
    p = np.asarray(a)
    if p.ndim != 2 or p.shape[1] != k:
        raise ValueError(f"{name}: expected shape (n, {k}), got {p.shape}")
    if p.dtype.kind != "f":  # (np.issubdtype, without its Python)
        raise TypeError(f"{name}: expected a float array, got {p.dtype}")
    return p


def rasterize(positions: object, triangles: object, view: object, proj: object, width: int, height: int,
              *, cull_back: bool = False, counters: bool = False, checked: bool = False,
              device: str = "cpu") -> Fragments:
    """Rasterize a triangle mesh with any matrices (no assumption about which axis is up).

    Args:
        positions: (n, 3) float32 vertex positions (float64 input is cast; camera-relative
            positions with a translation-free view matrix keep far terrains precise).
        triangles: (m, 3) int32 vertex indices, counter-clockwise front faces.
        view, proj: (4, 4) matrices (OpenGL conventions, clip z in [-w, w]).
        width, height: viewport in pixels (1..16384).
        cull_back: drop clockwise (back-facing) triangles, as ``glEnable(GL_CULL_FACE)``.
        counters: also return the draw's pipeline statistics (:attr:`Fragments.counters`); the images are the
            same either way.
        checked: the caller vouches that ``triangles`` is a C-contiguous (m, 3) int32 array of indices into
            ``positions`` and that ``positions`` is float32 and finite, as the meshes :func:`terrainwarp.render`
            makes itself are: their values are not scanned again (shapes and dtypes still are). A mesh that
            breaks this gives undefined results.

    Returns:
        :class:`Fragments`. Deterministic: bit-identical on every run and for any thread count.
    """
    pos = _points("positions", positions, 3)
    checked = check_bool("checked", checked)
    tri = check_triangles("triangles", triangles, None if checked else len(pos), scan=not checked)
    width, height = check_viewport(width, height)
    counters = check_bool("counters", counters)
    clip, win, prepared = _transform(pos, view, proj, device, width, height, finite=checked,  # see _targets
                                     then=lambda: (_tri_array(tri, device), _targets(width, height, device)))
    return _rasterize_clip(clip, win, tri, width, height, cull_back, device, counters, prepared)


def _transform(pos: np.ndarray, view: object, proj: object, device: str, width: int = 1, height: int = 1,
               finite: bool = False, then: Callable[[], object] | None = None) -> tuple[wp.array, wp.array, object]:
    """The vertices' clip coordinates and window positions (:func:`_vertex_kernel`), and what ``then()`` returns,
    called once the arguments are checked, before the launch (None: nothing); ``finite``: the positions are known to
    be finite."""
    pos32 = np.ascontiguousarray(pos, dtype=np.float32)
    if not finite and not np.all(np.isfinite(pos32)):
        raise ValueError("positions: expected finite coordinates")
    mvp = (_as_matrix("proj", proj) @ _as_matrix("view", view)).astype(np.float32)
    made = then() if then is not None else None
    n = max(len(pos32), 1)
    clip, win = pooled_arrays([(n, wp.vec4), (n, wp.vec4)], device, tag="vertices")  # clip: Fragments keeps it
    return clip, _vertices(clip, len(pos32), width, height, device, as_warp(pos32, wp.vec3, device), mvp, win), made


def _vertices(clip: wp.array, n: int, width: int, height: int, device: str, pos: wp.array | None = None,
              mvp: np.ndarray | None = None, win: wp.array | None = None) -> wp.array:
    """The window positions of ``n`` vertices (:func:`_vertex_kernel`; with ``pos`` and ``mvp`` their clip
    coordinates too, into ``clip``), into ``win`` (or a new pool array)."""
    win = pooled_rows_array(max(n, 1), wp.vec4, device) if win is None else win
    if n:
        mat = wp.mat44(*mvp.reshape(-1).tolist()) if mvp is not None else wp.mat44()
        launch(_vertex_kernel, n, [pos if pos is not None else wp.empty(1, dtype=wp.vec3, device=device), mat,
                                   int(pos is not None), width, height, _guard_band(width, height)], [clip, win],
               device, min_items=_MIN_VERTICES)
    return win


def clip_coordinates(positions: object, view: object, proj: object, *, device: str = "cpu") -> np.ndarray:
    """The clip-space vertices :func:`rasterize` computes: (n, 4) float32 ``(proj @ view) @ (p, 1)``,
    with the product of the matrices rounded to float32 first, as a vertex shader's uniform would be."""
    pos = _points("positions", positions, 3)
    return _transform(pos, view, proj, device)[0].numpy()[: len(pos)].reshape(-1, 4)


def rasterize_clip(clip: object, triangles: object, width: int, height: int, *, cull_back: bool = False,
                   counters: bool = False, device: str = "cpu") -> Fragments:
    """Rasterize triangles given clip-space vertices, as a GPU does after the vertex shader.

    Args:
        clip: (n, 4) float32 clip-space positions (x, y, z, w), OpenGL conventions.
        triangles: (m, 3) int32 vertex indices; width, height: viewport in pixels (1..16384).
        cull_back: drop clockwise triangles.
        counters: also return the pipeline statistics (:attr:`Fragments.counters`).

    Returns:
        :class:`Fragments`, as :func:`rasterize`.
    """
    c = _points("clip", clip, 4)
    tri = check_triangles("triangles", triangles, len(c))
    width, height = check_viewport(width, height)
    counters = check_bool("counters", counters)
    c32 = np.ascontiguousarray(c, dtype=np.float32)
    if not np.all(np.isfinite(c32)):
        raise ValueError("clip: expected finite coordinates")
    clip_wp = wp.array(c32 if len(c32) else np.zeros((1, 4), np.float32), dtype=wp.vec4, device=device)
    win = _vertices(clip_wp, len(c32), width, height, device)
    return _rasterize_clip(clip_wp, win, tri, width, height, cull_back, device, counters)

"""The rasterizer: a visibility pass (coverage + depth test) and a resolve pass, as Warp kernels.

The rules are OpenGL's as Mesa's llvmpipe implements them (checked pixel for pixel against llvmpipe
through EGL in tests/kernels/test_raster.py, with the same clip-space vertices):

1. Vertices go to clip space in one kernel (``clip = (proj @ view) @ (p, 1)``, the matrix product
   rounded to float32 first, like a uniform); :func:`rasterize_clip` starts from clip coordinates.
2. A triangle is trivially rejected when all three vertices lie outside one clip plane. When a vertex
   lies outside the viewport's x or y planes (llvmpipe here has no guard band: matching its pixels
   needs the viewport planes), or outside near ``z >= -w`` or far ``z <= w``, the triangle is clipped
   (Sutherland-Hodgman, x and y planes first, then near, then far, interpolating from the outside
   vertex to the inside one, as Mesa's clipper does) and drawn as a fan of triangles, each on its
   own. Clipping far as well as near matters: a vertex with ``-w <= z`` but ``z > w`` may have w < 0.
3. Window coordinates are ``x / w * (W / 2) + W / 2`` (fused multiply-add, as llvmpipe's vertex
   stage), snapped to 8 sub-pixel bits by rounding half to even (``lrintf``). Zero-area triangles
   (in fixed point) are dropped, and clockwise ones too with ``cull_back``; the others are made
   counter-clockwise.
4. Coverage: 64-bit integer edge functions at pixel centres with llvmpipe's fill convention for an
   OpenGL framebuffer (lower-left origin): a centre exactly on an edge belongs to the triangle for
   which the edge is a *left* edge or a *bottom* edge in the image (interior above it, window y up).
   A centre on an edge shared by two triangles is covered by exactly one of them.
5. Depth: the plane through the unsnapped window positions (x, y, z_window) of each (fan) triangle,
   evaluated at the pixel centre in float32 and clamped to [0, 1]. The test keeps the nearest fragment
   with one ``atomic_min`` on a 64-bit key ``(float bits of depth) << 32 | id``: window depth is a
   non-negative float, whose bit pattern orders like its value, so ties go to the lower triangle id
   and the result never depends on launch order (as ``GL_LESS`` in submission order). As with
   ``GL_LESS`` against a depth buffer cleared to 1.0, a fragment at depth exactly 1.0 is not drawn.
6. Speed: small triangles (pixel box < SMALL_PX each way; most terrain triangles, many without any
   pixel centre) are set up and drawn by their own thread without clipping arrays; larger ones are
   binned into TILE x TILE screen tiles (count -> scan -> emit) and drawn tile by tile, each tile
   touched only by triangles whose edges do not exclude it.

Resolve: the key decodes to the triangle id and depth, in the screen tiles the drawing kernels flagged
(where they wrote a key; the rest of the image is background, a host fill); perspective-correct
barycentrics of each pixel centre on the original (unclipped) triangle come from its clip-space vertices: with
``a_i = x_i - px*w_i`` and ``c_i = y_i - py*w_i`` (px, py the centre in NDC) they are
``cross(a, c) / sum(cross(a, c))``, exact for clipped triangles too. :func:`interpolate_warp` is the
same computation as a differentiable kernel (gradients to clip positions and attributes).

Output images have row 0 at the top (window y is flipped once, here).
"""


import numpy as np
import warp as wp

from .checks import check_bool, is_int
from .parallel import atomic_add_i32, atomic_min_u64, launch, launch_one, max_parts, scan
from .parallel import view as as_warp  # 'view' is a view matrix here
from .pool import Lease, host_layout, pooled, pooled_array, take

SUBPIXEL_BITS = 8
SUBPIXEL = 1 << SUBPIXEL_BITS
SUBPIXEL_HALF = SUBPIXEL // 2
GUARD_BAND_PX = 0.0  # x and y are clipped at the viewport itself, as llvmpipe does (its pixels match then)
TILE = 16  # screen tile edge in pixels (binning of large triangles)
SMALL_PX = 16  # triangles whose pixel box spans fewer pixels than this each way are drawn at once
_EMPTY_KEY = np.uint64(0xFFFFFFFFFFFFFFFF)
# the fewest items worth a CPU thread of their own, per launch (see parallel.launch)
_MIN_TRIANGLES = 2048
_MIN_TILES = 64
_MIN_PIXELS = 32768
_OVERSPLIT = 4  # chunks per thread where the work per item is uneven (near and far triangles)

poly9 = wp.types.matrix(shape=(9, 4), dtype=wp.float32)
vec9l = wp.types.vector(length=9, dtype=wp.int64)
vec9f = wp.types.vector(length=9, dtype=wp.float32)
vec8l = wp.types.vector(length=8, dtype=wp.int64)
_LISTED = 32  # records of a pixel's list sorted in place by the staircase pass
vec_listed = wp.types.vector(length=_LISTED, dtype=wp.uint64)


@wp.struct
class Counting:
    """What the drawing functions count besides drawing (the pipeline statistics of :func:`rasterize` with
    ``counters=True``).

    ``mode`` 0: nothing. 1: each (fan) triangle's 2x2 quads and 4x4 blocks (window-aligned) with a covered
    pixel centre, the clipper's output triangles, and every fragment (depth < 1) that reaches a pixel holding
    a key: it appends itself and the holder, two ``rec_key`` records (its depth|id key and the one it found),
    to the pixel's list (``head[p]``: the latest record, -1 when none; ``rec_next``: the one before), the
    pixel's first pair adding the pixel to ``pixels``. ``count`` = (records asked for, pixels listed); records
    past ``cap`` are left out (the caller draws again with room for them). Every fragment at a pixel that two
    reach is then listed at least once, whatever the arrival order: the second to arrive lists the first."""

    mode: int
    cap: int
    head: wp.array(dtype=wp.int32)
    rec_key: wp.array(dtype=wp.uint64)
    rec_next: wp.array(dtype=wp.int32)
    pixels: wp.array(dtype=wp.int32)
    count: wp.array(dtype=wp.int32)


# ------------------------------------------------------------------------------------------------
# functions
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


@wp.func_native("""union { float f; uint32_t u; } c; c.f = x; return c.u;""")
def float_bits(x: float) -> wp.uint32: ...


@wp.func_native("""union { float f; uint32_t u; } c; c.u = x; return c.f;""")
def bits_float(x: wp.uint32) -> float: ...


@wp.func_native("""return fmaf(a, b, c);""")
def _fma(a: float, b: float, c: float) -> float: ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
return __popc((unsigned)x);
#else
return __builtin_popcount((unsigned)x);
#endif
""")
def _popcount(x: int) -> int: ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
return atomicExch(wp::address(a, i), v);
#else
return __atomic_exchange_n(wp::address(a, i), v, __ATOMIC_RELAXED);
#endif
""")
def _exchange_i32(a: wp.array(dtype=wp.int32), i: int, v: int) -> int:
    """``a[i] = v`` atomically; returns the old value."""
    ...


@wp.func_native("""
uint64_t* k = wp::address(key, p0);
int32_t* ids = wp::address(out_id, p0);
float* dep = wp::address(out_depth, p0);
int64_t covered = 0;
if (flagged != 0) {
    for (int i = 0; i < n; ++i) {
        uint64_t v = k[i];
        union { uint32_t u; float f; } b;
        b.u = (uint32_t)(v >> 32);
        float d = b.f;
        bool c = v != 0xFFFFFFFFFFFFFFFFull;
        ids[i] = c ? (int32_t)(uint32_t)v : -1;
        dep[i] = c ? d : 1.0f;
        k[i] = 0xFFFFFFFFFFFFFFFFull;
        covered += c ? 1 : 0;
    }
} else {
    for (int i = 0; i < n; ++i) {
        ids[i] = -1;
        dep[i] = 1.0f;
    }
}
return covered;
""")
def _resolve_run(key: wp.array(dtype=wp.uint64), out_id: wp.array(dtype=wp.int32),
                 out_depth: wp.array(dtype=wp.float32), p0: int, n: int, flagged: int) -> wp.int64:
    """Pixels p0 .. p0 + n - 1 of one image row: with ``flagged``, each key decoded into its triangle id and
    window depth (-1 and 1.0 where the key is empty) and set back to empty; else background. A straight loop
    over contiguous memory the compiler vectorises. Returns the pixels covered."""
    ...


@wp.func
def _record_overlap(cnt: Counting, p: int, key: wp.uint64, held: wp.uint64):
    """A fragment (depth|id ``key``) found ``held`` at pixel p (:class:`Counting` mode 1): both appended to the
    pixel's list."""
    i = atomic_add_i32(cnt.count, 0, 2)
    if i + 2 <= cnt.cap:
        cnt.rec_key[i] = key
        cnt.rec_key[i + 1] = held
        cnt.rec_next[i + 1] = i
        prev = _exchange_i32(cnt.head, p, i + 1)
        cnt.rec_next[i] = prev
        if prev < 0:
            cnt.pixels[atomic_add_i32(cnt.count, 1, 1)] = p


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
    # round half to even, as llvmpipe's util_iround (lrintf) does
    return wp.int64(wp.rint(v * float(SUBPIXEL)))


@wp.func
def _is_top_left(dx: wp.int64, dy: wp.int64) -> wp.bool:
    # Edge a->b of a counter-clockwise triangle in window coordinates (y up, interior on the left).
    # Included edges (llvmpipe's convention for GL framebuffers, checked against it in the tests):
    # a left edge (it runs downwards, dy < 0, interior at +x) or a horizontal edge with the interior
    # above it in window y (dx > 0), which is the bottom edge of the triangle in the image.
    return dy < wp.int64(0) or (dy == wp.int64(0) and dx > wp.int64(0))


@wp.func
def _setup(c0: wp.vec4, c1: wp.vec4, c2: wp.vec4, width: int, height: int, gb: wp.vec2):
    """Trivial reject, near-plane and guard-band clipping, viewport transform and snapping.

    Returns (n, xs, ys, fxs, fys, zs): the clipped convex polygon with n vertices (0 when rejected),
    window x and y in fixed point (8 sub-pixel bits, pixel centres at k * 256 + 128), the same in float
    before snapping, and window depth.
    """
    xs = vec9l()
    ys = vec9l()
    fxs = vec9f()
    fys = vec9f()
    zs = vec9f()
    n = int(0)  # noqa: UP018 -- a mutable Warp int
    if _inside(c0, gb) and _inside(c1, gb) and _inside(c2, gb) and c0[3] > 0.0 and c1[3] > 0.0 and c2[3] > 0.0:
        # nothing to reject or clip (most triangles): what the polygon path below gives for them, without the
        # polygon arrays (the tile kernel sets a large triangle up again for every tile it is binned to)
        n = 3
        hw3 = 0.5 * float(width)
        hh3 = 0.5 * float(height)
        fa = _window(c0, hw3, hh3)
        fb = _window(c1, hw3, hh3)
        fc = _window(c2, hw3, hh3)
        fxs[0] = fa[0]
        fxs[1] = fb[0]
        fxs[2] = fc[0]
        fys[0] = fa[1]
        fys[1] = fb[1]
        fys[2] = fc[1]
        zs[0] = fa[2]
        zs[1] = fb[2]
        zs[2] = fc[2]
        for k in range(3):
            xs[k] = _snap(fxs[k])
            ys[k] = _snap(fys[k])
        return n, xs, ys, fxs, fys, zs
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
    if reject:
        return n, xs, ys, fxs, fys, zs
    poly = poly9()
    poly[0] = c0
    poly[1] = c1
    poly[2] = c2
    n = 3
    # Mesa's clipper order: the guard-band x and y planes first, then near, then far
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
    if n < 3:
        n = 0
        return n, xs, ys, fxs, fys, zs
    for k in range(n):
        if poly[k][3] <= 0.0:
            n = 0
            return n, xs, ys, fxs, fys, zs
    hw = 0.5 * float(width)
    hh = 0.5 * float(height)
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
    if _is_top_left(dx, dy):
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
def _raster_tri(ax: wp.int64, ay: wp.int64, bx: wp.int64, by: wp.int64, cx: wp.int64, cy: wp.int64,
                fa: wp.vec3, fb: wp.vec3, fc: wp.vec3, t: int, r: wp.vec4i, width: int, height: int,
                out_key: wp.array(dtype=wp.uint64), cnt: Counting) -> vec8l:
    """Cover the pixel centres of rectangle r = (x0, x1, y0, y1) inside the CCW triangle; depth-test
    with a 64-bit atomic min (a true one: chunks of a launch run on several CPU threads); with ``cnt.mode``
    1, count as :class:`Counting` says. Returns (0, fragments tested, fragments inside, pixels written, 2x2
    quads touched, 4x4 blocks touched, 0, 0) (quads and blocks with counting only)."""
    half = wp.int64(SUBPIXEL_HALF)
    one = wp.int64(SUBPIXEL)
    xmin = wp.min(ax, wp.min(bx, cx))
    xmax = wp.max(ax, wp.max(bx, cx))
    ymin = wp.min(ay, wp.min(by, cy))
    ymax = wp.max(ay, wp.max(by, cy))
    px0 = wp.max(r[0], _pixel_lo(xmin))
    px1 = wp.min(r[1], _pixel_hi(xmax))
    py0 = wp.max(r[2], _pixel_lo(ymin))
    py1 = wp.min(r[3], _pixel_hi(ymax))
    if px0 > px1 or py0 > py1:
        return vec8l()
    bias0 = _edge_bias(cx - bx, cy - by)
    bias1 = _edge_bias(ax - cx, ay - cy)
    bias2 = _edge_bias(bx - ax, by - ay)
    sx = wp.int64(px0) * one + half
    sy = wp.int64(py0) * one + half
    # E0: edge b->c (weight of a), E1: c->a (weight of b), E2: a->b (weight of c); bias folded in
    e0r = (cx - bx) * (sy - by) - (cy - by) * (sx - bx) + bias0
    e1r = (ax - cx) * (sy - cy) - (ay - cy) * (sx - cx) + bias1
    e2r = (bx - ax) * (sy - ay) - (by - ay) * (sx - ax) + bias2
    e0dx = -(cy - by) * one
    e1dx = -(ay - cy) * one
    e2dx = -(by - ay) * one
    e0dy = (cx - bx) * one
    e1dy = (ax - cx) * one
    e2dy = (bx - ax) * one
    # depth plane from the float (unsnapped) window coordinates, as llvmpipe's triangle setup does,
    # evaluated relative to the centre of pixel (px0, py0); fa = (x, y, z) of vertex a
    dx01 = fa[0] - fb[0]
    dy01 = fa[1] - fb[1]
    dx20 = fc[0] - fa[0]
    dy20 = fc[1] - fa[1]
    ooa = 1.0 / (dx01 * dy20 - dx20 * dy01)
    dz01 = fa[2] - fb[2]
    dz20 = fc[2] - fa[2]
    dzdx = (dz01 * dy20 - dz20 * dy01) * ooa
    dzdy = (dx01 * dz20 - dx20 * dz01) * ooa
    z00 = fa[2] - (dzdx * (fa[0] - (float(px0) + 0.5)) + dzdy * (fa[1] - (float(py0) + 0.5)))
    tid = wp.uint64(t)
    counting = cnt.mode == 1
    tested = wp.int64(0)
    inside = wp.int64(0)
    written = wp.int64(0)
    quads = wp.int64(0)
    blocks = wp.int64(0)
    qmask = int(0)  # noqa: UP018 -- the 2x2 quads touched in the current quad row (bit: quad column - px0 / 2)
    bmask = int(0)  # noqa: UP018 -- likewise the 4x4 blocks in the current block row
    for y in range(py0, py1 + 1):
        e0 = e0r
        e1 = e1r
        e2 = e2r
        row = (height - 1 - y) * width
        zr = z00 + dzdy * float(y - py0)
        first = px1 + 1  # the row's covered pixels: a run (the triangle is convex), first..last
        last = px0 - 1
        for x in range(px0, px1 + 1):
            if (e0 | e1 | e2) >= wp.int64(0):
                inside += wp.int64(1)
                first = wp.min(first, x)
                last = x
                # coverage is geometric (the polygon is clipped to near and far); depth is clamped
                # to [0, 1] as GL does, so a rounding excursion below 0 at the near plane stays drawn;
                # the depth test is GL_LESS against a buffer cleared to 1.0: depth 1.0 is never drawn
                d = wp.clamp(zr + dzdx * float(x - px0), 0.0, 1.0)
                if d < 1.0:
                    key = (wp.uint64(float_bits(d)) << wp.uint64(32)) | tid
                    old = atomic_min_u64(out_key, row + x, key)
                    if key < old:
                        written += wp.int64(1)
                    if counting and old != wp.uint64(0xFFFFFFFFFFFFFFFF):
                        _record_overlap(cnt, row + x, key, old)
            elif first <= last:
                break  # past the row's run: a convex triangle covers no more of it
            e0 += e0dx
            e1 += e1dx
            e2 += e2dx
        if counting:
            if first <= last:
                qmask = qmask | _run_bits((first >> 1) - (px0 >> 1), (last >> 1) - (px0 >> 1))
                bmask = bmask | _run_bits((first >> 2) - (px0 >> 2), (last >> 2) - (px0 >> 2))
            if qmask != 0 and ((y & 1) == 1 or y == py1):
                quads += wp.int64(_popcount(qmask))
                qmask = 0
            if bmask != 0 and ((y & 3) == 3 or y == py1):
                blocks += wp.int64(_popcount(bmask))
                bmask = 0
        tested += wp.int64(px1 - px0 + 1)
        e0r += e0dy
        e1r += e1dy
        e2r += e2dy
    return vec8l(wp.int64(0), tested, inside, written, quads, blocks, wp.int64(0), wp.int64(0))


@wp.func
def _run_bits(lo: int, hi: int) -> int:
    """Bits lo..hi set (0 <= lo <= hi < 31)."""
    return ((1 << (hi - lo + 1)) - 1) << lo


@wp.func
def _raster_poly(n: int, xs: vec9l, ys: vec9l, fxs: vec9f, fys: vec9f, zs: vec9f, t: int, r: wp.vec4i,
                 cull_back: int, width: int, height: int, out_key: wp.array(dtype=wp.uint64),
                 cnt: Counting) -> vec8l:
    """Draw the polygon's fan, each triangle on its own as llvmpipe does after clipping.
    Returns (fan triangles drawn, then :func:`_raster_tri`'s counts summed over them)."""
    acc = vec8l()
    for k in range(1, n - 1):
        ok, swap = _fan_tri(xs, ys, k, cull_back)
        if ok:
            kb = k
            kc = k + 1
            if swap == 1:
                kb = k + 1
                kc = k
            c = _raster_tri(xs[0], ys[0], xs[kb], ys[kb], xs[kc], ys[kc], wp.vec3(fxs[0], fys[0], zs[0]),
                            wp.vec3(fxs[kb], fys[kb], zs[kb]), wp.vec3(fxs[kc], fys[kc], zs[kc]), t, r,
                            width, height, out_key, cnt)
            acc = acc + c
            acc[0] += wp.int64(1)
    return acc


@wp.func
def _mark_tiles(out_dirty: wp.array(dtype=wp.int32), tiles_x: int, r: wp.vec4i):
    """Flag the screen tiles of pixel rectangle r = (x0, x1, y0, y1) (inside the viewport) as holding
    drawn keys: the resolve and the barycentrics visit only flagged tiles, so a caller flags every
    rectangle in which it wrote a key (a plain store of 1: concurrent writers all store the same)."""
    for ty in range(r[2] / TILE, r[3] / TILE + 1):
        for tx in range(r[0] / TILE, r[1] / TILE + 1):
            out_dirty[ty * tiles_x + tx] = 1


@wp.func
def _poly_rect(n: int, xs: vec9l, ys: vec9l, r: wp.vec4i, cull_back: int) -> wp.bool:
    """Whether some drawable fan triangle of the polygon may cover a pixel centre of rectangle r."""
    hit = wp.bool(False)
    for k in range(1, n - 1):
        ok, swap = _fan_tri(xs, ys, k, cull_back)
        if ok and not hit:
            kb = k
            kc = k + 1
            if swap == 1:
                kb = k + 1
                kc = k
            if _tri_rect(xs[0], ys[0], xs[kb], ys[kb], xs[kc], ys[kc], r):
                hit = True
    return hit


@wp.func
def _tile_rect(tx: int, ty: int, width: int, height: int) -> wp.vec4i:
    return wp.vec4i(tx * TILE, wp.min(tx * TILE + TILE - 1, width - 1),
                    ty * TILE, wp.min(ty * TILE + TILE - 1, height - 1))


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


# ------------------------------------------------------------------------------------------------
# kernels
# ------------------------------------------------------------------------------------------------


@wp.kernel(enable_backward=False)
def _vertex_kernel(
    offset: int,
    pos: wp.array(dtype=wp.vec3),
    mvp: wp.mat44,
    # outputs
    out_clip: wp.array(dtype=wp.vec4),
):
    k = wp.tid() + offset
    p = pos[k]
    out_clip[k] = mvp * wp.vec4(p[0], p[1], p[2], 1.0)


@wp.kernel
def _transform_kernel(
    pos: wp.array(dtype=wp.vec3),
    mvp: wp.mat44,
    # outputs
    out_clip: wp.array(dtype=wp.vec4),
):
    """Differentiable twin of _vertex_kernel (the same arithmetic), for gradients to positions."""
    k = wp.tid()
    p = pos[k]
    out_clip[k] = mvp * wp.vec4(p[0], p[1], p[2], 1.0)


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
    """The setup of a triangle inside every clip plane (most triangles: no clipping, no polygon arrays), the
    same arithmetic as :func:`_setup` and :func:`_raster_poly` for n = 3. Returns (drawn: not zero-area nor a
    culled back face, small: drawn at once, the CCW vertices in fixed point (ax, ay, bx, by, cx, cy) and in
    float (fa, fb, fc), its pixel box clamped to the viewport)."""
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
    box = wp.vec4i(wp.max(0, _pixel_lo(xmin)), wp.min(width - 1, _pixel_hi(xmax)),
                   wp.max(0, _pixel_lo(ymin)), wp.min(height - 1, _pixel_hi(ymax)))
    return drawn, small, ax, ay, bx, by, cx, cy, fa, fb, fc, box


@wp.func
def _add_stats(out_stats: wp.array2d(dtype=wp.int64), part: int, acc: vec8l, mode: int):
    """A drawn triangle's counts (:func:`_raster_poly`'s) into row ``part``: triangles, tested, inside, written;
    with counting (mode 1) the quads and blocks too (columns 8 and 9)."""
    wp.atomic_add(out_stats, part, 0, wp.int64(1))
    wp.atomic_add(out_stats, part, 1, acc[1])
    wp.atomic_add(out_stats, part, 2, acc[2])
    wp.atomic_add(out_stats, part, 3, acc[3])
    if mode == 1:
        wp.atomic_add(out_stats, part, 8, acc[4])
        wp.atomic_add(out_stats, part, 9, acc[5])


@wp.kernel(enable_backward=False)
def _small_count_kernel(
    offset: int,
    part: int,
    clip: wp.array(dtype=wp.vec4),
    tris: wp.array2d(dtype=wp.int32),
    width: int,
    height: int,
    cull_back: int,
    gb: wp.vec2,
    tiles_x: int,
    cnt: Counting,
    # outputs
    out_key: wp.array(dtype=wp.uint64),
    out_dirty: wp.array(dtype=wp.int32),
    out_big: wp.array(dtype=wp.int32),
    out_tile_count: wp.array(dtype=wp.int32),
    out_stats: wp.array2d(dtype=wp.int64),
):
    """Per triangle: set up; draw it at once when its pixel box spans at most SMALL_PX pixels each
    way, else count the screen tiles it may cover (out_big[t] = 1). Counters go to row ``part``; the
    tiles where a key was written are flagged in ``out_dirty``. With counting (``cnt.mode`` 1) the
    clipper's output triangles go to column 10, the quads and blocks to columns 8 and 9."""
    t = wp.tid() + offset
    out_big[t] = 0
    c0 = clip[tris[t, 0]]
    c1 = clip[tris[t, 1]]
    c2 = clip[tris[t, 2]]
    mode = cnt.mode
    inside3 = _inside(c0, gb) and _inside(c1, gb) and _inside(c2, gb)
    if inside3:
        if mode == 1:  # the clipper passes it on as it is
            wp.atomic_add(out_stats, part, 10, wp.int64(1))
        drawn, small, ax, ay, bx, by, cx, cy, fa, fb, fc, box = _fast_setup(c0, c1, c2, width, height, cull_back)
        if not drawn:
            return
        if small:
            c = _raster_tri(ax, ay, bx, by, cx, cy, fa, fb, fc, t, wp.vec4i(0, width - 1, 0, height - 1),
                            width, height, out_key, cnt)
            if c[3] > wp.int64(0):  # a key written: somewhere in the triangle's pixel box
                _mark_tiles(out_dirty, tiles_x, box)
            if c[1] > wp.int64(0):
                _add_stats(out_stats, part, c, mode)
            return
    n, xs, ys, fxs, fys, zs = _setup(c0, c1, c2, width, height, gb)
    if mode == 1 and not inside3 and n >= 3 and (cull_back == 0 or _front_facing(c0, c1, c2)):
        # a clipped polygon goes on as a fan of n - 2 triangles; with culling, llvmpipe's draw pipeline culls a
        # triangle it must clip before the clipper (the others after it, in triangle setup)
        wp.atomic_add(out_stats, part, 10, wp.int64(n - 2))
    if n == 0:
        return
    box = _poly_pixels(n, xs, ys, width, height)
    if box[0] > box[1] or box[2] > box[3]:
        return
    if box[1] - box[0] < SMALL_PX and box[3] - box[2] < SMALL_PX:
        acc = _raster_poly(n, xs, ys, fxs, fys, zs, t, box, cull_back, width, height, out_key, cnt)
        if acc[3] > wp.int64(0):
            _mark_tiles(out_dirty, tiles_x, box)
        if acc[0] > wp.int64(0):
            _add_stats(out_stats, part, acc, mode)
        return
    ntiles = int(0)  # noqa: UP018 -- a mutable Warp int
    for ty in range(box[2] / TILE, box[3] / TILE + 1):
        for tx in range(box[0] / TILE, box[1] / TILE + 1):
            if _poly_rect(n, xs, ys, _tile_rect(tx, ty, width, height), cull_back):
                atomic_add_i32(out_tile_count, ty * tiles_x + tx, 1)
                ntiles += 1
    if ntiles > 0:
        out_big[t] = 1
        wp.atomic_add(out_stats, part, 0, wp.int64(1))
        wp.atomic_add(out_stats, part, 4, wp.int64(1))
        wp.atomic_add(out_stats, part, 5, wp.int64(ntiles))


@wp.func
def _order_key(k: wp.uint64) -> wp.uint64:
    """A depth|id key as id|depth: ordered by submission (triangle id), then depth."""
    return (k << wp.uint64(32)) | (k >> wp.uint64(32))


@wp.func
def _passes_listed(head: int, rec_key: wp.array(dtype=wp.uint64), rec_next: wp.array(dtype=wp.int32)) -> wp.int64:
    """The fragments of one pixel's list (each counted once, however often listed) that pass ``GL_LESS`` in
    submission order: those whose depth is below that of every fragment of an earlier triangle. Up to
    ``_LISTED`` records are sorted in place by (triangle, depth) and scanned once; a longer list is compared
    pair by pair."""
    buf = vec_listed()
    n = int(0)  # noqa: UP018 -- a mutable Warp int
    i = head
    while i >= 0 and n < _LISTED:
        k = _order_key(rec_key[i])
        m = n  # insertion sort: the lists are short (2 records per fragment after the first)
        while m > 0 and buf[m - 1] > k:
            buf[m] = buf[m - 1]
            m -= 1
        buf[m] = k
        n += 1
        i = rec_next[i]
    passed = wp.int64(0)
    if i < 0:  # all of it sorted: a fragment passes when its depth is below every earlier one's
        best = wp.uint64(0xFFFFFFFF)  # the smallest depth bits so far (above any depth's bits: none yet)
        for m in range(n):
            if m == 0 or buf[m] != buf[m - 1]:
                d = buf[m] & wp.uint64(0xFFFFFFFF)
                if d < best:
                    passed += wp.int64(1)
                    best = d
        return passed
    i = head
    pos = int(0)  # noqa: UP018 -- i's place in the list
    while i >= 0:
        ki = rec_key[i]
        ti = wp.uint32(ki & wp.uint64(0xFFFFFFFF))
        di = wp.uint32(ki >> wp.uint64(32))  # depth bits: non-negative floats order like their bits
        ok = wp.bool(True)
        j = head
        q = int(0)  # noqa: UP018
        while j >= 0 and ok:
            kj = rec_key[j]
            if kj == ki:
                if q < pos:  # listed before: counted there
                    ok = False
            elif wp.uint32(kj & wp.uint64(0xFFFFFFFF)) < ti and wp.uint32(kj >> wp.uint64(32)) <= di:
                ok = False  # an earlier triangle's fragment at the same or a smaller depth: fails GL_LESS
            j = rec_next[j]
            q += 1
        if ok:
            passed += wp.int64(1)
        i = rec_next[i]
        pos += 1
    return passed


@wp.kernel(enable_backward=False)
def _staircase_kernel(
    offset: int,
    part: int,
    pixels: wp.array(dtype=wp.int32),
    rec_key: wp.array(dtype=wp.uint64),
    rec_next: wp.array(dtype=wp.int32),
    # outputs
    out_head: wp.array(dtype=wp.int32),
    out_stats: wp.array2d(dtype=wp.int64),
):
    """Per pixel that two fragments reached (``pixels``, :class:`Counting`): the fragments listed there that
    pass in submission order (:func:`_passes_listed`), less the first (which always passes), added to
    ``out_stats[part, 0]``; the pixel's list is then emptied (``out_head[p] = -1``)."""
    p = pixels[wp.tid() + offset]
    passed = _passes_listed(out_head[p], rec_key, rec_next)
    out_head[p] = -1
    wp.atomic_add(out_stats, part, 0, passed - wp.int64(1))


@wp.kernel(enable_backward=False)
def _bin_kernel(
    offset: int,
    clip: wp.array(dtype=wp.vec4),
    tris: wp.array2d(dtype=wp.int32),
    big: wp.array(dtype=wp.int32),
    width: int,
    height: int,
    cull_back: int,
    gb: wp.vec2,
    tiles_x: int,
    tile_start: wp.array(dtype=wp.int32),
    # outputs
    out_cursor: wp.array(dtype=wp.int32),
    out_list: wp.array(dtype=wp.int32),
):
    """Per large triangle: write its id into the list of every tile it may cover (the order within a
    tile's list depends on thread timing; what the tile kernel draws from it does not)."""
    t = wp.tid() + offset
    if big[t] == 0:
        return
    c0 = clip[tris[t, 0]]
    c1 = clip[tris[t, 1]]
    c2 = clip[tris[t, 2]]
    n, xs, ys, fxs, fys, zs = _setup(c0, c1, c2, width, height, gb)
    box = _poly_pixels(n, xs, ys, width, height)
    for ty in range(box[2] / TILE, box[3] / TILE + 1):
        for tx in range(box[0] / TILE, box[1] / TILE + 1):
            if _poly_rect(n, xs, ys, _tile_rect(tx, ty, width, height), cull_back):
                tile = ty * tiles_x + tx
                slot = atomic_add_i32(out_cursor, tile, 1)
                out_list[tile_start[tile] + slot] = t


@wp.kernel(enable_backward=False)
def _tile_kernel(
    offset: int,
    part: int,
    clip: wp.array(dtype=wp.vec4),
    tris: wp.array2d(dtype=wp.int32),
    width: int,
    height: int,
    cull_back: int,
    gb: wp.vec2,
    tiles_x: int,
    tile_start: wp.array(dtype=wp.int32),
    tile_count: wp.array(dtype=wp.int32),
    tri_list: wp.array(dtype=wp.int32),
    cnt: Counting,
    # outputs
    out_key: wp.array(dtype=wp.uint64),
    out_dirty: wp.array(dtype=wp.int32),
    out_stats: wp.array2d(dtype=wp.int64),
):
    """Per screen tile: draw the large triangles binned to it, clipped to the tile; flag it in
    ``out_dirty`` when a key was written."""
    tile = wp.tid() + offset
    ty = tile / tiles_x
    tx = tile - ty * tiles_x
    r = _tile_rect(tx, ty, width, height)
    acc = vec8l()
    s = tile_start[tile]
    for i in range(s, s + tile_count[tile]):
        t = tri_list[i]
        c0 = clip[tris[t, 0]]
        c1 = clip[tris[t, 1]]
        c2 = clip[tris[t, 2]]
        n, xs, ys, fxs, fys, zs = _setup(c0, c1, c2, width, height, gb)
        acc = acc + _raster_poly(n, xs, ys, fxs, fys, zs, t, r, cull_back, width, height, out_key, cnt)
    if acc[3] > wp.int64(0):
        out_dirty[tile] = 1
    if tile_count[tile] > 0:
        wp.atomic_add(out_stats, part, 1, acc[1])
        wp.atomic_add(out_stats, part, 2, acc[2])
        wp.atomic_add(out_stats, part, 3, acc[3])
        if cnt.mode == 1:
            wp.atomic_add(out_stats, part, 8, acc[4])
            wp.atomic_add(out_stats, part, 9, acc[5])


@wp.kernel(enable_backward=False)
def _resolve_ids_kernel(
    offset: int,
    part: int,
    dirty: wp.array(dtype=wp.int32),
    width: int,
    height: int,
    # outputs
    out_key: wp.array(dtype=wp.uint64),
    out_id: wp.array(dtype=wp.int32),
    out_depth: wp.array(dtype=wp.float32),
    out_covered: wp.array(dtype=wp.int64),
):
    """Decode the depth|id keys of the flagged screen tiles (``dirty``) of one band of TILE window rows (band
    ``ty``, from window row 0 up) into the triangle id and window depth of each drawn pixel, and set the key back
    to empty: unflagged tiles hold no drawn key, so the buffer is then clear for the next frame. Row by row
    (memory order); every pixel of the band is written, background as -1 and 1.0. Covered pixels are counted
    into ``out_covered[part]``."""
    ty = wp.tid() + offset
    tiles_x = (width + TILE - 1) / TILE
    covered = wp.int64(0)
    for y in range(ty * TILE, wp.min(ty * TILE + TILE, height)):
        p0 = (height - 1 - y) * width
        x0 = int(0)  # runs of tiles flagged alike, one straight loop each
        for tx in range(1, tiles_x + 1):
            flag = int(dirty[ty * tiles_x + tx - 1] != 0)
            ends = tx == tiles_x
            if not ends:
                ends = int(dirty[ty * tiles_x + tx] != 0) != flag
            if ends:
                x1 = wp.min(tx * TILE, width)
                covered += _resolve_run(out_key, out_id, out_depth, p0 + x0, x1 - x0, flag)
                x0 = x1
    wp.atomic_add(out_covered, part, covered)  # one writer per part on the CPU; a true atomic on CUDA


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


@wp.kernel
def interpolate_kernel(
    pix_id: wp.array3d(dtype=wp.int32),
    clip: wp.array(dtype=wp.vec4),
    tris: wp.array2d(dtype=wp.int32),
    attr: wp.array2d(dtype=wp.float32),
    # outputs
    out: wp.array3d(dtype=wp.float32),
):
    """Differentiable resolve, one thread per (row, column, channel); background gives 0.

    ``pix_id`` is the (H, W, C) triangle id image repeated over the C channels: the first input's shape
    is the launch and output shape that ``warp.jax_kernel`` infers (it takes no ``output_dims`` with
    ``enable_backward=True``). Differentiable with respect to ``clip`` and ``attr``."""
    i, j, ch = wp.tid()
    t = pix_id[i, j, ch]
    v = float(0.0)
    if t >= 0:
        i0 = tris[t, 0]
        i1 = tris[t, 1]
        i2 = tris[t, 2]
        b = clip_barycentrics(clip[i0], clip[i1], clip[i2], pixel_ndc(i, j, pix_id.shape[0], pix_id.shape[1]))
        v = b[0] * attr[i0, ch] + b[1] * attr[i1, ch] + b[2] * attr[i2, ch]
    out[i, j, ch] = v


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
        stats: per-frame counters: triangles_in; triangles_rasterized (that reached the coverage test
            after trivial rejection, clipping, zero-area and back-face culling); triangles_binned (large
            triangles drawn tile by tile) and tile_entries; fragments_tested (pixel centres
            evaluated), fragments_inside (centres covered), pixels_written (depth tests passed), and
            pixels_covered (non-background pixels in the end). pixels_written alone depends on the
            order of the depth tests, so, as on a GPU, it may differ between runs with more than one
            thread (``terrainwarp.set_threads``); the images and every other counter never do.
        counters: the pipeline statistics of the draw, as OpenGL's ARB_pipeline_statistics_query names them,
            when asked for (``counters=True``; None otherwise), bit-identical for any thread count:
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

    Iterating yields (triangle_id, depth, barycentrics, stats), as the earlier NamedTuple did.
    """

    __slots__ = ("triangle_id", "depth", "stats", "counters", "_bary", "_clip", "_tris", "_device", "_ids",
                 "_rows", "_tiles")

    def __init__(self, triangle_id, depth, barycentrics, stats, *, clip=None, tris=None, device="cpu", ids=None,
                 rows=None, tiles=None):
        self.triangle_id = triangle_id
        self.depth = depth
        self.stats = stats
        self.counters: dict[str, int] | None = None
        self._bary = barycentrics
        self._clip, self._tris, self._device = clip, tris, device
        self._ids = ids  # the triangle ids as a device array (on the CPU: triangle_id's own memory)
        self._rows = rows  # image rows [top, bottom) outside which every pixel is background
        self._tiles = tiles  # int32 flag per screen tile (window order), 0: every pixel in it is background

    @property
    def barycentrics(self) -> np.ndarray:
        if self._bary is None:
            hh, ww = self.triangle_id.shape
            dirty = _band_tiles(ww, hh, self._rows) if self._tiles is None else self._tiles
            bands = _bands(dirty, ww)
            ids = self._ids
            if ids is None or ids.device.is_cuda:  # the host image, as the caller may have changed it
                ids = wp.array(self.triangle_id, dtype=wp.int32, device=self._device)
            out = _filled((hh, ww), wp.vec2, 0.0, self._device)  # the background; the kernel writes covered pixels
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
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: expected finite entries")
    return a


def _check_triangles(triangles: object, n: int) -> np.ndarray:
    tri = np.asarray(triangles)
    if tri.ndim != 2 or tri.shape[1] != 3:
        raise ValueError(f"triangles: expected shape (m, 3), got {tri.shape}")
    if tri.size and not np.issubdtype(tri.dtype, np.integer):
        raise TypeError(f"triangles: expected an integer array, got {tri.dtype}")
    if tri.size and (tri.min() < 0 or tri.max() >= n):
        raise ValueError(f"triangles: indices must lie in [0, {n}), got [{tri.min()}, {tri.max()}]")
    return np.ascontiguousarray(tri, dtype=np.int32).reshape(-1, 3)


def _check_size(width: object, height: object) -> tuple[int, int]:
    for nm, v in (("width", width), ("height", height)):
        if not is_int(v):
            raise TypeError(f"{nm}: expected an integer, got {v!r}")
        if not 1 <= int(v) <= 16384:
            raise ValueError(f"{nm}: expected 1..16384 pixels, got {v}")
    return int(width), int(height)


# Depth|id key buffers, all empty, on scratch leases of the frame-buffer pool (pool.take), by (device, pixels): the
# drawing kernels flag each screen tile in which they wrote a key, and the resolve reads the flagged tiles only and
# sets every drawn key it reads back to empty, so a buffer is given back clear and the next frame of that size
# clears nothing (a frame-sized fill per frame saved; the resolve's cost follows the tiles drawn, not the viewport).
# A rasterize that fails part-way never gives its lease back: that buffer is dropped.
_KEYS_KEPT = 2  # buffers kept per (device, size)


def _new_keys(npx: int, device: str) -> wp.array:
    if wp.get_device(device).is_cpu:
        key_np = np.empty(npx, np.uint64)  # numpy's large allocations ask for huge pages (parallel.empty)
        key_np.view(np.uint8).fill(255)  # all ones: the empty key (a byte fill is faster than wp.full)
        return wp.array(key_np, dtype=wp.uint64, device=device, copy=False)
    return wp.full(npx, value=_EMPTY_KEY, dtype=wp.uint64, device=device)


def _take_keys(npx: int, device: str):
    """A scratch lease of an all-empty key buffer of ``npx`` pixels (``lease.buffer``)."""
    return take(("raster_keys", str(wp.get_device(device)), npx), lambda: _new_keys(npx, device), keep=_KEYS_KEPT)


def _tiles_x(width: int) -> int:
    return (width + TILE - 1) // TILE


def _band_tiles(width: int, height: int, rows: tuple[int, int] | None) -> np.ndarray:
    """Flags (int32, window tile order, as the binning's) of the screen tiles that meet image rows
    [top, bottom), all of them with None."""
    top, bottom = (0, height) if rows is None else rows
    tx = _tiles_x(width)
    flags = np.zeros(tx * ((height + TILE - 1) // TILE), np.int32)
    if bottom > top:
        flags[(height - bottom) // TILE * tx:((height - 1 - top) // TILE + 1) * tx] = 1
    return flags


def _bands(dirty: np.ndarray, width: int) -> np.ndarray:
    """The rows of screen tiles (int32, from window row 0 up) with a flagged tile."""
    return np.flatnonzero(dirty.reshape(-1, _tiles_x(width)).any(axis=1)).astype(np.int32)


# Output images (ids, depth, barycentrics) on the CPU come from the frame-buffer pool (parallel.pooled): a frame's
# images are the caller's, but once the caller holds no view of one any more, the next frame of that size takes it
# again. Freshly allocated frame-sized memory costs page faults on its first write (~5-10 ms for a 1080p frame's
# 32 MB here, more than drawing 10k triangles); memory seen before costs a fill.
_IMAGES_KEPT = 2  # per (shape, dtype): the frame being made and the one before it, still held by its caller
_IMAGES_MAX_BYTES = 64 << 20  # larger images are not kept


def _image(shape: tuple[int, ...], dtype: type) -> np.ndarray:
    """An uninitialised host array for an output image: a kept one no view of which is alive, else a new one."""
    return pooled(shape, dtype, keep=_IMAGES_KEPT, max_bytes=_IMAGES_MAX_BYTES)


def _output(shape: int | tuple[int, ...], dtype: type, device: str) -> wp.array:
    """A new output array, uninitialised (on the CPU a kept image, see _image, or a new one)."""
    if not wp.get_device(device).is_cpu:
        return wp.empty(shape, dtype=dtype, device=device)
    return wp.array(_image(*host_layout(shape, dtype)), dtype=dtype, device=device, copy=False)


def _filled(shape: int | tuple[int, ...], dtype: type, value: float, device: str) -> wp.array:
    """A new output array holding ``value`` everywhere (on the CPU a kept image, see _image, or a new one)."""
    shape = (shape,) if isinstance(shape, int) else tuple(shape)
    if not wp.get_device(device).is_cpu:
        return wp.zeros(shape, dtype=dtype, device=device) if value == 0 else \
            wp.full(shape, value=value, dtype=dtype, device=device)
    a = _image(*host_layout(shape, dtype))
    a.fill(value)
    return wp.array(a, dtype=dtype, device=device, copy=False)


def _resolve(key: wp.array, dirty: wp.array, width: int, height: int, device: str):
    """Ids and depth images from the keys, decoding only the screen tiles flagged in ``dirty``; every other
    pixel is background, filled on the host. -> (ids (H, W), depth (H, W), device ids, the tile flags (int32),
    pixels covered)."""
    npx = width * height
    out_id, out_depth = _output(npx, wp.int32, device), _output(npx, wp.float32, device)  # the kernel writes all
    covered = wp.zeros(max_parts(), dtype=wp.int64, device=device)
    launch(_resolve_ids_kernel, (height + TILE - 1) // TILE, [dirty, width, height], [key, out_id, out_depth, covered],
           device, parts=True, min_items=_MIN_PIXELS // (TILE * width) + 1)
    ids = out_id.numpy().reshape(height, width)
    depth = out_depth.numpy().reshape(height, width)
    if not wp.get_device(device).is_cpu:  # numpy() copied: the device arrays keep the kernel's values only
        out_id = None
    return ids, depth, out_id, dirty.numpy(), int(covered.numpy().sum())


# Counting: the lists' heads of a frame of that size, all -1, on scratch leases of the frame-buffer pool (pool.take)
# by (device, pixels): the staircase pass empties every list it reads (as the resolve empties the keys), so a buffer
# is given back all -1; and the records a frame of that size has needed at most (the room the next one is given; a
# frame that needs more is drawn again with room for them).
_RECORDS: dict[tuple[str, int], int] = {}
_NO_COUNTING: dict[str, Counting] = {}  # the Counting argument with counting off, per device


def _take_heads(npx: int, device: str) -> Lease:
    """A scratch lease of an all -1 heads buffer of ``npx`` pixels (``lease.buffer``)."""
    return take(("raster_heads", str(wp.get_device(device)), npx),
                lambda: wp.full(npx, value=-1, dtype=wp.int32, device=device), keep=_KEYS_KEPT)


def _counting(npx: int, device: str) -> tuple[Counting, Lease]:
    """A :class:`Counting` in mode 1 for a frame of ``npx`` pixels, with room for the records such a frame has
    needed so far (at least a quarter of the pixels), and the lease of its heads."""
    cnt = Counting()
    cnt.mode = 1
    cnt.cap = max(_RECORDS.get((str(wp.get_device(device)), npx), 0), npx // 4, 1 << 12)
    heads = _take_heads(npx, device)
    cnt.head = heads.buffer
    cnt.rec_key = pooled_array(cnt.cap, wp.uint64, device)
    cnt.rec_next = pooled_array(cnt.cap, wp.int32, device)
    cnt.pixels = pooled_array(cnt.cap // 2 + 1, wp.int32, device)
    cnt.count = wp.zeros(2, dtype=wp.int32, device=device)
    return cnt, heads


def _no_counting(device: str) -> Counting:
    key = str(wp.get_device(device))
    if key not in _NO_COUNTING:
        cnt = Counting()
        cnt.mode = 0
        cnt.cap = 0
        cnt.head = wp.zeros(1, dtype=wp.int32, device=device)
        cnt.rec_key = wp.zeros(1, dtype=wp.uint64, device=device)
        cnt.rec_next = wp.zeros(1, dtype=wp.int32, device=device)
        cnt.pixels = wp.zeros(1, dtype=wp.int32, device=device)
        cnt.count = wp.zeros(2, dtype=wp.int32, device=device)
        _NO_COUNTING[key] = cnt
    return _NO_COUNTING[key]


def _passed_after_first(cnt: Counting, heads: Lease, npx: int, device: str) -> tuple[int, int]:
    """The fragments that pass the depth test in submission order after the first at their pixel
    (:func:`_staircase_kernel` over the listed pixels, which empties their lists), and the records the frame
    asked for (more than ``cnt.cap``: some were left out, the count is short). Gives the heads back."""
    asked, listed = (int(v) for v in cnt.count.numpy())
    stats = wp.zeros((max_parts(_OVERSPLIT), 1), dtype=wp.int64, device=device)
    launch(_staircase_kernel, listed, [cnt.pixels, cnt.rec_key, cnt.rec_next], [cnt.head, stats], device,
           parts=True, min_items=_MIN_PIXELS // 8, oversplit=_OVERSPLIT)
    heads.give_back()  # every list read is empty again
    return int(stats.numpy().sum()), asked


def _rasterize_clip(clip: wp.array, n: int, tri: np.ndarray, width: int, height: int, cull_back: bool,
                    device: str, counters: bool = False) -> Fragments:
    npx = width * height
    lease = _take_keys(npx, device)
    key = lease.buffer
    stats = wp.zeros((max_parts(_OVERSPLIT), 16), dtype=wp.int64, device=device)  # a row per chunk, added up below
    m = int(tri.shape[0])
    tri_wp = as_warp(tri if m else np.zeros((1, 3), np.int32), wp.int32, device)  # not copied on the CPU
    tiles_x = _tiles_x(width)
    tiles_y = (height + TILE - 1) // TILE
    dirty = as_warp(np.zeros(tiles_x * tiles_y, np.int32), wp.int32, device)  # flags of the tiles with keys written
    cnt, heads = _counting(npx, device) if counters else (_no_counting(device), None)
    if n and m:
        gb = wp.vec2(1.0 + 2.0 * GUARD_BAND_PX / width, 1.0 + 2.0 * GUARD_BAND_PX / height)
        cb = int(bool(cull_back))
        big = wp.empty(m, dtype=wp.int32, device=device)
        tile_count = wp.zeros(tiles_x * tiles_y, dtype=wp.int32, device=device)
        launch(_small_count_kernel, m, [clip, tri_wp, width, height, cb, gb, tiles_x, cnt],
               [key, dirty, big, tile_count, stats], device, parts=True, min_items=_MIN_TRIANGLES,
               oversplit=_OVERSPLIT)
        total = int(stats.numpy()[:, 5].sum())
        if total:
            tile_start = wp.empty_like(tile_count)
            scan(tile_count, tile_start, inclusive=False)
            cursor = wp.zeros_like(tile_count)
            tri_list = wp.empty(total, dtype=wp.int32, device=device)
            launch(_bin_kernel, m, [clip, tri_wp, big, width, height, cb, gb, tiles_x, tile_start],
                   [cursor, tri_list], device, min_items=_MIN_TRIANGLES)
            launch(_tile_kernel, tiles_x * tiles_y,
                   [clip, tri_wp, width, height, cb, gb, tiles_x, tile_start, tile_count, tri_list, cnt],
                   [key, dirty, stats], device, parts=True, min_items=_MIN_TILES,
                   oversplit=_OVERSPLIT)
    ids, depth, ids_wp, tiles, covered = _resolve(key, dirty, width, height, device)
    lease.give_back()  # every key drawn is empty again
    if counters:
        extra, asked = _passed_after_first(cnt, heads, npx, device)
        if asked > cnt.cap:  # records left out: the frame again, with room for them (the buffers are clear)
            _RECORDS[(str(wp.get_device(device)), npx)] = asked
            return _rasterize_clip(clip, n, tri, width, height, cull_back, device, counters)
    c = stats.numpy()[:, :11].sum(axis=0)  # integer sums: the same whatever the chunks
    stats_d = {"triangles_in": m, "triangles_rasterized": int(c[0]), "triangles_binned": int(c[4]),
               "tile_entries": int(c[5]), "fragments_tested": int(c[1]), "fragments_inside": int(c[2]),
               "pixels_written": int(c[3]), "pixels_covered": covered}
    frag = Fragments(ids, depth, None, stats_d, clip=clip, tris=tri_wp, device=device, ids=ids_wp, tiles=tiles)
    if counters:
        frag.counters = {"clipping_input_primitives": m, "clipping_output_primitives": int(c[10]),
                         "fragment_shader_invocations": 4 * int(c[8]),
                         "fragment_shader_invocations_llvmpipe": 16 * int(c[9]),
                         "samples_passed": covered + extra, "samples_covered": int(c[2]), "pixels_covered": covered}
    return frag


def rasterize(positions: object, triangles: object, view: object, proj: object, width: int, height: int,
              *, cull_back: bool = False, counters: bool = False, device: str = "cpu") -> Fragments:
    """Rasterize a triangle mesh with any matrices (no assumption about which axis is up).

    Args:
        positions: (n, 3) float32 vertex positions (float64 input is cast; camera-relative
            positions with a translation-free view matrix keep far terrains precise).
        triangles: (m, 3) int32 vertex indices, counter-clockwise front faces.
        view, proj: (4, 4) matrices (OpenGL conventions, clip z in [-w, w]).
        width, height: viewport in pixels (1..16384).
        cull_back: drop clockwise (back-facing) triangles, as ``glEnable(GL_CULL_FACE)``.
        counters: also count the draw's pipeline statistics (:attr:`Fragments.counters`); the images are the
            same either way.

    Returns:
        :class:`Fragments`. Deterministic: bit-identical on every run.
    """
    pos = np.asarray(positions)
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ValueError(f"positions: expected shape (n, 3), got {pos.shape}")
    if not np.issubdtype(pos.dtype, np.floating):
        raise TypeError(f"positions: expected a float array, got {pos.dtype}")
    tri = _check_triangles(triangles, len(pos))
    width, height = _check_size(width, height)
    clip = _transform(pos, view, proj, device)
    return _rasterize_clip(clip, len(pos), tri, width, height, cull_back, device, _flag("counters", counters))


def _transform(pos: np.ndarray, view: object, proj: object, device: str) -> wp.array:
    pos32 = np.ascontiguousarray(pos, dtype=np.float32)
    if not np.all(np.isfinite(pos32)):
        raise ValueError("positions: expected finite coordinates")
    mvp = (_as_matrix("proj", proj) @ _as_matrix("view", view)).astype(np.float32)
    clip = wp.empty(max(len(pos32), 1), dtype=wp.vec4, device=device)
    if len(pos32):
        launch(_vertex_kernel, len(pos32), [as_warp(pos32, wp.vec3, device),
                                            wp.mat44(*mvp.reshape(-1).tolist())], [clip], device)
    return clip


def clip_coordinates(positions: object, view: object, proj: object, *, device: str = "cpu") -> np.ndarray:
    """The clip-space vertices :func:`rasterize` computes: (n, 4) float32 ``(proj @ view) @ (p, 1)``,
    with the product of the matrices rounded to float32 first, as a vertex shader's uniform would be."""
    pos = np.asarray(positions)
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ValueError(f"positions: expected shape (n, 3), got {pos.shape}")
    return _transform(pos, view, proj, device).numpy()[: len(pos)].reshape(-1, 4)


def rasterize_clip(clip: object, triangles: object, width: int, height: int, *, cull_back: bool = False,
                   counters: bool = False, device: str = "cpu") -> Fragments:
    """Rasterize triangles given clip-space vertices, as a GPU does after the vertex shader.

    Args:
        clip: (n, 4) float32 clip-space positions (x, y, z, w), OpenGL conventions.
        triangles: (m, 3) int32 vertex indices; width, height: viewport in pixels (1..16384).
        cull_back: drop clockwise triangles.
        counters: also count the pipeline statistics (:attr:`Fragments.counters`).

    Returns:
        :class:`Fragments`, as :func:`rasterize`.
    """
    c = np.asarray(clip)
    if c.ndim != 2 or c.shape[1] != 4:
        raise ValueError(f"clip: expected shape (n, 4), got {c.shape}")
    if not np.issubdtype(c.dtype, np.floating):
        raise TypeError(f"clip: expected a float array, got {c.dtype}")
    tri = _check_triangles(triangles, len(c))
    width, height = _check_size(width, height)
    c32 = np.ascontiguousarray(c, dtype=np.float32)
    if not np.all(np.isfinite(c32)):
        raise ValueError("clip: expected finite coordinates")
    clip_wp = wp.array(c32 if len(c32) else np.zeros((1, 4), np.float32), dtype=wp.vec4, device=device)
    return _rasterize_clip(clip_wp, len(c32), tri, width, height, cull_back, device, _flag("counters", counters))


def _flag(name: str, v: object) -> bool:
    return check_bool(name, v)


def transform_warp(positions: wp.array, view: object, proj: object) -> wp.array:
    """Differentiable vertex transform on Warp arrays, recorded by an active ``wp.Tape``: (n,) vec3
    positions -> (n,) vec4 clip coordinates, bit-identical to what :func:`rasterize` uses."""
    mvp = (_as_matrix("proj", proj) @ _as_matrix("view", view)).astype(np.float32)
    out = wp.zeros(positions.shape[0], dtype=wp.vec4, device=positions.device, requires_grad=positions.requires_grad)
    launch_one(_transform_kernel, dim=positions.shape[0], inputs=[positions, wp.mat44(*mvp.reshape(-1).tolist())],
               outputs=[out], device=positions.device)
    return out


def interpolate_warp(pix_id: wp.array, clip: wp.array, triangles: wp.array, attr: wp.array) -> wp.array:
    """Differentiable resolve on Warp arrays; recorded by an active ``wp.Tape``.

    Args:
        pix_id: (H, W, C) int32 triangle id per pixel (-1 background), the visibility pass's
            ``triangle_id`` repeated over the C channels.
        clip: (n,) vec4 clip-space vertices (differentiable; ``requires_grad`` for gradients).
        triangles: (m, 3) int32.
        attr: (n, C) float32 vertex attributes (differentiable).

    Returns:
        (H, W, C) float32 perspective-correct interpolation at the pixel centres; 0 on background.
        Gradients flow to ``clip`` (through the barycentrics recomputed from clip coordinates, as
        nvdiffrast's ``interpolate`` does) and to ``attr``; none through the (discrete) coverage.
    """
    out = wp.zeros(pix_id.shape, dtype=wp.float32, device=attr.device,
                   requires_grad=bool(clip.requires_grad or attr.requires_grad))
    launch_one(interpolate_kernel, dim=pix_id.shape, inputs=[pix_id, clip, triangles, attr], outputs=[out],
               device=attr.device)
    return out


def interpolate(attr: object, triangle_id: object, clip: object, triangles: object, *,
                device: str = "cpu") -> np.ndarray:
    """Perspective-correct interpolation of vertex attributes at pixel centres (forward only; see
    :func:`interpolate_warp` for the tape and ``terrainwarp.diff.interpolate`` for JAX).

    Args:
        attr: (n, C) or (n,) float32 per-vertex attributes (position, normal, uv, level, ...).
        triangle_id: (H, W) int32 from :func:`rasterize` / :func:`rasterize_clip`.
        clip: (n, 4) float32 clip-space vertices (those the visibility pass used).
        triangles: (m, 3) int32.

    Returns:
        (H, W, C) float32 (or (H, W) for 1-D ``attr``), 0 on background.
    """
    a = np.asarray(attr, dtype=np.float32)
    squeeze = a.ndim == 1
    if squeeze:
        a = a[:, None]
    c = np.asarray(clip, dtype=np.float32)
    if c.ndim != 2 or c.shape[1] != 4:
        raise ValueError(f"clip: expected shape (n, 4), got {c.shape}")
    if a.ndim != 2 or a.shape[0] != c.shape[0]:
        raise ValueError(f"attr: expected shape ({c.shape[0]}, C), got {a.shape}")
    ids = np.asarray(triangle_id)
    if ids.ndim != 2:
        raise ValueError(f"triangle_id: expected shape (H, W), got {ids.shape}")
    tri = _check_triangles(triangles, len(c))
    if ids.size and ids.max() >= max(len(tri), 0):
        raise ValueError(f"triangle_id: ids must be < {len(tri)}, got {ids.max()}")
    hh, ww = ids.shape
    ch = a.shape[1]
    pid = np.ascontiguousarray(np.broadcast_to(ids.astype(np.int32)[..., None], (hh, ww, ch)))
    out = interpolate_warp(
        wp.array(pid, dtype=wp.int32, device=device),
        wp.array(c if len(c) else np.zeros((1, 4), np.float32), dtype=wp.vec4, device=device),
        wp.array(tri if len(tri) else np.zeros((1, 3), np.int32), dtype=wp.int32, device=device),
        wp.array(a if len(a) else np.zeros((1, ch), np.float32), dtype=wp.float32, device=device)).numpy()
    return out[..., 0] if squeeze else out

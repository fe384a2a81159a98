"""The rasterizer: a visibility pass (coverage + depth test) and a barycentric pass, as Warp kernels.

Visibility (one launch over triangles, non-differentiable):

1. Vertices are transformed to clip space by one kernel (``clip = proj @ view @ (p, 1)``, float32).
2. Each triangle is trivially rejected when all three vertices lie outside one clip plane, then
   clipped against the near plane ``z >= -w`` (Sutherland-Hodgman), and against guard-band planes
   ``|x|, |y| <= GB * w`` only when a vertex lies outside the guard band, so window coordinates stay
   well inside the fixed-point range. The far plane and the viewport are applied per pixel (depth in
   [0, 1], pixel inside the viewport), which covers the same pixels as geometric clipping.
3. Window coordinates are snapped to a fixed-point grid with 8 bits of sub-pixel precision
   (round to nearest), and the clipped polygon is drawn as a fan.
4. Coverage uses 64-bit integer edge functions at pixel centres (x + 0.5, y + 0.5) with the top-left
   fill rule (a pixel centre exactly on an edge belongs to the triangle for which that edge is a top
   edge or a left edge, in the visual sense: image row 0 at the top), so a centre on an edge shared
   by two triangles is covered by exactly one of them.
5. Depth is interpolated linearly in window space (z_ndc is affine in screen space) and the test keeps
   the nearest fragment with one ``atomic_min`` on a 64-bit key ``(float bits of depth) << 32 | id``:
   window depth is a non-negative float, whose bit pattern orders like its value, so ties go to the
   lower triangle id and the result never depends on the order of the launch.

The barycentric pass (one launch over pixels) decodes the key and computes perspective-correct
barycentrics of the pixel centre on the original (unclipped) triangle from its clip-space vertices:
with ``a_i = x_i - px*w_i`` and ``c_i = y_i - py*w_i`` (px, py the centre in NDC), the barycentrics
are ``cross(a, c) / sum(cross(a, c))``. They stay exact for clipped triangles, whose clipped vertices
lie on the original plane.

Output images have row 0 at the top (window y is flipped once, here).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import warp as wp

SUBPIXEL_BITS = 8
SUBPIXEL = 1 << SUBPIXEL_BITS
SUBPIXEL_HALF = SUBPIXEL // 2
GUARD_BAND_PX = 16384.0  # window coordinates are kept within [-GB, size + GB]
_EMPTY_KEY = np.uint64(0xFFFFFFFFFFFFFFFF)

poly9 = wp.types.matrix(shape=(9, 4), dtype=wp.float32)
vec9l = wp.types.vector(length=9, dtype=wp.int64)
vec9f = wp.types.vector(length=9, dtype=wp.float32)

# ------------------------------------------------------------------------------------------------
# functions
# ------------------------------------------------------------------------------------------------


@wp.func
def _clip_poly(poly: poly9, n: int, plane: wp.vec4) -> tuple[poly9, int]:
    """Sutherland-Hodgman clip of an n-gon (rows of poly) against dot(plane, v) >= 0."""
    out = poly9()
    m = int(0)
    for k in range(n):
        a = poly[k]
        b = poly[(k + 1) % n]
        da = wp.dot(plane, a)
        db = wp.dot(plane, b)
        if da >= 0.0:
            out[m] = a
            m += 1
        if (da >= 0.0) != (db >= 0.0):
            t = da / (da - db)
            out[m] = a + t * (b - a)
            m += 1
    return out, m


@wp.func_native("""union { float f; uint32_t u; } c; c.f = x; return c.u;""")
def float_bits(x: float) -> wp.uint32: ...


@wp.func_native("""union { float f; uint32_t u; } c; c.u = x; return c.f;""")
def bits_float(x: wp.uint32) -> float: ...


@wp.func
def _floordiv(a: wp.int64, b: wp.int64) -> wp.int64:
    """floor(a / b) for b > 0 (C division truncates towards zero)."""
    if a >= wp.int64(0):
        return a / b
    return -((-a + b - wp.int64(1)) / b)


@wp.func
def _snap(v: float) -> wp.int64:
    return wp.int64(wp.floor(v * float(SUBPIXEL) + 0.5))


@wp.func
def _is_top_left(dx: wp.int64, dy: wp.int64) -> wp.bool:
    # Edge a->b of a counter-clockwise triangle in window coordinates (y up, interior on the left).
    # Visually (row 0 at the top): a top edge is horizontal with the interior below (dx < 0);
    # a left edge has the interior to its right (it runs downwards, dy < 0).
    return dy < wp.int64(0) or (dy == wp.int64(0) and dx < wp.int64(0))


# ------------------------------------------------------------------------------------------------
# kernels
# ------------------------------------------------------------------------------------------------


@wp.kernel(enable_backward=False)
def _vertex_kernel(
    pos: wp.array(dtype=wp.vec3),
    mvp: wp.mat44,
    # outputs
    out_clip: wp.array(dtype=wp.vec4),
):
    k = wp.tid()
    p = pos[k]
    out_clip[k] = mvp * wp.vec4(p[0], p[1], p[2], 1.0)


@wp.kernel(enable_backward=False)
def _raster_kernel(
    clip: wp.array(dtype=wp.vec4),
    tris: wp.array2d(dtype=wp.int32),
    width: int,
    height: int,
    cull_back: int,
    gb: wp.vec2,
    # outputs
    out_key: wp.array(dtype=wp.uint64),
    out_count: wp.array(dtype=wp.int64),
):
    t = wp.tid()
    c0 = clip[tris[t, 0]]
    c1 = clip[tris[t, 1]]
    c2 = clip[tris[t, 2]]
    # trivial reject against the six clip planes
    if c0[0] > c0[3] and c1[0] > c1[3] and c2[0] > c2[3]:
        return
    if c0[0] < -c0[3] and c1[0] < -c1[3] and c2[0] < -c2[3]:
        return
    if c0[1] > c0[3] and c1[1] > c1[3] and c2[1] > c2[3]:
        return
    if c0[1] < -c0[3] and c1[1] < -c1[3] and c2[1] < -c2[3]:
        return
    if c0[2] > c0[3] and c1[2] > c1[3] and c2[2] > c2[3]:
        return
    if c0[2] < -c0[3] and c1[2] < -c1[3] and c2[2] < -c2[3]:
        return
    poly = poly9()
    poly[0] = c0
    poly[1] = c1
    poly[2] = c2
    n = int(3)
    if c0[2] < -c0[3] or c1[2] < -c1[3] or c2[2] < -c2[3]:
        poly, n = _clip_poly(poly, n, wp.vec4(0.0, 0.0, 1.0, 1.0))
    # guard band (only when needed)
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
    if n < 3:
        return
    # to window coordinates, fixed point; z_ndc kept as float
    xs = vec9l()
    ys = vec9l()
    zs = vec9f()
    hw = 0.5 * float(width)
    hh = 0.5 * float(height)
    for k in range(n):
        v = poly[k]
        iw = 1.0 / v[3]
        xs[k] = _snap((v[0] * iw + 1.0) * hw)
        ys[k] = _snap((v[1] * iw + 1.0) * hh)
        zs[k] = v[2] * iw
    # orientation of the polygon (sum over the fan)
    area2 = wp.int64(0)
    for k in range(1, n - 1):
        area2 += (xs[k] - xs[0]) * (ys[k + 1] - ys[0]) - (xs[k + 1] - xs[0]) * (ys[k] - ys[0])
    if area2 == wp.int64(0):
        return
    if cull_back != 0 and area2 < wp.int64(0):
        return
    tested = wp.int64(0)
    half = wp.int64(SUBPIXEL_HALF)
    one = wp.int64(SUBPIXEL)
    for k in range(1, n - 1):
        ax = xs[0]
        ay = ys[0]
        bx = xs[k]
        by = ys[k]
        cx = xs[k + 1]
        cy = ys[k + 1]
        za = zs[0]
        zb = zs[k]
        zc = zs[k + 1]
        area = (bx - ax) * (cy - ay) - (cx - ax) * (by - ay)
        if area == wp.int64(0):
            continue
        if area < wp.int64(0):  # make it counter-clockwise
            tx = bx
            ty = by
            tz = zb
            bx = cx
            by = cy
            zb = zc
            cx = tx
            cy = ty
            zc = tz
            area = -area
        # bounding box in pixels whose centres may be covered
        xmin = wp.min(ax, wp.min(bx, cx))
        xmax = wp.max(ax, wp.max(bx, cx))
        ymin = wp.min(ay, wp.min(by, cy))
        ymax = wp.max(ay, wp.max(by, cy))
        px0 = int(wp.max(wp.int64(0), _floordiv(xmin - half + one - wp.int64(1), one)))
        px1 = int(wp.min(wp.int64(width - 1), _floordiv(xmax - half, one)))
        py0 = int(wp.max(wp.int64(0), _floordiv(ymin - half + one - wp.int64(1), one)))
        py1 = int(wp.min(wp.int64(height - 1), _floordiv(ymax - half, one)))
        if px0 > px1 or py0 > py1:
            continue
        # edge functions E_ab(P) = (b - a) x (P - a); bias excludes non-top-left edges at E == 0
        bias0 = wp.int64(0)
        bias1 = wp.int64(0)
        bias2 = wp.int64(0)
        if not _is_top_left(cx - bx, cy - by):
            bias0 = wp.int64(-1)
        if not _is_top_left(ax - cx, ay - cy):
            bias1 = wp.int64(-1)
        if not _is_top_left(bx - ax, by - ay):
            bias2 = wp.int64(-1)
        sx = wp.int64(px0) * one + half
        sy = wp.int64(py0) * one + half
        # E0: edge b->c (weight of a), E1: c->a (weight of b), E2: a->b (weight of c)
        e0r = (cx - bx) * (sy - by) - (cy - by) * (sx - bx)
        e1r = (ax - cx) * (sy - cy) - (ay - cy) * (sx - cx)
        e2r = (bx - ax) * (sy - ay) - (by - ay) * (sx - ax)
        e0dx = -(cy - by) * one
        e1dx = -(ay - cy) * one
        e2dx = -(by - ay) * one
        e0dy = (cx - bx) * one
        e1dy = (ax - cx) * one
        e2dy = (bx - ax) * one
        inv_area = 1.0 / float(area)
        dzb = zb - za
        dzc = zc - za
        for py in range(py0, py1 + 1):
            e0 = e0r
            e1 = e1r
            e2 = e2r
            row = (height - 1 - py) * width
            for px in range(px0, px1 + 1):
                tested += wp.int64(1)
                if e0 + bias0 >= wp.int64(0) and e1 + bias1 >= wp.int64(0) and e2 + bias2 >= wp.int64(0):
                    zn = za + (float(e1) * dzb + float(e2) * dzc) * inv_area
                    d = 0.5 * zn + 0.5
                    if d >= 0.0 and d <= 1.0:
                        key = (wp.uint64(float_bits(d)) << wp.uint64(32)) | wp.uint64(t)
                        wp.atomic_min(out_key, row + px, key)
                e0 += e0dx
                e1 += e1dx
                e2 += e2dx
            e0r += e0dy
            e1r += e1dy
            e2r += e2dy
    wp.atomic_add(out_count, 0, wp.int64(1))
    wp.atomic_add(out_count, 1, tested)


@wp.kernel(enable_backward=False)
def _resolve_ids_kernel(
    key: wp.array(dtype=wp.uint64),
    clip: wp.array(dtype=wp.vec4),
    tris: wp.array2d(dtype=wp.int32),
    width: int,
    height: int,
    # outputs
    out_id: wp.array(dtype=wp.int32),
    out_depth: wp.array(dtype=wp.float32),
    out_bary: wp.array(dtype=wp.vec2),
):
    p = wp.tid()
    k = key[p]
    if k == wp.uint64(0xFFFFFFFFFFFFFFFF):
        out_id[p] = -1
        out_depth[p] = 1.0
        out_bary[p] = wp.vec2(0.0, 0.0)
        return
    t = int(k & wp.uint64(0xFFFFFFFF))
    out_id[p] = t
    out_depth[p] = bits_float(wp.uint32(k >> wp.uint64(32)))
    row = p / width
    col = p - row * width
    wy = height - 1 - row
    nx = (float(col) + 0.5) / float(width) * 2.0 - 1.0
    ny = (float(wy) + 0.5) / float(height) * 2.0 - 1.0
    c0 = clip[tris[t, 0]]
    c1 = clip[tris[t, 1]]
    c2 = clip[tris[t, 2]]
    a = wp.vec3(c0[0] - nx * c0[3], c1[0] - nx * c1[3], c2[0] - nx * c2[3])
    c = wp.vec3(c0[1] - ny * c0[3], c1[1] - ny * c1[3], c2[1] - ny * c2[3])
    b = wp.cross(a, c)
    s = b[0] + b[1] + b[2]
    if s != 0.0:
        out_bary[p] = wp.vec2(b[0] / s, b[1] / s)
    else:
        out_bary[p] = wp.vec2(1.0 / 3.0, 1.0 / 3.0)


# ------------------------------------------------------------------------------------------------
# host
# ------------------------------------------------------------------------------------------------


class Fragments(NamedTuple):
    """The visibility pass's output; images have row 0 at the top.

    Attributes:
        triangle_id: (H, W) int32, the visible triangle per pixel, -1 for background.
        depth: (H, W) float32 window depth in [0, 1] (1.0 for background).
        barycentrics: (H, W, 2) float32 perspective-correct weights (b0, b1) of the triangle's
            vertices 0 and 1 at the pixel centre (b2 = 1 - b0 - b1); 0 for background.
        stats: counters: triangles_in, triangles_rasterized (after rejection, clipping and culling),
            fragments_tested, pixels_covered.
    """

    triangle_id: np.ndarray
    depth: np.ndarray
    barycentrics: np.ndarray
    stats: dict


def _as_matrix(name: str, m: object) -> np.ndarray:
    a = np.asarray(m, dtype=np.float64)
    if a.shape != (4, 4):
        raise ValueError(f"{name}: expected a (4, 4) matrix, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: expected finite entries")
    return a


def rasterize(positions: object, triangles: object, view: object, proj: object, width: int, height: int,
              *, cull_back: bool = False, device: str = "cpu") -> Fragments:
    """Rasterize a triangle mesh with any matrices (no assumption about which axis is up).

    Args:
        positions: (n, 3) float32 vertex positions (float64 input is cast; camera-relative
            positions with a translation-free view matrix keep far terrains precise).
        triangles: (m, 3) int32 vertex indices, counter-clockwise front faces.
        view, proj: (4, 4) matrices (OpenGL conventions, clip z in [-w, w]).
        width, height: viewport in pixels (1..16384).
        cull_back: drop clockwise (back-facing) triangles, as ``glEnable(GL_CULL_FACE)``.

    Returns:
        :class:`Fragments`. Deterministic: bit-identical on every run.
    """
    pos = np.asarray(positions)
    tri = np.asarray(triangles)
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ValueError(f"positions: expected shape (n, 3), got {pos.shape}")
    if not np.issubdtype(pos.dtype, np.floating):
        raise TypeError(f"positions: expected a float array, got {pos.dtype}")
    if tri.ndim != 2 or tri.shape[1] != 3:
        raise ValueError(f"triangles: expected shape (m, 3), got {tri.shape}")
    if tri.size and not np.issubdtype(tri.dtype, np.integer):
        raise TypeError(f"triangles: expected an integer array, got {tri.dtype}")
    for nm, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, int | np.integer):
            raise TypeError(f"{nm}: expected an integer, got {v!r}")
        if not 1 <= int(v) <= 16384:
            raise ValueError(f"{nm}: expected 1..16384 pixels, got {v}")
    width, height = int(width), int(height)
    if tri.size and (tri.min() < 0 or tri.max() >= len(pos)):
        raise ValueError(f"triangles: indices must lie in [0, {len(pos)}), got [{tri.min()}, {tri.max()}]")
    pos32 = np.ascontiguousarray(pos, dtype=np.float32)
    if not np.all(np.isfinite(pos32)):
        raise ValueError("positions: expected finite coordinates")
    mvp = (_as_matrix("proj", proj) @ _as_matrix("view", view)).astype(np.float32)
    npx = width * height
    key = wp.array(np.full(npx, _EMPTY_KEY, dtype=np.uint64), dtype=wp.uint64, device=device)
    count = wp.zeros(2, dtype=wp.int64, device=device)
    clip = wp.empty(max(len(pos32), 1), dtype=wp.vec4, device=device)
    m = int(tri.shape[0])
    tri_wp = wp.array(np.ascontiguousarray(tri, dtype=np.int32).reshape(m, 3) if m else
                      np.zeros((1, 3), np.int32), dtype=wp.int32, device=device)
    if len(pos32) and m:
        wp.launch(_vertex_kernel, dim=len(pos32), inputs=[wp.array(pos32, dtype=wp.vec3, device=device),
                                                          wp.mat44(*mvp.reshape(-1).tolist())],
                  outputs=[clip], device=device)
        gb = wp.vec2(1.0 + 2.0 * GUARD_BAND_PX / width, 1.0 + 2.0 * GUARD_BAND_PX / height)
        wp.launch(_raster_kernel, dim=m, inputs=[clip, tri_wp, width, height, int(bool(cull_back)), gb],
                  outputs=[key, count], device=device)
    out_id = wp.empty(npx, dtype=wp.int32, device=device)
    out_depth = wp.empty(npx, dtype=wp.float32, device=device)
    out_bary = wp.empty(npx, dtype=wp.vec2, device=device)
    wp.launch(_resolve_ids_kernel, dim=npx, inputs=[key, clip, tri_wp, width, height],
              outputs=[out_id, out_depth, out_bary], device=device)
    ids = out_id.numpy().reshape(height, width)
    c = count.numpy()
    stats = {"triangles_in": m, "triangles_rasterized": int(c[0]), "fragments_tested": int(c[1]),
             "pixels_covered": int((ids >= 0).sum())}
    return Fragments(ids, out_depth.numpy().reshape(height, width),
                     out_bary.numpy().reshape(height, width, 2), stats)

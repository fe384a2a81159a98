"""Analytic antialiasing of silhouette and occlusion edges (Laine et al. 2020, "Modular Primitives for
High-Performance Differentiable Rendering", section 3.4), forward and a hand-written backward.

For each pair of horizontally or vertically adjacent pixels A, B (A left of / above B) with different
triangle ids:

1. The front triangle T of the pair is the one of the two nearer the camera at its own pixel centre
   (window depth from the clip-space vertices; background is farthest; equal depths: the lower id).
2. An edge of T is a silhouette edge when no triangle lies across it (``neighbours`` -1: a mesh border or
   a non-manifold edge) or the one across it faces the other way (the sign of ``det[x y w]`` of the clip
   vertices, the homogeneous facing test, so edges of triangles crossing w = 0 are classed right too).
3. The first silhouette edge of T (in edge order 0: v0-v1, 1: v1-v2, 2: v2-v0) whose segment crosses the
   segment between the two pixel centres, both edge vertices at w > 0, gives the crossing position alpha
   in [0, 1] from A's centre to B's (pixel units). A horizontal pair takes only steep edges (``|dx| <= |dy|``
   on screen) and a vertical pair only the others, so each edge is filtered once, along the axis it
   crosses most: moving an edge by d pixels across it then changes the image by d per pixel row (or
   column) it spans, as it changes the covered area.
4. The pixel whose footprint (one pixel wide along the pair) holds the crossing is blended towards the
   other: ``out[A] += max(0.5 - alpha, 0) (c[B] - c[A])`` and ``out[B] += max(alpha - 0.5, 0) (c[A] -
   c[B])``. Whichever side T is on, this is the same formula. The image stays continuous when the edge
   crosses a pixel centre (the ids change there and the blend hands over), so its derivative with
   respect to the vertices is the derivative of coverage.

Gradients reach the colours (a gather over the four pairs of each pixel) and the clip coordinates of the
two edge vertices through alpha. Deterministic: every pixel gathers its own four pairs (forward and colour
gradient), and each triangle adds the pairs it owns, walking its coverage box (widened by one pixel up and
left, where a pair's A pixel may lie) in row-major order; corners are then summed per vertex in a fixed
order (``gradients.corners_to_vertices``). No float atomics.
"""

from __future__ import annotations

import warp as wp

from .gradients import box_rows, clip_barycentrics, corners_to_vertices, coverage_box, pixel_ndc
from .parallel import launch

_MIN_PIXELS = 32768
_MIN_TRIANGLES = 1024
_OVERSPLIT = 4
_FAR = 3.0e38  # depth of the background (farther than any window depth)

# ------------------------------------------------------------------------------------------------
# functions
# ------------------------------------------------------------------------------------------------


@wp.func
def _window(c: wp.vec4, hw: float, hh: float) -> wp.vec2:
    """Window x, y in pixels (y up) of a clip vertex with w > 0: x / w * W/2 + W/2."""
    return wp.vec2(c[0] / c[3] * hw + hw, c[1] / c[3] * hh + hh)


@wp.func
def _centre(i: int, j: int, h: int) -> wp.vec2:
    """Window position (pixels, y up) of the centre of image pixel (row i from the top, column j)."""
    return wp.vec2(float(j) + 0.5, float(h - 1 - i) + 0.5)


@wp.func
def _depth(clip: wp.array(dtype=wp.vec4), tris: wp.array2d(dtype=wp.int32), t: int, i: int, j: int, h: int,
           w: int) -> float:
    """z / w of triangle t's surface at the centre of pixel (i, j); background is farthest."""
    if t < 0:
        return _FAR
    c0 = clip[tris[t, 0]]
    c1 = clip[tris[t, 1]]
    c2 = clip[tris[t, 2]]
    b = clip_barycentrics(c0, c1, c2, pixel_ndc(i, j, h, w))
    return (b[0] * c0[2] + b[1] * c1[2] + b[2] * c2[2]) / (b[0] * c0[3] + b[1] * c1[3] + b[2] * c2[3])


@wp.func
def _facing(clip: wp.array(dtype=wp.vec4), tris: wp.array2d(dtype=wp.int32), t: int) -> float:
    """Sign of det[x y w] of the triangle's clip vertices (counter-clockwise on screen when > 0)."""
    c0 = clip[tris[t, 0]]
    c1 = clip[tris[t, 1]]
    c2 = clip[tris[t, 2]]
    d = wp.dot(wp.vec3(c0[0], c0[1], c0[3]), wp.cross(wp.vec3(c1[0], c1[1], c1[3]), wp.vec3(c2[0], c2[1], c2[3])))
    return wp.sign(d)


@wp.func
def _cross2(a: wp.vec2, b: wp.vec2) -> float:
    return a[0] * b[1] - a[1] * b[0]


@wp.func
def _pair(ids: wp.array2d(dtype=wp.int32), clip: wp.array(dtype=wp.vec4), tris: wp.array2d(dtype=wp.int32),
          nbr: wp.array2d(dtype=wp.int32), ia: int, ja: int, ib: int, jb: int) -> wp.vec3:
    """The pair (A, B) = ((ia, ja), (ib, jb)): (T, k, alpha) as floats, T = -1 when nothing is blended."""
    none = wp.vec3(-1.0, 0.0, 0.0)
    ta = ids[ia, ja]
    tb = ids[ib, jb]
    if ta == tb:
        return none
    h = ids.shape[0]
    w = ids.shape[1]
    da = _depth(clip, tris, ta, ia, ja, h, w)
    db = _depth(clip, tris, tb, ib, jb, h, w)
    t = tb
    if da < db or (da == db and ta >= 0 and ta < tb):
        t = ta
    if t < 0:
        return none
    pa = _centre(ia, ja, h)
    pb = _centre(ib, jb, h)
    hw = 0.5 * float(w)
    hh = 0.5 * float(h)
    face = _facing(clip, tris, t)
    for k in range(3):
        n = nbr[t, k]
        silhouette = n < 0
        if not silhouette:
            silhouette = _facing(clip, tris, n) != face
        c0 = clip[tris[t, k]]
        c1 = clip[tris[t, (k + 1) % 3]]
        if silhouette and c0[3] > 0.0 and c1[3] > 0.0:
            v0 = _window(c0, hw, hh)
            v1 = _window(c1, hw, hh)
            e = v1 - v0
            fa = _cross2(e, pa - v0)
            fb = _cross2(e, pb - v0)
            s = pb - pa
            g0 = _cross2(s, v0 - pa)
            g1 = _cross2(s, v1 - pa)
            steep = wp.abs(e[0]) <= wp.abs(e[1])  # a horizontal pair takes steep edges, a vertical pair the others
            if fa * fb < 0.0 and g0 * g1 <= 0.0 and steep == (ia == ib):
                return wp.vec3(float(t), float(k), fa / (fa - fb))
    return none


@wp.func
def _alpha_grad(c0: wp.vec4, c1: wp.vec4, pa: wp.vec2, pb: wp.vec2, hw: float, hh: float, ga: float):
    """d(loss)/d(clip) of the edge's two vertices from d(loss)/d(alpha), alpha = fA / (fA - fB) with
    f(P) = cross(v1 - v0, P - v0) and v = window(clip)."""
    v0 = _window(c0, hw, hh)
    v1 = _window(c1, hw, hh)
    e = v1 - v0
    fa = _cross2(e, pa - v0)
    fb = _cross2(e, pb - v0)
    den = fa - fb
    gfa = -ga * fb / (den * den)
    gfb = ga * fa / (den * den)
    g0 = gfa * wp.vec2(v1[1] - pa[1], pa[0] - v1[0]) + gfb * wp.vec2(v1[1] - pb[1], pb[0] - v1[0])
    g1 = gfa * wp.vec2(pa[1] - v0[1], v0[0] - pa[0]) + gfb * wp.vec2(pb[1] - v0[1], v0[0] - pb[0])
    return _window_grad(c0, g0, hw, hh), _window_grad(c1, g1, hw, hh)


@wp.func
def _window_grad(c: wp.vec4, g: wp.vec2, hw: float, hh: float) -> wp.vec4:
    iw = 1.0 / c[3]
    gx = g[0] * hw
    gy = g[1] * hh
    return wp.vec4(gx * iw, gy * iw, 0.0, -(gx * c[0] + gy * c[1]) * iw * iw)


@wp.func
def _weights(alpha: float) -> wp.vec2:
    """Blend weights (of A towards B, of B towards A) for a crossing at alpha."""
    return wp.vec2(wp.max(0.5 - alpha, 0.0), wp.max(alpha - 0.5, 0.0))


@wp.func
def _neighbour_pair(ids: wp.array2d(dtype=wp.int32), clip: wp.array(dtype=wp.vec4),
                    tris: wp.array2d(dtype=wp.int32), nbr: wp.array2d(dtype=wp.int32), i: int, j: int, d: int):
    """Pair d of pixel (i, j) (0 left, 1 right, 2 up, 3 down): (ok, neighbour row, column, weight of (i, j),
    weight of the neighbour)."""
    di = 0
    dj = 0
    if d == 0:
        dj = -1
    if d == 1:
        dj = 1
    if d == 2:
        di = -1
    if d == 3:
        di = 1
    qi = i + di
    qj = j + dj
    if qi < 0 or qj < 0 or qi >= ids.shape[0] or qj >= ids.shape[1]:
        return False, qi, qj, 0.0, 0.0
    if ids[i, j] == ids[qi, qj]:
        return False, qi, qj, 0.0, 0.0
    first = d == 1 or d == 3  # (i, j) is A
    r = wp.vec3()
    if first:
        r = _pair(ids, clip, tris, nbr, i, j, qi, qj)
    else:
        r = _pair(ids, clip, tris, nbr, qi, qj, i, j)
    if r[0] < 0.0:
        return False, qi, qj, 0.0, 0.0
    wab = _weights(r[2])
    if first:
        return True, qi, qj, wab[0], wab[1]
    return True, qi, qj, wab[1], wab[0]


# ------------------------------------------------------------------------------------------------
# kernels
# ------------------------------------------------------------------------------------------------


@wp.kernel(enable_backward=False)
def _antialias_kernel(
    offset: int,
    color: wp.array3d(dtype=wp.float32),
    ids: wp.array2d(dtype=wp.int32),
    clip: wp.array(dtype=wp.vec4),
    tris: wp.array2d(dtype=wp.int32),
    nbr: wp.array2d(dtype=wp.int32),
    # outputs
    out: wp.array3d(dtype=wp.float32),
):
    """out[p] = c[p] + sum over p's pairs (left, right, up, down) of w_p (c[q] - c[p])."""
    i, j = wp.tid()
    i += offset
    nc = color.shape[2]
    for ch in range(nc):
        out[i, j, ch] = color[i, j, ch]
    for d in range(4):
        ok, qi, qj, wself, wq = _neighbour_pair(ids, clip, tris, nbr, i, j, d)
        if ok and wself > 0.0:
            for ch in range(nc):
                out[i, j, ch] += wself * (color[qi, qj, ch] - color[i, j, ch])


@wp.kernel(enable_backward=False)
def _color_grad_kernel(
    offset: int,
    ids: wp.array2d(dtype=wp.int32),
    clip: wp.array(dtype=wp.vec4),
    tris: wp.array2d(dtype=wp.int32),
    nbr: wp.array2d(dtype=wp.int32),
    g: wp.array3d(dtype=wp.float32),
    # outputs
    out: wp.array3d(dtype=wp.float32),
):
    """d(loss)/d(c[p]) = g[p] (1 - sum of w_p) + sum of w_q g[q], over p's pairs in a fixed order."""
    i, j = wp.tid()
    i += offset
    nc = g.shape[2]
    for ch in range(nc):
        out[i, j, ch] = g[i, j, ch]
    for d in range(4):
        ok, qi, qj, wself, wq = _neighbour_pair(ids, clip, tris, nbr, i, j, d)
        if ok:
            for ch in range(nc):
                out[i, j, ch] += wq * g[qi, qj, ch] - wself * g[i, j, ch]


@wp.func
def _pair_clip_grad(color: wp.array3d(dtype=wp.float32), ids: wp.array2d(dtype=wp.int32),
                    clip: wp.array(dtype=wp.vec4), tris: wp.array2d(dtype=wp.int32),
                    nbr: wp.array2d(dtype=wp.int32), g: wp.array3d(dtype=wp.float32), t: int, ia: int, ja: int,
                    ib: int, jb: int):
    """(owned, k, d/dclip of edge vertex k, of vertex k+1) of the pair (A, B) for triangle t."""
    zero = wp.vec4()
    if ib >= ids.shape[0] or jb >= ids.shape[1] or ia < 0 or ja < 0:
        return False, 0, zero, zero
    r = _pair(ids, clip, tris, nbr, ia, ja, ib, jb)
    if int(r[0]) != t:
        return False, 0, zero, zero
    k = int(r[1])
    alpha = r[2]
    ga = float(0.0)  # d(loss)/d(alpha)
    for ch in range(color.shape[2]):
        dc = color[ib, jb, ch] - color[ia, ja, ch]
        if alpha < 0.5:
            ga -= g[ia, ja, ch] * dc
        if alpha > 0.5:
            ga -= g[ib, jb, ch] * dc
    h = ids.shape[0]
    hw = 0.5 * float(ids.shape[1])
    hh = 0.5 * float(h)
    g0, g1 = _alpha_grad(clip[tris[t, k]], clip[tris[t, (k + 1) % 3]], _centre(ia, ja, h), _centre(ib, jb, h),
                         hw, hh, ga)
    return True, k, g0, g1


@wp.kernel(enable_backward=False)
def _clip_grad_kernel(
    offset: int,
    box: wp.array2d(dtype=wp.int32),
    color: wp.array3d(dtype=wp.float32),
    ids: wp.array2d(dtype=wp.int32),
    clip: wp.array(dtype=wp.vec4),
    tris: wp.array2d(dtype=wp.int32),
    nbr: wp.array2d(dtype=wp.int32),
    g: wp.array3d(dtype=wp.float32),
    # outputs
    out_corner: wp.array2d(dtype=wp.float32),
):
    """Per triangle t: d(loss)/d(clip) of its corners (rows 3t..3t+2) from the pairs it is the front
    triangle of, A pixels walked in row-major order over its coverage box widened up and left by one."""
    t = wp.tid() + offset
    acc0 = wp.vec4()
    acc1 = wp.vec4()
    acc2 = wp.vec4()
    r = box_rows(box, t)
    for i in range(r[0] - 1, r[1] + 1):
        for j in range(r[2] - 1, r[3] + 1):
            for d in range(2):  # the right pair, then the down pair of A = (i, j)
                ok, k, g0, g1 = _pair_clip_grad(color, ids, clip, tris, nbr, g, t, i, j, i + d, j + 1 - d)
                if ok:
                    if k == 0:
                        acc0 += g0
                        acc1 += g1
                    elif k == 1:
                        acc1 += g0
                        acc2 += g1
                    else:
                        acc2 += g0
                        acc0 += g1
    for c in range(4):
        out_corner[3 * t, c] = acc0[c]
        out_corner[3 * t + 1, c] = acc1[c]
        out_corner[3 * t + 2, c] = acc2[c]


# ------------------------------------------------------------------------------------------------
# host (Warp arrays in, Warp arrays out: called from the JAX callables of terrainwarp.diff)
# ------------------------------------------------------------------------------------------------


def antialias_forward(color: wp.array, ids: wp.array, clip: wp.array, tris: wp.array, nbr: wp.array,
                      out: wp.array) -> None:
    """(H, W, C) colour, (H, W) ids, (n,) vec4 clip, (m, 3) triangles, (m, 3) edge neighbours -> ``out``."""
    launch(_antialias_kernel, ids.shape, [color, ids, clip, tris, nbr], [out], out.device, min_items=_MIN_PIXELS)


def antialias_backward(color: wp.array, ids: wp.array, clip: wp.array, tris: wp.array, nbr: wp.array,
                       g: wp.array, out_color: wp.array, out_clip: wp.array) -> None:
    """Gradients of :func:`antialias_forward` for the (H, W, C) gradient ``g``: ``out_color`` (H, W, C) and
    ``out_clip`` (n, 4) float32."""
    dev = ids.device
    launch(_color_grad_kernel, ids.shape, [ids, clip, tris, nbr, g], [out_color], dev, min_items=_MIN_PIXELS)
    m = tris.shape[0]
    corner = wp.empty((3 * m, 4), dtype=wp.float32, device=dev)
    box = coverage_box(ids, m)
    launch(_clip_grad_kernel, m, [box, color, ids, clip, tris, nbr, g], [corner], dev, min_items=_MIN_TRIANGLES,
           oversplit=_OVERSPLIT)
    corners_to_vertices(tris, corner, out_clip)

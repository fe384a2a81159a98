"""The vertex stages of the LOD schemes engines ship (CDLOD, Chunked LOD with skirts, geometry clipmaps), as
Warp launches over every vertex / quad of a frame. The host side (selection, parameters, what each
publication prescribes) lives in ``terrainwarp.lod.cdlod``, ``terrainwarp.lod.chunked`` and
``terrainwarp.lod.clipmaps``.

Coordinates: heightmap cell units (column ``cx`` along +x, row ``cz`` along +z), as in
:mod:`.displacement`; a lattice point is placed like :func:`.displacement.grid_mesh` places sample
(i, j): ``rel_origin.x + cx * dx`` in float32, height minus the eye height. Integer cells therefore give
the grid mesh's vertices bit for bit, and every scheme's full-detail mesh passes through every sample.
Cells outside the grid are clamped to its border (degenerate triangles there), as the tessellator does.

Grids of items (CDLOD quadrants, chunks) are triangulated like the grid mesh: per quad
``(v00, v10, v01), (v01, v10, v11)`` (v01 one step along +x, v10 one step along +z), counter-clockwise
seen from +y. Every launch goes through :func:`.parallel.launch` (one launch per stage per frame).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .displacement import write_quad
from .lod import (
    QuadTree,
    TreeWalk,
    box_distance,
    box_outside,
    keep_inside,
    node_box,
    node_index,
    push_children,
    screen_error,
    walk_roots,
)
from .parallel import empty, launch, scan, view
from .sampling import sample_bilinear

# ------------------------------------------------------------------------------------------------
# functions
# ------------------------------------------------------------------------------------------------


@wp.func
def _place(h: wp.array2d(dtype=wp.float32), cx: float, cz: float, rel: wp.vec3, dx: float, dz: float) -> wp.vec3:
    """Camera-relative surface point at cell coordinates (cx, cz), clamped to the grid, bilinear height."""
    x = wp.clamp(cx, 0.0, float(h.shape[1] - 1))
    z = wp.clamp(cz, 0.0, float(h.shape[0] - 1))
    return wp.vec3(rel[0] + x * dx, sample_bilinear(h, x, z) - rel[1], rel[2] + z * dz)


@wp.func
def _uv(h: wp.array2d(dtype=wp.float32), cx: float, cz: float) -> wp.vec2:
    x = wp.clamp(cx, 0.0, float(h.shape[1] - 1))
    z = wp.clamp(cz, 0.0, float(h.shape[0] - 1))
    return wp.vec2(x / float(wp.max(h.shape[1] - 1, 1)), z / float(wp.max(h.shape[0] - 1, 1)))


@wp.func
def _coarse_surface(h: wp.array2d(dtype=wp.float32), cx: float, cz: float, s2: float) -> float:
    """Height at grid point (cx, cz) (inside the grid) of the coarser clipmap level's surface: its lattice has
    spacing ``s2`` cells, its quads clamped to the grid like any quad, split along the grid's diagonal."""
    w1 = float(h.shape[1] - 1)
    h1 = float(h.shape[0] - 1)
    ncx = wp.max(int(wp.ceil(w1 / s2)), 1)
    ncz = wp.max(int(wp.ceil(h1 / s2)), 1)
    kx = wp.min(int(wp.floor(cx / s2)), ncx - 1)
    kz = wp.min(int(wp.floor(cz / s2)), ncz - 1)
    x0 = float(kx) * s2
    z0 = float(kz) * s2
    x1 = wp.min(x0 + s2, w1)
    z1 = wp.min(z0 + s2, h1)
    tx = wp.where(x1 > x0, (cx - x0) / (x1 - x0), 0.0)
    tz = wp.where(z1 > z0, (cz - z0) / (z1 - z0), 0.0)
    h00 = sample_bilinear(h, x0, z0)
    h01 = sample_bilinear(h, x1, z0)
    h10 = sample_bilinear(h, x0, z1)
    h11 = sample_bilinear(h, x1, z1)
    if tx + tz <= 1.0:  # triangle (v00, v10, v01)
        return h00 + tx * (h01 - h00) + tz * (h10 - h00)
    return h11 + (1.0 - tx) * (h10 - h11) + (1.0 - tz) * (h01 - h11)


# ------------------------------------------------------------------------------------------------
# kernels: grids of items (CDLOD quadrants, chunks)
# ------------------------------------------------------------------------------------------------


@wp.kernel(enable_backward=False)
def _cdlod_vertices_kernel(
    offset: int,
    h: wp.array2d(dtype=wp.float32),
    item_origin: wp.array(dtype=wp.vec2),
    item_step: wp.array(dtype=wp.float32),
    item_lod: wp.array(dtype=wp.int32),
    n: int,
    morph_start: wp.array(dtype=wp.float32),
    morph_inv: wp.array(dtype=wp.float32),
    rel: wp.vec3,
    dx: float,
    dz: float,
    # outputs
    out_pos: wp.array(dtype=wp.vec3),
    out_uv: wp.array(dtype=wp.vec2),
    out_level: wp.array(dtype=wp.int32),
    out_item: wp.array(dtype=wp.int32),
):
    k = wp.tid() + offset
    per = (n + 1) * (n + 1)
    item = k / per
    r = k - item * per
    a = r % (n + 1)
    b = r / (n + 1)
    step = item_step[item]
    o = item_origin[item]
    cx = o[0] + float(a) * step
    cz = o[1] + float(b) * step
    lod = item_lod[item]
    # the morph factor from the eye distance of the unmorphed vertex (Strugar's vertex shader)
    p = _place(h, cx, cz, rel, dx, dz)
    km = wp.clamp((wp.length(p) - morph_start[lod]) * morph_inv[lod], 0.0, 1.0)
    # odd vertices of the level's lattice slide toward their even (parent-lattice) neighbour
    ga = int(wp.round(o[0] / step)) + a
    gb = int(wp.round(o[1] / step)) + b
    mx = cx - float(ga % 2) * step * km
    mz = cz - float(gb % 2) * step * km
    out_pos[k] = _place(h, mx, mz, rel, dx, dz)
    out_uv[k] = _uv(h, mx, mz)
    out_level[k] = lod
    out_item[k] = item


@wp.kernel(enable_backward=False)
def _item_triangles_kernel(
    offset: int,
    n: int,
    stride: int,
    # outputs
    out_tri: wp.array2d(dtype=wp.int32),
):
    k = wp.tid() + offset  # quad k of the frame: item, then row b, then column a
    per = n * n
    item = k / per
    r = k - item * per
    a = r % n
    b = r / n
    v00 = item * stride + b * (n + 1) + a
    write_quad(out_tri, 2 * k, v00, v00 + 1, v00 + n + 1, v00 + n + 2)


@wp.func
def _edge_vertex(n: int, e: int, t: int) -> int:
    """Local index of vertex t (0..n) along edge e (0: u=0, 1: v=0, 2: u=1, 3: v=1) of an (n+1)^2 grid."""
    if e == 0:
        return t * (n + 1)
    if e == 1:
        return t
    if e == 2:
        return t * (n + 1) + n
    return n * (n + 1) + t


@wp.kernel(enable_backward=False)
def _chunk_vertices_kernel(
    offset: int,
    h: wp.array2d(dtype=wp.float32),
    item_origin: wp.array(dtype=wp.vec2),
    item_step: wp.array(dtype=wp.float32),
    item_level: wp.array(dtype=wp.int32),
    item_skirt: wp.array(dtype=wp.float32),
    n: int,
    rel: wp.vec3,
    dx: float,
    dz: float,
    # outputs
    out_pos: wp.array(dtype=wp.vec3),
    out_uv: wp.array(dtype=wp.vec2),
    out_level: wp.array(dtype=wp.int32),
    out_item: wp.array(dtype=wp.int32),
):
    k = wp.tid() + offset
    grid = (n + 1) * (n + 1)
    stride = grid + 4 * (n + 1)
    item = k / stride
    r = k - item * stride
    drop = float(0.0)
    if r >= grid:  # a skirt vertex: below vertex t of edge e
        e = (r - grid) / (n + 1)
        r = _edge_vertex(n, e, (r - grid) - e * (n + 1))
        drop = item_skirt[item]
    step = item_step[item]
    o = item_origin[item]
    cx = o[0] + float(r % (n + 1)) * step
    cz = o[1] + float(r / (n + 1)) * step
    p = _place(h, cx, cz, rel, dx, dz)
    out_pos[k] = wp.vec3(p[0], p[1] - drop, p[2])
    out_uv[k] = _uv(h, cx, cz)
    out_level[k] = item_level[item]
    out_item[k] = item


@wp.kernel(enable_backward=False)
def _chunk_triangles_kernel(
    offset: int,
    n: int,
    item_mask: wp.array(dtype=wp.int32),
    item_start: wp.array(dtype=wp.int32),
    # outputs
    out_tri: wp.array2d(dtype=wp.int32),
):
    c, t = wp.tid()
    c += offset
    grid = (n + 1) * (n + 1)
    base = c * (grid + 4 * (n + 1))
    start = item_start[c]
    if t < 2 * n * n:  # the chunk's grid
        if t % 2 == 0:
            q = t / 2
            v00 = base + (q / n) * (n + 1) + q % n
            write_quad(out_tri, start + t, v00, v00 + 1, v00 + n + 1, v00 + n + 2)
        return
    s = t - 2 * n * n
    e = s / (2 * n)
    mask = item_mask[c]
    if ((mask >> e) & 1) == 0 or s % 2 == 1:
        return
    below = int(0)  # skirted edges before e: their triangles come first
    for f in range(4):
        if f < e:
            below += (mask >> f) & 1
    seg = (s - e * 2 * n) / 2
    top0 = base + _edge_vertex(n, e, seg)
    top1 = base + _edge_vertex(n, e, seg + 1)
    bot0 = base + grid + e * (n + 1) + seg
    o = start + 2 * n * n + below * 2 * n + 2 * seg
    out_tri[o, 0] = top0
    out_tri[o, 1] = top1
    out_tri[o, 2] = bot0
    out_tri[o + 1, 0] = top1
    out_tri[o + 1, 1] = bot0 + 1
    out_tri[o + 1, 2] = bot0


# ------------------------------------------------------------------------------------------------
# kernels: clipmap levels
# ------------------------------------------------------------------------------------------------


@wp.kernel(enable_backward=False)
def _clipmap_vertices_kernel(
    offset: int,
    h: wp.array2d(dtype=wp.float32),
    lv_origin: wp.array(dtype=wp.vec2),
    lv_spacing: wp.array(dtype=wp.float32),
    lv_coarser: wp.array(dtype=wp.int32),
    lv_level: wp.array(dtype=wp.int32),
    n: int,
    viewer: wp.vec2,
    alpha_offset: float,
    width: float,
    rel: wp.vec3,
    dx: float,
    dz: float,
    # outputs
    out_pos: wp.array(dtype=wp.vec3),
    out_uv: wp.array(dtype=wp.vec2),
    out_level: wp.array(dtype=wp.int32),
    out_item: wp.array(dtype=wp.int32),
):
    k = wp.tid() + offset
    li = k / (n * n)
    r = k - li * n * n
    a = r % n
    b = r / n
    s = lv_spacing[li]
    o = lv_origin[li]
    cx = o[0] + float(a) * s
    cz = o[1] + float(b) * s
    x = wp.clamp(cx, 0.0, float(h.shape[1] - 1))
    z = wp.clamp(cz, 0.0, float(h.shape[0] - 1))
    zf = sample_bilinear(h, x, z)
    y = zf
    if lv_coarser[li] != 0:
        # GPU Gems 2 ch. 2: alpha from the viewer's distance, per axis, in this level's grid units
        ax = wp.clamp((wp.abs(cx - viewer[0]) / s - alpha_offset) / width, 0.0, 1.0)
        az = wp.clamp((wp.abs(cz - viewer[1]) / s - alpha_offset) / width, 0.0, 1.0)
        alpha = wp.max(ax, az)
        if a == 0 or b == 0 or a == n - 1 or b == n - 1:
            alpha = 1.0  # the outer border is the coarse level's surface exactly (not 1 - rounding)
        zc = _coarse_surface(h, x, z, 2.0 * s)
        y = zf * (1.0 - alpha) + zc * alpha
    out_pos[k] = wp.vec3(rel[0] + x * dx, y - rel[1], rel[2] + z * dz)
    out_uv[k] = _uv(h, cx, cz)
    out_level[k] = lv_level[li]
    out_item[k] = li


@wp.func
def _block_quads(li: int, bx: int, by: int, block: int, n: int, hole: wp.array(dtype=wp.vec4i),
                 lv_origin: wp.array(dtype=wp.vec2), lv_spacing: wp.array(dtype=wp.float32), cols: int, rows: int,
                 q: int) -> int:
    """Quad q of block (bx, by) of level li: its index a + b * (n - 1) in the level, or -1 when it is not drawn
    (past the block, in the finer level's hole, or wholly outside the grid)."""
    a = bx * block + q % block
    b = by * block + q / block
    if a >= n - 1 or b >= n - 1 or q >= block * block:
        return -1
    hr = hole[li]
    if a >= hr[0] and a < hr[1] and b >= hr[2] and b < hr[3]:
        return -1
    s = lv_spacing[li]
    x0 = lv_origin[li][0] + float(a) * s
    z0 = lv_origin[li][1] + float(b) * s
    if x0 >= float(cols - 1) or z0 >= float(rows - 1) or x0 + s <= 0.0 or z0 + s <= 0.0:
        return -1
    return a + b * (n - 1)


@wp.kernel(enable_backward=False)
def _clipmap_count_kernel(
    offset: int,
    pos: wp.array(dtype=wp.vec3),
    hole: wp.array(dtype=wp.vec4i),
    lv_origin: wp.array(dtype=wp.vec2),
    lv_spacing: wp.array(dtype=wp.float32),
    planes: wp.array(dtype=wp.vec4),
    n: int,
    block: int,
    blocks: int,
    cols: int,
    rows: int,
    # outputs
    out_count: wp.array(dtype=wp.int32),
):
    k = wp.tid() + offset  # block k: level, then block row, then block column
    li = k / (blocks * blocks)
    r = k - li * blocks * blocks
    bx = r % blocks
    by = r / blocks
    # the block's box: its vertices' bounds (GPU Gems 2 ch. 2 culls per block)
    lo = wp.vec3(3.0e38, 3.0e38, 3.0e38)
    hi = wp.vec3(-3.0e38, -3.0e38, -3.0e38)
    for j in range(block + 1):
        for i in range(block + 1):
            a = wp.min(bx * block + i, n - 1)
            b = wp.min(by * block + j, n - 1)
            p = pos[li * n * n + b * n + a]
            lo = wp.min(lo, p)
            hi = wp.max(hi, p)
    cnt = int(0)
    if box_outside(planes, lo, hi) == 0:
        for q in range(block * block):
            if _block_quads(li, bx, by, block, n, hole, lv_origin, lv_spacing, cols, rows, q) >= 0:
                cnt += 2
    out_count[k] = cnt


@wp.kernel(enable_backward=False)
def _clipmap_emit_kernel(
    offset: int,
    count: wp.array(dtype=wp.int32),
    start: wp.array(dtype=wp.int32),
    hole: wp.array(dtype=wp.vec4i),
    lv_origin: wp.array(dtype=wp.vec2),
    lv_spacing: wp.array(dtype=wp.float32),
    n: int,
    block: int,
    blocks: int,
    cols: int,
    rows: int,
    # outputs
    out_tri: wp.array2d(dtype=wp.int32),
):
    k = wp.tid() + offset
    if count[k] == 0:
        return
    li = k / (blocks * blocks)
    r = k - li * blocks * blocks
    bx = r % blocks
    by = r / blocks
    t = start[k]
    for q in range(block * block):
        idx = _block_quads(li, bx, by, block, n, hole, lv_origin, lv_spacing, cols, rows, q)
        if idx >= 0:
            v00 = li * n * n + (idx / (n - 1)) * n + idx % (n - 1)
            write_quad(out_tri, t, v00, v00 + 1, v00 + n, v00 + n + 1)
            t += 2


@wp.kernel(enable_backward=False)
def _clipmap_stitch_kernel(
    offset: int,
    n: int,
    first: int,
    # outputs
    out_tri: wp.array2d(dtype=wp.int32),
):
    k = wp.tid() + offset  # stitch k: level, side, segment
    half = (n - 1) / 2
    li = k / (4 * half)
    r = k - li * 4 * half
    side = r / half
    seg = r - side * half
    t = 2 * seg  # the even lattice vertices t and t + 2 of the side, the odd one between
    v0 = int(0)
    v1 = int(0)
    v2 = int(0)
    if side == 0:  # b = 0
        v0 = t
        v1 = t + 1
        v2 = t + 2
    elif side == 1:  # a = n - 1
        v0 = t * n + n - 1
        v1 = (t + 1) * n + n - 1
        v2 = (t + 2) * n + n - 1
    elif side == 2:  # b = n - 1
        v0 = (n - 1) * n + t
        v1 = v0 + 1
        v2 = v0 + 2
    else:  # a = 0
        v0 = t * n
        v1 = (t + 1) * n
        v2 = (t + 2) * n
    base = li * n * n
    out_tri[first + k, 0] = base + v0
    out_tri[first + k, 1] = base + v1
    out_tri[first + k, 2] = base + v2


# ------------------------------------------------------------------------------------------------
# kernels: CDLOD's and chunked LOD's selections, the whole quadtree walked in one launch
# ------------------------------------------------------------------------------------------------
@wp.func
def _cdlod_item(out_item: wp.array2d(dtype=wp.float32), out_int: wp.array2d(dtype=wp.int32), i: int,
                ox: wp.float64, oy: wp.float64, size: wp.float64, step: wp.float64, lod: int):
    out_item[i, 0] = wp.float32(ox)
    out_item[i, 1] = wp.float32(oy)
    out_item[i, 2] = wp.float32(size)
    out_item[i, 3] = wp.float32(step)
    out_int[i, 0] = lod


@wp.func
def _farther_than(x: int, y: int, size: wp.vec2d, rel: wp.vec3d, mn: float, mx: float, limit: wp.float64) -> int:
    """1 when the farthest point of node (x, y)'s box (float64, from the eye) lies past ``limit``."""
    x0 = rel[0] + wp.float64(x) * size[0]
    z0 = rel[2] + wp.float64(y) * size[1]
    fx = wp.max(wp.abs(x0), wp.abs(x0 + size[0]))
    fz = wp.max(wp.abs(z0), wp.abs(z0 + size[1]))
    fy = wp.max(wp.abs(wp.float64(mn) - rel[1]), wp.abs(wp.float64(mx) - rel[1]))
    if wp.sqrt(fx * fx + fy * fy + fz * fz) > limit:
        return 1
    return 0


@wp.func
def _chunk_neighbours(qt: QuadTree, leaf_map: wp.array(dtype=wp.int32), leaf: wp.array2d(dtype=wp.int32), j: int,
                      out_nbr: wp.array2d(dtype=wp.int32), out_err: wp.array2d(dtype=wp.float32)):
    """Leaf ``j``'s neighbours across its west, north, east and south edges (the level of the leaf holding the
    finest cell just outside each edge's first one, -1 beyond the grid) and the geometric errors of the chunk-sized
    nodes there (0 for none), then its own error."""
    lv = leaf[j, 0]
    shift = qt.depth - lv
    fx0 = leaf[j, 1] << shift
    fy0 = leaf[j, 2] << shift
    size = 1 << shift
    out_err[j, 4] = qt.herr[node_index(qt, lv, leaf[j, 1], leaf[j, 2])]
    for e in range(4):  # the finest cell just outside the edge's first one: west, north, east, south
        fx = fx0
        fy = fy0
        if e == 0:
            fx = fx0 - 1
        elif e == 1:
            fy = fy0 - 1
        elif e == 2:
            fx = fx0 + size
        else:
            fy = fy0 + size
        found = int(-1)
        if fx >= 0 and fy >= 0 and fx < (qt.roots[0] << qt.depth) and fy < (qt.roots[1] << qt.depth):
            for k in range(qt.depth + 1):  # the leaf holding it: the one level where its ancestor is a leaf
                if found < 0:
                    if leaf_map[node_index(qt, k, fx >> (qt.depth - k), fy >> (qt.depth - k))] != 0:
                        found = k
        out_nbr[j, e] = found
        err = float(0.0)
        if found >= 0:  # a finer neighbour: the chunk-sized node holding it
            at = wp.min(found, lv)
            err = qt.herr[node_index(qt, at, fx >> (qt.depth - at), fy >> (qt.depth - at))]
        out_err[j, e] = err


@wp.kernel(enable_backward=False)
def _chunk_select_kernel(
    qt: QuadTree,
    eye: wp.array(dtype=wp.vec3),
    planes: wp.array(dtype=wp.vec4),
    view: wp.array(dtype=wp.float32),
    front: wp.array3d(dtype=wp.int32),
    code: wp.array(dtype=wp.int32),
    leaf_map: wp.array(dtype=wp.int32),
    out_leaf: wp.array2d(dtype=wp.int32),
    out_nbr: wp.array2d(dtype=wp.int32),
    out_err: wp.array2d(dtype=wp.float32),
    # outputs
    out_chunk: wp.array2d(dtype=wp.int32),
    out_chunk_err: wp.array2d(dtype=wp.float32),
    out_n: wp.array(dtype=wp.int64),
):
    """One thread walks the tree level by level, splitting while a node's screen-space error exceeds
    ``view[0]`` pixels (``view[1]``: focal length in pixels), then finds each leaf's neighbours through a map of
    the leaves over every node of the tree (``leaf_map``, all 0, left all 0); see :meth:`ChunkTree.select`."""
    rel = eye[0]
    max_sse = view[0]
    focal = view[1]
    n = walk_roots(front, qt.roots)
    p = int(0)
    q = int(0)
    visited = int(0)
    for lvl in range(qt.depth + 1):
        n = keep_inside(front, p, n, qt.inside[lvl])
        if n == 0:
            break
        visited += n
        base = qt.level_start[lvl]
        width = qt.roots[0] << lvl
        for i in range(n):  # 0 a leaf in view, 1 a culled leaf, 2 split
            x = front[p, i, 0]
            y = front[p, i, 1]
            k = base + y * width + x
            lo, hi = node_box(rel, qt.size32[lvl], x, y, qt.hmin[k], qt.hmax[k])
            kind = int(0)
            if box_outside(planes, lo, hi) != 0:
                kind = 1
            elif lvl < qt.depth and screen_error(qt.herr[k], box_distance(lo, hi), focal) > max_sse:
                kind = 2
            code[i] = kind
            if kind != 2:
                out_leaf[q, 0] = lvl
                out_leaf[q, 1] = x
                out_leaf[q, 2] = y
                out_leaf[q, 3] = kind
                q += 1
        n = push_children(front, p, n, code, 2)
        p = 1 - p
    for j in range(q):  # every leaf, culled or not, marked on the map
        lv = out_leaf[j, 0]
        leaf_map[node_index(qt, lv, out_leaf[j, 1], out_leaf[j, 2])] = j + 1
    for j in range(q):
        _chunk_neighbours(qt, leaf_map, out_leaf, j, out_nbr, out_err)
    d = int(0)
    cells = qt.level_start[qt.depth] + (qt.roots[0] * qt.roots[1] << (2 * qt.depth))
    for cell in range(cells):  # the drawn chunks in key order: the map level by level, row-major
        v = leaf_map[cell]
        if v > 0:
            j = v - 1
            if out_leaf[j, 3] == 0:
                for k in range(3):
                    out_chunk[d, k] = out_leaf[j, k]
                for k in range(4):
                    out_chunk[d, 3 + k] = out_nbr[j, k]
                    out_chunk_err[d, k] = out_err[j, k]
                out_chunk_err[d, 4] = out_err[j, 4]
                d += 1
            leaf_map[cell] = 0
    out_n[0] = wp.int64(q)
    out_n[1] = wp.int64(visited)
    out_n[2] = wp.int64(d)


@wp.func
def _cdlod_codes(qt: QuadTree, lvl: int, front: wp.array3d(dtype=wp.int32), p: int, n: int, rel: wp.vec3,
                 planes: wp.array(dtype=wp.vec4), r_in: wp.float64, r_split: wp.float64,
                 code: wp.array(dtype=wp.int32)) -> wp.vec2i:
    """The level's nodes (frontier ``p``) classified into ``code``: 0 culled, 1 drawn as the parent's quadrant
    (beyond the level's range), 2 drawn whole, 3 split (within the finer level's range). Returns (nodes drawn
    whole, nodes culled)."""
    base = qt.level_start[lvl]
    width = qt.roots[0] << lvl
    n_whole = int(0)
    culled = int(0)
    for i in range(n):
        x = front[p, i, 0]
        y = front[p, i, 1]
        k = base + y * width + x
        lo, hi = node_box(rel, qt.size32[lvl], x, y, qt.hmin[k], qt.hmax[k])
        dist = wp.float64(box_distance(lo, hi))
        kind = int(0)
        if box_outside(planes, lo, hi) != 0:
            culled += 1
        elif not (dist < r_in):
            kind = 1
        elif dist < r_split:
            kind = 3
        else:
            kind = 2
            n_whole += 1
        code[i] = kind
    return wp.vec2i(n_whole, culled)


@wp.kernel(enable_backward=False)
def _cdlod_select_kernel(
    qt: QuadTree,
    size64: wp.array(dtype=wp.vec2d),
    eye: wp.array(dtype=wp.vec3),
    eye64: wp.array(dtype=wp.vec3d),
    planes: wp.array(dtype=wp.vec4),
    ranges: wp.array2d(dtype=wp.float64),
    levels: int,
    root_cells: wp.float64,
    grid: int,
    front: wp.array3d(dtype=wp.int32),
    code: wp.array(dtype=wp.int32),
    # outputs
    out_item: wp.array2d(dtype=wp.float32),
    out_int: wp.array2d(dtype=wp.int32),
    out_n: wp.array(dtype=wp.int64),
):
    """One thread walks the tree level by level (see :meth:`CdlodTree.select`)."""
    rel = eye[0]
    rel64 = eye64[0]
    n = walk_roots(front, qt.roots)
    p = int(0)
    q = int(0)  # quadrants emitted
    o = int(0)  # entries of the draw order
    d = int(0)  # draws
    visited = int(0)
    culled = int(0)
    too_small = int(0)
    wholes = int(0)
    singles = int(0)
    for lvl in range(qt.depth + 1):
        lod = qt.depth - lvl
        n = keep_inside(front, p, n, qt.inside[lvl])
        if n == 0:
            break
        visited += n
        base = qt.level_start[lvl]
        width = qt.roots[0] << lvl
        r_in = ranges[lod, 0]
        r_split = wp.float64(-1.0)
        if lod > 0:
            r_split = ranges[lod - 1, 0]
        counts = _cdlod_codes(qt, lvl, front, p, n, rel, planes, r_in, r_split, code)
        n_whole = counts[0]
        culled += counts[1]
        s = root_cells / wp.float64(1 << lvl)
        if lvl > 0:  # a parent draws these quadrants with its grid: lod + 1
            st = root_cells / wp.float64(1 << (lvl - 1)) / wp.float64(grid)
            for i in range(n):
                if code[i] == 1:
                    _cdlod_item(out_item, out_int, q, wp.float64(front[p, i, 0]) * s, wp.float64(front[p, i, 1]) * s,
                                s, st, lod + 1)
                    out_int[o, 1] = q
                    out_int[d, 2] = o
                    out_int[d, 3] = o + 1
                    q += 1
                    o += 1
                    d += 1
                    singles += 1
        half = s / wp.float64(2.0)
        st = s / wp.float64(grid)
        j = int(0)
        for i in range(n):
            if code[i] == 2:  # four quadrants: quadrant c of the level's j-th whole node at q + c n_whole + j
                x = front[p, i, 0]
                y = front[p, i, 1]
                for c in range(4):
                    e = q + c * n_whole + j
                    _cdlod_item(out_item, out_int, e, wp.float64(x) * s + wp.float64(c % 2) * half,
                                wp.float64(y) * s + wp.float64(c / 2) * half, half, st, lod)
                    out_int[o + c, 1] = e
                out_int[d, 2] = o
                out_int[d, 3] = o + 4
                o += 4
                d += 1
                j += 1
                if lod + 1 < levels:
                    k = base + y * width + x
                    too_small += _farther_than(x, y, size64[lvl], rel64, qt.hmin[k], qt.hmax[k], ranges[lod + 1, 1])
        q += 4 * n_whole
        wholes += n_whole
        n = push_children(front, p, n, code, 3)
        p = 1 - p
    out_n[0] = wp.int64(q)
    out_n[1] = wp.int64(d)
    out_n[2] = wp.int64(visited)
    out_n[3] = wp.int64(culled)
    out_n[4] = wp.int64(too_small)
    out_n[5] = wp.int64(wholes)
    out_n[6] = wp.int64(singles)


# ------------------------------------------------------------------------------------------------
# host wrappers
# ------------------------------------------------------------------------------------------------
MeshArrays = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def _heights(heights: np.ndarray | wp.array, device: str) -> wp.array:
    if isinstance(heights, wp.array):
        return heights
    return view(heights, wp.float32, device)  # the heightmap: not copied per frame on the CPU


def _vertex_outputs(nv: int, device: str) -> list[wp.array]:
    return [empty(max(nv, 1), wp.vec3, device), empty(max(nv, 1), wp.vec2, device),
            empty(max(nv, 1), wp.int32, device), empty(max(nv, 1), wp.int32, device)]


def _to_numpy(verts: list[wp.array], nv: int, tri: wp.array, nt: int) -> MeshArrays:
    pos, uv, lev, item = (a.numpy()[:nv] for a in verts)
    return (pos.reshape(-1, 3), uv.reshape(-1, 2), lev, item, tri.numpy()[:nt].reshape(-1, 3))


def cdlod_mesh(heights: np.ndarray | wp.array, origin: np.ndarray, step: np.ndarray, lod: np.ndarray, n: int,
               morph_start: np.ndarray, morph_inv: np.ndarray, rel_origin: tuple[float, float, float], dx: float,
               dz: float, device: str = "cpu") -> MeshArrays:
    """The CDLOD vertex stage over every selected quadrant (each an ``(n+1)^2`` grid), one launch, and its
    triangles (another).

    Args:
        heights: (H, W) float32 (or a Warp array of it).
        origin: (Q, 2) float32 quadrant corner in cells; step: (Q,) float32 vertex spacing in cells (a power of
            two); lod: (Q,) int32 CDLOD level (0 finest).
        n: quads per quadrant side (half the node's grid resolution).
        morph_start: (levels,) float32 eye distance (m) where each level's morph begins; morph_inv: (levels,)
            float32 ``1 / (morph_end - morph_start)`` (0: never morphs).
        rel_origin: :func:`terrainwarp.camera.relative_origin` of the heightmap.

    Returns:
        positions (Q (n+1)^2, 3) float32 camera-relative, uv (., 2) float32, level (.,) int32, quadrant index
        (.,) int32, triangles (2 Q n^2, 3) int32.
    """
    q = len(step)
    nv, nt = q * (n + 1) ** 2, 2 * q * n * n
    h = _heights(heights, device)
    verts = _vertex_outputs(nv, device)
    tri = empty((max(nt, 1), 3), wp.int32, device)
    if q:
        launch(_cdlod_vertices_kernel, dim=nv, inputs=[
            h, wp.array(np.ascontiguousarray(origin, np.float32), dtype=wp.vec2, device=device),
            wp.array(np.ascontiguousarray(step, np.float32), dtype=wp.float32, device=device),
            wp.array(np.ascontiguousarray(lod, np.int32), dtype=wp.int32, device=device), int(n),
            wp.array(np.ascontiguousarray(morph_start, np.float32), dtype=wp.float32, device=device),
            wp.array(np.ascontiguousarray(morph_inv, np.float32), dtype=wp.float32, device=device),
            wp.vec3(*rel_origin), float(dx), float(dz)], outputs=verts, device=device)
        launch(_item_triangles_kernel, dim=nt // 2, inputs=[int(n), (n + 1) ** 2], outputs=[tri], device=device)
    return _to_numpy(verts, nv, tri, nt)


def chunk_mesh(heights: np.ndarray | wp.array, origin: np.ndarray, step: np.ndarray, level: np.ndarray,
               skirt_m: np.ndarray, skirt_mask: np.ndarray, n: int, rel_origin: tuple[float, float, float],
               dx: float, dz: float, device: str = "cpu") -> MeshArrays:
    """Chunks (each an ``(n+1)^2`` grid) with vertical skirts hanging ``skirt_m`` metres below the edges set in
    ``skirt_mask`` (bit e: edge e, OpenGL order u=0, v=0, u=1, v=1).

    Args:
        origin: (C, 2) float32 chunk corner in cells; step: (C,) float32 vertex spacing in cells; level: (C,)
            int32; skirt_m: (C,) float32 skirt depth (m); skirt_mask: (C,) int32.

    Returns:
        positions (C ((n+1)^2 + 4 (n+1)), 3) float32 camera-relative (each chunk's grid, then its four edges'
        skirt-bottom vertices, used or not), uv, level, chunk index, triangles (sum over chunks of
        ``2 n^2 + 2 n * popcount(mask)``, 3) int32: each chunk's grid, then its skirts.
    """
    c = len(step)
    stride = (n + 1) ** 2 + 4 * (n + 1)
    per = 2 * n * n + 2 * n * np.array([bin(int(m)).count("1") for m in np.asarray(skirt_mask)], np.int64)
    start = np.concatenate([[0], np.cumsum(per)[:-1]]).astype(np.int32) if c else np.zeros(0, np.int32)
    nv, nt = c * stride, int(per.sum())
    h = _heights(heights, device)
    verts = _vertex_outputs(nv, device)
    tri = empty((max(nt, 1), 3), wp.int32, device)
    if c:
        launch(_chunk_vertices_kernel, dim=nv, inputs=[
            h, wp.array(np.ascontiguousarray(origin, np.float32), dtype=wp.vec2, device=device),
            wp.array(np.ascontiguousarray(step, np.float32), dtype=wp.float32, device=device),
            wp.array(np.ascontiguousarray(level, np.int32), dtype=wp.int32, device=device),
            wp.array(np.ascontiguousarray(skirt_m, np.float32), dtype=wp.float32, device=device), int(n),
            wp.vec3(*rel_origin), float(dx), float(dz)], outputs=verts, device=device)
        launch(_chunk_triangles_kernel, dim=(c, 2 * n * n + 8 * n), inputs=[
            int(n), wp.array(np.ascontiguousarray(skirt_mask, np.int32), dtype=wp.int32, device=device),
            wp.array(start, dtype=wp.int32, device=device)], outputs=[tri], device=device, min_items=1024)
    return _to_numpy(verts, nv, tri, nt)


def clipmap_mesh(heights: np.ndarray | wp.array, origin: np.ndarray, spacing: np.ndarray, coarser: np.ndarray,
                 level: np.ndarray, hole: np.ndarray, n: int, viewer: tuple[float, float], alpha_offset: float,
                 width: float, planes: np.ndarray, rel_origin: tuple[float, float, float], dx: float, dz: float,
                 block: int, device: str = "cpu") -> MeshArrays:
    """The clipmap levels' vertices (each an n x n lattice, transition-blended toward the next coarser level),
    their drawn quads (count per block with frustum culling -> scan -> emit), and zero-area stitch triangles
    along the outer border of every level that has a coarser one.

    Args:
        origin: (L, 2) float32 each level's lattice corner in cells; spacing: (L,) float32 cells (2^level);
            coarser: (L,) int32 1 when a coarser level is drawn around it; level: (L,) int32 clipmap level;
            hole: (L, 4) int32 ``[a0, a1) x [b0, b1)`` quads covered by the finer level (empty: a0 = a1 = 0).
        n: lattice vertices per side (odd); viewer: the viewer's (x, z) in cells; alpha_offset, width: the
            transition (GPU Gems 2 ch. 2: ``(n - 1) / 2 - w - 1`` and ``w``, level grid units).
        planes: (6, 4) float32 camera-relative frustum planes; block: quads per culling block side.

    Returns:
        positions (L n^2, 3) float32 camera-relative, uv, level, level index, triangles (m, 3) int32, and the draws
        a GPU issues for them: (D, 2) int32 triangle ranges, one per block with a quad drawn and one per level's
        stitches, level by level (a level's blocks, then its stitches), and (L, 2) int32 the draw range of each
        level (draws of a level share its lattice vertices; levels share none).
    """
    nl = len(spacing)
    hh, ww = np.shape(heights)
    nv = nl * n * n
    blocks = -(-(n - 1) // block)
    nb = nl * blocks * blocks
    n_stitch = int(np.asarray(coarser).sum()) * 2 * (n - 1)
    h = _heights(heights, device)
    verts = _vertex_outputs(nv, device)
    lv = [wp.array(np.ascontiguousarray(origin, np.float32), dtype=wp.vec2, device=device),
          wp.array(np.ascontiguousarray(spacing, np.float32), dtype=wp.float32, device=device)]
    launch(_clipmap_vertices_kernel, dim=nv, inputs=[
        h, *lv, wp.array(np.ascontiguousarray(coarser, np.int32), dtype=wp.int32, device=device),
        wp.array(np.ascontiguousarray(level, np.int32), dtype=wp.int32, device=device), int(n),
        wp.vec2(*viewer), float(alpha_offset), float(width), wp.vec3(*rel_origin), float(dx), float(dz)],
        outputs=verts, device=device)
    holes = wp.array(np.ascontiguousarray(hole, np.int32), dtype=wp.vec4i, device=device)
    grid = [int(n), int(block), int(blocks), int(ww), int(hh)]
    cnt = wp.empty(nb, dtype=wp.int32, device=device)
    launch(_clipmap_count_kernel, dim=nb, inputs=[
        verts[0], holes, *lv, wp.array(np.ascontiguousarray(planes, np.float32), dtype=wp.vec4, device=device),
        *grid], outputs=[cnt], device=device, min_items=1)
    start = wp.empty_like(cnt)
    scan(cnt, start, inclusive=False)
    n_quad_tri = int(start.numpy()[-1] + cnt.numpy()[-1])
    # stitches of the levels with a coarser one: they come first among the levels (finest first)
    nt = n_quad_tri + n_stitch
    tri = empty((max(nt, 1), 3), wp.int32, device)
    launch(_clipmap_emit_kernel, dim=nb, inputs=[cnt, start, holes, *lv, *grid], outputs=[tri], device=device,
           min_items=1)
    if n_stitch:
        launch(_clipmap_stitch_kernel, dim=n_stitch, inputs=[int(n), n_quad_tri], outputs=[tri], device=device)
    return (*_to_numpy(verts, nv, tri, nt), *_clipmap_draws(cnt.numpy(), start.numpy(), np.asarray(coarser), n,
                                                           n_quad_tri))


def _clipmap_draws(cnt: np.ndarray, start: np.ndarray, coarser: np.ndarray, n: int,
                   first_stitch: int) -> tuple[np.ndarray, np.ndarray]:
    """(draws (D, 2), groups (L, 2)) of :func:`clipmap_mesh`: per level its drawn blocks, then its stitches (the
    stitch triangles of the levels with a coarser one follow the quads, 2 (n - 1) each, finest first)."""
    nl = len(coarser)
    per_level = cnt.reshape(nl, -1) if nl else cnt.reshape(0, 1)
    first = start.reshape(nl, -1) if nl else start.reshape(0, 1)
    draws, groups = [], []
    stitch = first_stitch
    for li in range(nl):
        g0 = len(draws)
        drawn = np.flatnonzero(per_level[li])
        draws += [(int(first[li, b]), int(first[li, b] + per_level[li, b])) for b in drawn]
        if coarser[li]:
            draws.append((stitch, stitch + 2 * (n - 1)))
            stitch += 2 * (n - 1)
        groups.append((g0, len(draws)))
    return np.asarray(draws, np.int32).reshape(-1, 2), np.asarray(groups, np.int32).reshape(-1, 2)


class CdlodTree(TreeWalk):
    """CDLOD's selection (Strugar 2010) over one quadtree, in one launch (see :class:`TreeWalk`)."""

    def __init__(self, stats: list, inside: np.ndarray, roots: tuple[int, int], root_cells: float,
                 sizes: list[tuple[float, float]], grid: int, device: str = "cpu") -> None:
        """As :class:`TreeWalk`; ``root_cells``: a root node's side in cells; ``grid``: quads per node side."""
        super().__init__(stats, inside, roots, sizes, device)
        self.grid = int(grid)
        cap = self.capacity
        inputs = [empty(1, wp.vec3, device), empty(1, wp.vec3d, device), empty(6, wp.vec4, device),
                  empty((self.levels, 2), wp.float64, device)]
        self._args = [wp.array(np.asarray(sizes, np.float64), dtype=wp.vec2d, device=device), *inputs, self.levels,
                      float(root_cells), self.grid, *self._frontier(max(cap, int(roots[0]) * int(roots[1])))]
        self._record(_cdlod_select_kernel, inputs,
                     [empty((cap, 4), wp.float32, device), empty((cap, 4), wp.int32, device),
                      empty(8, wp.int64, device)])

    def select(self, rel_origin: tuple[float, float, float], planes: np.ndarray, ranges: np.ndarray,
               morph_start: np.ndarray) -> tuple[np.ndarray, ...]:
        """The selection for one camera.

        Per level, the nodes whose origin lies inside the grid are tested: culled when their box is outside the
        frustum; drawn as their parent's quadrant (with the parent's grid, lod + 1) when the box lies beyond
        ``ranges[lod]``; split when it lies within ``ranges[lod - 1]``; else drawn whole, as its four quadrants,
        and counted ``too_small`` when its farthest point lies past ``morph_start[lod + 1]``. The children of
        split nodes are the next level's nodes, quadrant by quadrant ((0, 0), (1, 0), (0, 1), (1, 1) blocks).

        Args:
            rel_origin: :func:`terrainwarp.camera.relative_origin` of the heightmap (float32 for the boxes,
                float64 for the ``too_small`` check).
            planes: (6, 4) float32 frustum planes (:func:`.lod.frustum_planes`).
            ranges: (levels,) float64 range of each LOD (0 finest; the coarsest infinite); morph_start:
                (levels,) float64.

        Returns:
            origin (Q, 2) float32 quadrant corner in cells, size (Q,) float32, step (Q,) float32 vertex spacing,
            lod (Q,) int32, draws (D, 2) int32 ranges of ``order`` (a whole node's four quadrants, or one parent
            quadrant), order (Q,) int32, and counts (7,) int64: quadrants, draws, nodes visited, culled,
            too_small, whole nodes, parent quadrants. Quadrants come level by level: parent quadrants, then the
            whole nodes' quadrants (quadrant by quadrant); ``order`` takes them node by node.
        """
        with self._lock:
            f, i, n = self._run([rel_origin, rel_origin, planes, np.stack([ranges, morph_start], 1)])
            n = n.copy()
            q, d = int(n[0]), int(n[1])
            return f[:q, :2].copy(), f[:q, 2].copy(), f[:q, 3].copy(), i[:q, 0].copy(), i[:d, 2:4].copy(), \
                i[:q, 1].copy(), n[:7]


class ChunkTree(TreeWalk):
    """Chunked LOD's selection (Ulrich 2002) over one quadtree, in one launch (see :class:`TreeWalk`)."""

    def __init__(self, stats: list, inside: np.ndarray, roots: tuple[int, int], sizes: list[tuple[float, float]],
                 device: str = "cpu") -> None:
        super().__init__(stats, inside, roots, sizes, device)
        inputs = [empty(1, wp.vec3, device), empty(6, wp.vec4, device), empty(2, wp.float32, device)]
        nodes = sum(a[0].size for a in stats)
        cap = self.capacity
        self._args = [*inputs, *self._frontier(max(cap, int(roots[0]) * int(roots[1]))),
                      wp.zeros(nodes, dtype=wp.int32, device=device)]
        self._args += [wp.empty((cap, 4), dtype=wp.int32, device=device),
                       wp.empty((cap, 4), dtype=wp.int32, device=device),
                       wp.empty((cap, 5), dtype=wp.float32, device=device)]
        self._record(_chunk_select_kernel, inputs, [empty((cap, 7), wp.int32, device),
                                                    empty((cap, 5), wp.float32, device), empty(3, wp.int64, device)])

    def select(self, rel_origin: tuple[float, float, float], planes: np.ndarray, max_sse_px: float,
               focal_px: float) -> tuple[np.ndarray, ...]:
        """The leaves for one camera: per level, the nodes whose origin lies inside the grid are tested; a node
        whose box is outside the frustum is a culled leaf; one whose screen-space error (its geometric error
        times ``focal_px`` over its box's distance, float32) exceeds ``max_sse_px`` is split, below the deepest
        level; the others are leaves. Children come quadrant by quadrant, as in :class:`CdlodTree`.

        The drawn chunks (the leaves not culled) come in key order (level, then row, then column) with their
        neighbours: per edge (west, north, east, south: u = 0, v = 0, u = 1, v = 1), the level of the leaf (culled
        or not) holding the finest cell just outside the edge's first one (a leaf at the chunk's level or coarser
        covers the whole edge), -1 beyond the root grid; and its geometric error, or that of the chunk-sized node
        holding it when it is finer (0 where none).

        Returns:
            level, x, y (C,) int64 of the drawn chunks; their neighbour levels (C, 4) int32 and errors (C, 4)
            float32; their own geometric errors (C,) float32; leaves, nodes visited.
        """
        with self._lock:
            chunk, err, n = self._run([rel_origin, planes, (max_sse_px, focal_px)])
            d = int(n[2])
            return (chunk[:d, 0].astype(np.int64), chunk[:d, 1].astype(np.int64), chunk[:d, 2].astype(np.int64),
                    chunk[:d, 3:7].copy(), err[:d, :4].copy(), err[:d, 4].copy(), int(n[0]), int(n[1]))

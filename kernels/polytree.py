"""Bottom-up polygon merging of taylor-barrett-continuous-resolution.txt as Warp kernels.

The heightmap's (H-1) x (W-1) cells are the unit polygons; a rectangle is ``(i0, i1, j0, j1)`` in cell
coordinates (half-open), so its corners are the samples ``(i0, j0)`` .. ``(i1, j1)``. The paper's
corners z1..z4 are ``h[i0, j0]``, ``h[i0, j1]``, ``h[i1, j1]``, ``h[i1, j0]`` and its unnormalised
gradients (equations 1-2) are ``Xgr = (z2 - z1) + (z3 - z4)`` and ``Ygr = (z4 - z1) + (z3 - z2)``.

Quadtree: the cells are padded to N x N, N = 2^depth; a node of level ``l`` covers 2^l x 2^l cells and
nodes of a level are numbered in Morton order (bit 2b of the code is bit b of the column, bit 2b+1 of the
row), so the four sons of node k are 4k .. 4k+3 in the order son 1 (low row, low column), son 2 (low row,
high column), son 4 (high row, low column), son 3 (high row, high column) of the paper's figure 6, and
the polygon lists of the sons of a node lie next to each other in the level's record array.

One pass (one tolerance) runs the levels bottom-up, three launches each, all nodes of a level in
parallel and each node sequential (deterministic):

1. ``_leaf_count_kernel`` / ``_merge_kernel``: a node copies its sons' records into scratch and merges
   along border A (son 1 | son 2), then B (son 4 | son 3), then C (top half | bottom half), walking each
   border with the neighbour search of section 2.1: descend the quadtree to the topmost node that holds
   a single polygon and contains the point, then follow the polytree's father pointers up to the sons'
   level and the merge forwarding pointers inside the node: O(depth). A pair passes the bounds check
   when its extents along the border are equal (the union is a rectangle) and the homogeneity check
   when ``|dXgr| + |dYgr| <= tolerance`` (the paper says "less than"; ``<=`` lets tolerance 0 merge
   exactly coplanar cells). A failed pair sets a flag bit on both polygons (FLAG_* below).
2. ``wp.utils.array_scan`` of the per-node counts.
3. ``_emit_kernel``: the surviving polygons become the level's records; every son record gets its father
   pointer (the polygon of this level it merged into); ``single_rec`` marks nodes holding one polygon.

Nodes that held a single polygon after an earlier (lower) tolerance keep it without merging, and their
descendants are not launched at all (step j of the paper: single is hereditary and monotone in the
tolerance); the launches are recorded once per quadtree and replayed with the new tolerance and work-list
length, so a late tolerance costs what is left to merge.

Section 2.4 (``_tri_count_kernel`` / ``_tri_emit_kernel``) and section 2.5 (``_morph_target_kernel``,
``_morph_positions_kernel``) follow; the host side is :mod:`terrainwarp.lod.polytree`.
"""

from __future__ import annotations

import numpy as np
import warp as wp

FLAG_LOW_J = 1  # a merge across (part of) the polygon's j0 side was tried and failed
FLAG_HIGH_J = 2  # ... across its j1 side
FLAG_LOW_I = 4  # ... across its i0 side
FLAG_HIGH_I = 8  # ... across its i1 side

# stats counters of a pass
STAT_TESTS, STAT_BOUNDS_FAIL, STAT_SIMILARITY_FAIL, STAT_MERGES, STAT_FIND_STEPS, STAT_FIND_MAX = range(6)
# (two neighbour searches per pair test: mean steps per search = STAT_FIND_STEPS / (2 * STAT_TESTS))

# ------------------------------------------------------------------------------------------------
# functions
# ------------------------------------------------------------------------------------------------


@wp.func
def _morton(i: int, j: int, depth: int) -> int:
    code = int(0)
    for b in range(depth):
        code = code | (((j >> b) & 1) << (2 * b)) | (((i >> b) & 1) << (2 * b + 1))
    return code


@wp.func
def _demorton(code: int, depth: int) -> wp.vec2i:
    i = int(0)
    j = int(0)
    for b in range(depth):
        j = j | (((code >> (2 * b)) & 1) << b)
        i = i | (((code >> (2 * b + 1)) & 1) << b)
    return wp.vec2i(i, j)


@wp.func
def _grads(h: wp.array2d(dtype=wp.float32), r: wp.vec4i) -> wp.vec2:
    z1 = h[r[0], r[2]]
    z2 = h[r[0], r[3]]
    z3 = h[r[1], r[3]]
    z4 = h[r[1], r[2]]
    return wp.vec2((z2 - z1) + (z3 - z4), (z4 - z1) + (z3 - z2))


@wp.func
def _node_rect(k: int, level: int, depth: int, ch: int, cw: int) -> wp.vec4i:
    o = _demorton(k, depth - level)
    s = 1 << level
    i0 = o[0] * s
    j0 = o[1] * s
    return wp.vec4i(i0, wp.min(i0 + s, ch), j0, wp.min(j0 + s, cw))


@wp.func
def _find(r: int, c: int, m: int, depth: int, single_rec: wp.array(dtype=wp.int32),
          node_base: wp.array(dtype=wp.int32), rec_father: wp.array(dtype=wp.int32),
          level_base: wp.array(dtype=wp.int32), sc_fwd: wp.array(dtype=wp.int32)) -> wp.vec2i:
    """(scratch index (level m-1 numbering) of the live polygon of the node being merged at level m that
    contains cell (r, c), pointer steps taken): section 2.1's descent to the topmost node holding a single
    polygon, then father pointers up to the sons' level and merge pointers inside the node, O(depth)."""
    code = _morton(r, c, depth)
    lv = m - 1
    rec = int(-1)
    steps = int(0)
    while lv >= 0:
        rec = single_rec[node_base[lv] + (code >> (2 * lv))]
        steps = steps + 1
        if rec >= 0:
            break
        lv = lv - 1
    while lv < m - 1:
        rec = rec_father[rec]
        lv = lv + 1
        steps = steps + 1
    s = rec - level_base[m - 1]
    while sc_fwd[s] >= 0:
        s = sc_fwd[s]
        steps = steps + 1
    return wp.vec2i(s, steps)


@wp.func
def _merge_border(h: wp.array2d(dtype=wp.float32), vertical: int, fixed: int, start: int, end: int, tol: float,
                  m: int, depth: int, single_rec: wp.array(dtype=wp.int32), node_base: wp.array(dtype=wp.int32),
                  rec_father: wp.array(dtype=wp.int32), level_base: wp.array(dtype=wp.int32),
                  sc_rect: wp.array(dtype=wp.vec4i), sc_fwd: wp.array(dtype=wp.int32),
                  sc_flags: wp.array(dtype=wp.int32), stats: wp.array(dtype=wp.int64)) -> int:
    """Walk one border (column ``fixed`` if vertical, else row ``fixed``) from ``start`` to ``end`` and
    merge every passing pair; returns the number of merges."""
    merges = int(0)
    tests = int(0)
    bfail = int(0)
    sfail = int(0)
    steps = int(0)
    max_steps = int(0)
    p = start
    while p < end:
        a = int(0)
        b = int(0)
        fa = wp.vec2i()
        fb = wp.vec2i()
        if vertical != 0:
            fa = _find(p, fixed - 1, m, depth, single_rec, node_base, rec_father, level_base, sc_fwd)
            fb = _find(p, fixed, m, depth, single_rec, node_base, rec_father, level_base, sc_fwd)
        else:
            fa = _find(fixed - 1, p, m, depth, single_rec, node_base, rec_father, level_base, sc_fwd)
            fb = _find(fixed, p, m, depth, single_rec, node_base, rec_father, level_base, sc_fwd)
        a = fa[0]
        b = fb[0]
        steps = steps + fa[1] + fb[1]
        max_steps = wp.max(max_steps, wp.max(fa[1], fb[1]))
        ra = sc_rect[a]
        rb = sc_rect[b]
        k0 = 2  # extent along the border: rows for a vertical border, columns for a horizontal one
        if vertical != 0:
            k0 = 0
        ea = ra[k0 + 1]
        eb = rb[k0 + 1]
        tests = tests + 1
        ok = int(0)
        if ra[k0] == rb[k0] and ea == eb:
            ga = _grads(h, ra)
            gb = _grads(h, rb)
            d = wp.abs(ga[0] - gb[0]) + wp.abs(ga[1] - gb[1])
            if d <= tol:
                u = wp.vec4i(ra[0], rb[1], ra[2], rb[3])  # a is on the low side of the border
                sc_rect[a] = u
                sc_fwd[b] = a
                # the union keeps the failures of its outer sides (the shared side is gone)
                if vertical != 0:
                    sc_flags[a] = (sc_flags[a] & 13) | (sc_flags[b] & 14)
                else:
                    sc_flags[a] = (sc_flags[a] & 7) | (sc_flags[b] & 11)
                merges = merges + 1
                ok = 1
            else:
                sfail = sfail + 1
        else:
            bfail = bfail + 1
        if ok == 0:
            if vertical != 0:
                sc_flags[a] = sc_flags[a] | 2
                sc_flags[b] = sc_flags[b] | 1
            else:
                sc_flags[a] = sc_flags[a] | 8
                sc_flags[b] = sc_flags[b] | 4
        p = wp.min(ea, eb)
    wp.atomic_add(stats, 0, wp.int64(tests))
    wp.atomic_add(stats, 1, wp.int64(bfail))
    wp.atomic_add(stats, 2, wp.int64(sfail))
    wp.atomic_add(stats, 3, wp.int64(merges))
    wp.atomic_add(stats, 4, wp.int64(steps))
    wp.atomic_max(stats, 5, wp.int64(max_steps))
    return merges


# ------------------------------------------------------------------------------------------------
# kernels
# ------------------------------------------------------------------------------------------------


@wp.kernel(enable_backward=False)
def _leaf_count_kernel(
    active: wp.array(dtype=wp.int32),
    depth: int,
    ch: int,
    cw: int,
    single_prev: wp.array(dtype=wp.int32),
    node_base: wp.array(dtype=wp.int32),
    # outputs
    out_count: wp.array(dtype=wp.int32),
):
    k = active[wp.tid()]
    ij = _demorton(k, depth)
    c = int(0)
    if ij[0] < ch and ij[1] < cw:
        c = 1
        if depth > 0:
            if single_prev[node_base[1] + (k >> 2)] != 0:
                c = 0
    out_count[k] = c


@wp.kernel(enable_backward=False)
def _merge_kernel(
    active: wp.array(dtype=wp.int32),
    h: wp.array2d(dtype=wp.float32),
    m: int,
    depth: int,
    ch: int,
    cw: int,
    tol: float,
    single_prev: wp.array(dtype=wp.int32),
    node_base: wp.array(dtype=wp.int32),
    level_base: wp.array(dtype=wp.int32),
    prev_off: wp.array(dtype=wp.int32),
    rec_rect: wp.array(dtype=wp.vec4i),
    rec_flags: wp.array(dtype=wp.int32),
    rec_father: wp.array(dtype=wp.int32),
    single_rec: wp.array(dtype=wp.int32),
    # outputs
    sc_rect: wp.array(dtype=wp.vec4i),
    sc_fwd: wp.array(dtype=wp.int32),
    sc_flags: wp.array(dtype=wp.int32),
    out_count: wp.array(dtype=wp.int32),
    stats: wp.array(dtype=wp.int64),
):
    k = active[wp.tid()]
    if m < depth:
        if single_prev[node_base[m + 1] + (k >> 2)] != 0:
            out_count[k] = 0
            return
    if single_prev[node_base[m] + k] != 0:
        out_count[k] = 1
        return
    lo = prev_off[4 * k]
    hi = prev_off[4 * k + 4]
    if hi == lo:
        out_count[k] = 0
        return
    pb = level_base[m - 1]
    for s in range(lo, hi):
        sc_rect[s] = rec_rect[pb + s]
        sc_fwd[s] = -1
        sc_flags[s] = rec_flags[pb + s]
    nr = _node_rect(k, m, depth, ch, cw)
    half = 1 << (m - 1)
    jm = nr[2] + half
    im = nr[0] + half
    n = hi - lo
    if jm < cw:
        # border A (son 1 | son 2), then B (son 4 | son 3)
        n = n - _merge_border(h, 1, jm, nr[0], wp.min(im, nr[1]), tol, m, depth, single_rec, node_base, rec_father,
                              level_base, sc_rect, sc_fwd, sc_flags, stats)
        if im < ch:
            n = n - _merge_border(h, 1, jm, im, nr[1], tol, m, depth, single_rec, node_base, rec_father,
                                  level_base, sc_rect, sc_fwd, sc_flags, stats)
    if im < ch:
        # border C (sons 1-2 | sons 4-3)
        n = n - _merge_border(h, 0, im, nr[2], nr[3], tol, m, depth, single_rec, node_base, rec_father,
                              level_base, sc_rect, sc_fwd, sc_flags, stats)
    out_count[k] = n


@wp.kernel(enable_backward=False)
def _emit_kernel(
    active: wp.array(dtype=wp.int32),
    h: wp.array2d(dtype=wp.float32),
    m: int,
    depth: int,
    ch: int,
    cw: int,
    single_prev: wp.array(dtype=wp.int32),
    node_base: wp.array(dtype=wp.int32),
    level_base: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
    off: wp.array(dtype=wp.int32),
    prev_off: wp.array(dtype=wp.int32),
    sc_rect: wp.array(dtype=wp.vec4i),
    sc_fwd: wp.array(dtype=wp.int32),
    sc_flags: wp.array(dtype=wp.int32),
    # outputs
    sc_out: wp.array(dtype=wp.int32),
    rec_rect: wp.array(dtype=wp.vec4i),
    rec_grad: wp.array(dtype=wp.vec2),
    rec_flags: wp.array(dtype=wp.int32),
    rec_father: wp.array(dtype=wp.int32),
    single_rec: wp.array(dtype=wp.int32),
):
    k = active[wp.tid()]
    cnt = count[k]
    o = level_base[m] + off[k]
    if cnt == 1:
        single_rec[node_base[m] + k] = o
    else:
        single_rec[node_base[m] + k] = -1
    if cnt == 0:
        return
    if m == 0 or single_prev[node_base[m] + k] != 0:
        r = _node_rect(k, m, depth, ch, cw)
        rec_rect[o] = r
        rec_grad[o] = _grads(h, r)
        rec_flags[o] = 0
        rec_father[o] = -1
        return
    lo = prev_off[4 * k]
    hi = prev_off[4 * k + 4]
    n = int(0)
    for s in range(lo, hi):
        if sc_fwd[s] < 0:
            r = sc_rect[s]
            rec_rect[o + n] = r
            rec_grad[o + n] = _grads(h, r)
            rec_flags[o + n] = sc_flags[s]
            rec_father[o + n] = -1
            sc_out[s] = o + n
            n = n + 1
    pb = level_base[m - 1]
    for s in range(lo, hi):
        f = s
        while sc_fwd[f] >= 0:
            f = sc_fwd[f]
        rec_father[pb + s] = sc_out[f]


@wp.kernel(enable_backward=False)
def _keep_single_kernel(
    single_rec: wp.array(dtype=wp.int32),
    # outputs
    single_prev: wp.array(dtype=wp.int32),
):
    k = wp.tid()
    if single_rec[k] >= 0:
        single_prev[k] = 1


@wp.kernel(enable_backward=False)
def _paint_kernel(
    rects: wp.array(dtype=wp.vec4i),
    # outputs
    out_label: wp.array2d(dtype=wp.int32),
    out_hits: wp.array2d(dtype=wp.int32),
):
    p = wp.tid()
    r = rects[p]
    for i in range(r[0], r[1]):
        for j in range(r[2], r[3]):
            out_label[i, j] = p
            wp.atomic_add(out_hits, i, j, 1)


# ------------------------------------------------------------------------------------------------
# triangulation (section 2.4)
# ------------------------------------------------------------------------------------------------
# Sides of a rectangle (i0, i1, j0, j1): 0 = the i0 side (j varies), 1 = the j1 side (i varies),
# 2 = the i1 side (j varies), 3 = the j0 side (i varies). The vertices on a side are its two corners and
# every end of a neighbour's extent that falls inside it (found through the label map: the polygon of the
# cell across the side), so two rectangles sharing a segment see the same vertices on it.


@wp.func
def _side_step(label: wp.array2d(dtype=wp.int32), rects: wp.array(dtype=wp.vec4i), r: wp.vec4i, side: int,
               pos: int, direction: int) -> int:
    """Next vertex position along ``side`` of ``r`` from ``pos`` in ``direction`` (+1 / -1)."""
    ch = label.shape[0]
    cw = label.shape[1]
    lo = r[2]
    hi = r[3]
    if side == 1 or side == 3:
        lo = r[0]
        hi = r[1]
    cell = pos
    if direction < 0:
        cell = pos - 1
    nb = int(-1)
    if side == 0:
        if r[0] > 0:
            nb = label[r[0] - 1, cell]
    elif side == 2:
        if r[1] < ch:
            nb = label[r[1], cell]
    elif side == 1:
        if r[3] < cw:
            nb = label[cell, r[3]]
    else:
        if r[2] > 0:
            nb = label[cell, r[2] - 1]
    if nb < 0:
        if direction > 0:
            return hi
        return lo
    q = rects[nb]
    if side == 0 or side == 2:
        if direction > 0:
            return wp.min(q[3], hi)
        return wp.max(q[2], lo)
    if direction > 0:
        return wp.min(q[1], hi)
    return wp.max(q[0], lo)


@wp.func
def _side_vertex(r: wp.vec4i, side: int, pos: int) -> wp.vec2i:
    """Grid (i, j) of the vertex at ``pos`` on ``side``."""
    if side == 0:
        return wp.vec2i(r[0], pos)
    if side == 2:
        return wp.vec2i(r[1], pos)
    if side == 1:
        return wp.vec2i(pos, r[3])
    return wp.vec2i(pos, r[2])


@wp.func
def _side_count(label: wp.array2d(dtype=wp.int32), rects: wp.array(dtype=wp.vec4i), r: wp.vec4i,
                side: int) -> int:
    lo = r[2]
    hi = r[3]
    if side == 1 or side == 3:
        lo = r[0]
        hi = r[1]
    n = int(0)
    p = lo
    while p < hi:
        p = _side_step(label, rects, r, side, p, 1)
        n = n + 1
    return n


@wp.func
def _len2(a: wp.vec2i, b: wp.vec2i, dx: float, dz: float) -> float:
    ex = float(a[1] - b[1]) * dx
    ez = float(a[0] - b[0]) * dz
    return ex * ex + ez * ez


@wp.func
def _emit_tri(a: wp.vec2i, b: wp.vec2i, c: wp.vec2i, w: int, remap: wp.array(dtype=wp.int32), t: int,
              out_tri: wp.array2d(dtype=wp.int32)):
    # counter-clockwise seen from +y with x = column, z = row: (bz - az)(cx - ax) - (bx - ax)(cz - az) > 0
    ny = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
    out_tri[t, 0] = remap[a[0] * w + a[1]]
    if ny > 0:
        out_tri[t, 1] = remap[b[0] * w + b[1]]
        out_tri[t, 2] = remap[c[0] * w + c[1]]
    else:
        out_tri[t, 1] = remap[c[0] * w + c[1]]
        out_tri[t, 2] = remap[b[0] * w + b[1]]


@wp.func
def _zipper(label: wp.array2d(dtype=wp.int32), rects: wp.array(dtype=wp.vec4i), r: wp.vec4i, xs: int, x0: int,
            xm: int, xd: int, ys: int, y0: int, ym: int, yd: int, dx: float, dz: float, w: int,
            remap: wp.array(dtype=wp.int32), t0: int, out_tri: wp.array2d(dtype=wp.int32)) -> int:
    """Triangulate the half of ``r`` between side ``xs`` (walked from x0 to the shared corner xm, direction
    xd) and side ``ys`` (walked from y0 to the corner ym, direction yd): the diagonal joins x0 and y0.
    Every triangle has one vertex on each side except the last, so none is degenerate."""
    t = t0
    xa = x0
    yb = y0
    mc = _side_vertex(r, xs, xm)
    while True:
        xn = _side_step(label, rects, r, xs, xa, xd)
        yn = _side_step(label, rects, r, ys, yb, yd)
        va = _side_vertex(r, xs, xa)
        vb = _side_vertex(r, ys, yb)
        canx = xn != xm
        cany = yn != ym
        if not canx and not cany:
            _emit_tri(va, mc, vb, w, remap, t, out_tri)
            t = t + 1
            break
        vxn = _side_vertex(r, xs, xn)
        vyn = _side_vertex(r, ys, yn)
        takex = canx
        if canx and cany:
            takex = _len2(vxn, vb, dx, dz) <= _len2(va, vyn, dx, dz)
        if takex:
            _emit_tri(va, vxn, vb, w, remap, t, out_tri)
            xa = xn
        else:
            _emit_tri(va, vyn, vb, w, remap, t, out_tri)
            yb = yn
        t = t + 1
    return t


@wp.func
def _use_ac(h: wp.array2d(dtype=wp.float32), r: wp.vec4i) -> bool:
    """Split along the (i0, j0)-(i1, j1) diagonal when its midpoint is closer to the heightmap at the
    rectangle's centre than the other diagonal's (ties: that diagonal)."""
    za = h[r[0], r[2]]
    zb = h[r[0], r[3]]
    zc = h[r[1], r[3]]
    zd = h[r[1], r[2]]
    ci = r[0] + r[1]
    cj = r[2] + r[3]
    zm = 0.25 * (h[ci / 2, cj / 2] + h[(ci + 1) / 2, cj / 2] + h[ci / 2, (cj + 1) / 2] + h[(ci + 1) / 2, (cj + 1) / 2])
    return wp.abs(0.5 * (za + zc) - zm) <= wp.abs(0.5 * (zb + zd) - zm)


@wp.kernel(enable_backward=False)
def _tri_count_kernel(
    label: wp.array2d(dtype=wp.int32),
    rects: wp.array(dtype=wp.vec4i),
    w: int,
    # outputs
    out_count: wp.array(dtype=wp.int32),
    out_used: wp.array(dtype=wp.int32),
):
    p = wp.tid()
    r = rects[p]
    n = int(0)
    for side in range(4):
        n = n + _side_count(label, rects, r, side)
    out_count[p] = n - 2
    # mark the boundary vertices (every writer writes 1: order-independent)
    for side in range(4):
        lo = r[2]
        hi = r[3]
        if side == 1 or side == 3:
            lo = r[0]
            hi = r[1]
        q = lo
        while q < hi:
            v = _side_vertex(r, side, q)
            out_used[v[0] * w + v[1]] = 1
            q = _side_step(label, rects, r, side, q, 1)
        v = _side_vertex(r, side, hi)
        out_used[v[0] * w + v[1]] = 1


@wp.kernel(enable_backward=False)
def _tri_emit_kernel(
    h: wp.array2d(dtype=wp.float32),
    label: wp.array2d(dtype=wp.int32),
    rects: wp.array(dtype=wp.vec4i),
    off: wp.array(dtype=wp.int32),
    remap: wp.array(dtype=wp.int32),
    dx: float,
    dz: float,
    # outputs
    out_tri: wp.array2d(dtype=wp.int32),
):
    p = wp.tid()
    r = rects[p]
    w = h.shape[1]
    t = off[p]
    if _use_ac(h, r):
        # corner B = (i0, j1): sides 0 (A -> B) and 1 (C -> B); corner D = (i1, j0): sides 2 (C -> D), 3 (A -> D)
        t = _zipper(label, rects, r, 0, r[2], r[3], 1, 1, r[1], r[0], -1, dx, dz, w, remap, t, out_tri)
        t = _zipper(label, rects, r, 2, r[3], r[2], -1, 3, r[0], r[1], 1, dx, dz, w, remap, t, out_tri)
    else:
        # corner C = (i1, j1): sides 1 (B -> C) and 2 (D -> C); corner A: sides 3 (D -> A) and 0 (B -> A)
        t = _zipper(label, rects, r, 1, r[0], r[1], 1, 2, r[2], r[3], 1, dx, dz, w, remap, t, out_tri)
        t = _zipper(label, rects, r, 3, r[1], r[0], -1, 0, r[3], r[2], -1, dx, dz, w, remap, t, out_tri)


# ------------------------------------------------------------------------------------------------
# TIN morphing (section 2.5)
# ------------------------------------------------------------------------------------------------


@wp.func
def _is_corner(q: wp.vec4i, i: int, j: int) -> bool:
    return (i == q[0] or i == q[1]) and (j == q[2] or j == q[3])


@wp.func
def _nearer(v: int, a: int, b: int) -> int:
    if v - a <= b - v:
        return a
    return b


@wp.kernel(enable_backward=False)
def _morph_target_kernel(
    src: wp.array(dtype=wp.vec2i),
    label: wp.array2d(dtype=wp.int32),
    rects: wp.array(dtype=wp.vec4i),
    # outputs
    out_dst: wp.array(dtype=wp.vec2i),
):
    """Map each fine vertex to a vertex of the coarse tiling (label, rects) that lies on the closure of
    every coarse polygon the fine vertex touches: coarse vertices stay, vertices on a coarse edge slide
    along it to its nearer end, vertices inside a coarse polygon go to its nearest corner."""
    t = wp.tid()
    v = src[t]
    i = v[0]
    j = v[1]
    ch = label.shape[0]
    cw = label.shape[1]
    ll = int(-1)  # labels of cells (i-1, j-1), (i-1, j), (i, j-1), (i, j)
    lr = int(-1)
    ul = int(-1)
    ur = int(-1)
    if i > 0 and j > 0:
        ll = label[i - 1, j - 1]
    if i > 0 and j < cw:
        lr = label[i - 1, j]
    if i < ch and j > 0:
        ul = label[i, j - 1]
    if i < ch and j < cw:
        ur = label[i, j]
    corner = False
    if ll >= 0:
        corner = corner or _is_corner(rects[ll], i, j)
    if lr >= 0:
        corner = corner or _is_corner(rects[lr], i, j)
    if ul >= 0:
        corner = corner or _is_corner(rects[ul], i, j)
    if ur >= 0:
        corner = corner or _is_corner(rects[ur], i, j)
    if corner:
        out_dst[t] = v
        return
    a = ll  # some polygon touching v
    if a < 0:
        a = lr
    if a < 0:
        a = ul
    if a < 0:
        a = ur
    b = ur
    if b < 0:
        b = ul
    if b < 0:
        b = lr
    if a == b or b < 0:
        # inside one polygon (or on its terrain-border side): per axis, keep a coordinate on a side
        q = rects[a]
        ni = i
        nj = j
        if i != q[0] and i != q[1]:
            ni = _nearer(i, q[0], q[1])
        if j != q[2] and j != q[3]:
            nj = _nearer(j, q[2], q[3])
        out_dst[t] = wp.vec2i(ni, nj)
        return
    # on a coarse edge between two polygons: horizontal if the row above differs from the row below
    qa = rects[a]
    qb = rects[b]
    if qa[1] == i or qa[0] == i:
        lo = wp.max(qa[2], qb[2])
        hi = wp.min(qa[3], qb[3])
        out_dst[t] = wp.vec2i(i, _nearer(j, lo, hi))
    else:
        lo = wp.max(qa[0], qb[0])
        hi = wp.min(qa[1], qb[1])
        out_dst[t] = wp.vec2i(_nearer(i, lo, hi), j)


@wp.func
def _bilinear(h: wp.array2d(dtype=wp.float32), fi: float, fj: float) -> float:
    i0 = wp.min(int(wp.floor(fi)), h.shape[0] - 2)
    j0 = wp.min(int(wp.floor(fj)), h.shape[1] - 2)
    i0 = wp.max(i0, 0)
    j0 = wp.max(j0, 0)
    ti = fi - float(i0)
    tj = fj - float(j0)
    a = h[i0, j0] + tj * (h[i0, j0 + 1] - h[i0, j0])
    b = h[i0 + 1, j0] + tj * (h[i0 + 1, j0 + 1] - h[i0 + 1, j0])
    return a + ti * (b - a)


@wp.kernel(enable_backward=False)
def _morph_positions_kernel(
    h: wp.array2d(dtype=wp.float32),
    src: wp.array(dtype=wp.vec2i),
    dst: wp.array(dtype=wp.vec2i),
    s: float,
    dx: float,
    dz: float,
    rel_origin: wp.vec3,
    # outputs
    out_pos: wp.array(dtype=wp.vec3),
):
    t = wp.tid()
    a = src[t]
    b = dst[t]
    fi = float(a[0]) + s * float(b[0] - a[0])
    fj = float(a[1]) + s * float(b[1] - a[1])
    y = float(0.0)
    if s == 0.0:
        y = h[a[0], a[1]]
    elif s == 1.0:
        y = h[b[0], b[1]]
    else:
        y = _bilinear(h, fi, fj)
    out_pos[t] = wp.vec3(rel_origin[0] + fj * dx, y - rel_origin[1], rel_origin[2] + fi * dz)


# ------------------------------------------------------------------------------------------------
# host drivers
# ------------------------------------------------------------------------------------------------


class MergeState:
    """Device arrays of the merge, reused across tolerances (the quadtree of the paper).

    Attributes:
        depth: quadtree depth (N = 2^depth cells a side).
        n_nodes: nodes per level, level 0 (cells) .. depth (root).
        node_base: (depth+2,) int32 offsets of each level in the flat per-node arrays.
        level_base: (depth+1,) int32 offsets of each level's records in the flat record arrays
            (each level has room for one record per cell).
        single_prev: flat (sum n_nodes,) int32, 1 where a node held one polygon after an earlier tolerance.
    """

    def __init__(self, heights: np.ndarray, device: str = "cpu"):
        hh, ww = heights.shape
        self.ch, self.cw = hh - 1, ww - 1
        self.ncells = self.ch * self.cw
        n = max(self.ch, self.cw)
        self.depth = int(max(0, int(np.ceil(np.log2(n))))) if n > 1 else 0
        d = self.depth
        self.n_nodes = [4 ** (d - m) for m in range(d + 1)]
        nb = np.zeros(d + 2, np.int32)
        nb[1:] = np.cumsum(self.n_nodes)
        self.node_base_np = nb
        self.device = device
        self.h = wp.array(np.ascontiguousarray(heights, np.float32), dtype=wp.float32, device=device)
        self.node_base = wp.array(nb, dtype=wp.int32, device=device)
        self.level_base = wp.array(np.arange(d + 1, dtype=np.int32) * self.ncells, dtype=wp.int32, device=device)
        total_nodes = int(nb[-1])
        self.single_prev = wp.zeros(total_nodes, dtype=wp.int32, device=device)
        self.single_rec = wp.full(total_nodes, value=-1, dtype=wp.int32, device=device)
        cap = self.ncells * (d + 1)
        self.rec_rect = wp.zeros(cap, dtype=wp.vec4i, device=device)
        self.rec_grad = wp.zeros(cap, dtype=wp.vec2, device=device)
        self.rec_flags = wp.zeros(cap, dtype=wp.int32, device=device)
        self.rec_father = wp.full(cap, value=-1, dtype=wp.int32, device=device)
        self.sc_rect = wp.zeros(self.ncells, dtype=wp.vec4i, device=device)
        self.sc_fwd = wp.full(self.ncells, value=-1, dtype=wp.int32, device=device)
        self.sc_flags = wp.zeros(self.ncells, dtype=wp.int32, device=device)
        self.sc_out = wp.zeros(self.ncells, dtype=wp.int32, device=device)
        self.count = [wp.zeros(c + 1, dtype=wp.int32, device=device) for c in self.n_nodes]
        self.off = [wp.zeros(c + 1, dtype=wp.int32, device=device) for c in self.n_nodes]
        self.stats = wp.zeros(6, dtype=wp.int64, device=device)
        self._cmds = None
        # nodes that hold at least one cell, per level (Morton order)
        self._inside = []
        for m in range(d + 1):
            code = np.arange(self.n_nodes[m], dtype=np.int64)
            i = np.zeros_like(code)
            j = np.zeros_like(code)
            for b in range(d - m):
                j |= ((code >> (2 * b)) & 1) << b
                i |= ((code >> (2 * b + 1)) & 1) << b
            self._inside.append(((i << m) < self.ch) & ((j << m) < self.cw))
        self.active = [wp.zeros(c, dtype=wp.int32, device=device) for c in self.n_nodes]
        self.n_active = [0] * (d + 1)
        self._update_active()

    def run_pass(self, tol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Merge every level at ``tol``; returns the root's polygons: rects (P, 4) int32 (i0, i1, j0, j1),
        gradients (P, 2) float32 (Xgr, Ygr), flags (P,) int32."""
        dev = self.device
        d = self.depth
        if self._cmds is None:
            self._cmds = self._record()
        for m in range(d + 1):
            first, emit = self._cmds[m]
            na = self.n_active[m]
            self.count[m].zero_()
            if na:
                if m > 0:
                    first.set_param_by_name("tol", float(tol))
                first.set_dim(na)
                first.launch()
            wp.utils.array_scan(self.count[m], self.off[m], inclusive=False)  # count[n] is 0: off[n] = total
            if na:
                emit.set_dim(na)
                emit.launch()
        # step j: nodes holding one polygon keep it for every higher tolerance
        wp.launch(_keep_single_kernel, dim=self.single_rec.shape[0], inputs=[self.single_rec],
                  outputs=[self.single_prev], device=dev)
        self._update_active()
        base = d * self.ncells
        total = int(self.off[d].numpy()[1])
        # copies: on the CPU .numpy() is a view of memory the next pass overwrites
        rects = self.rec_rect[base:base + total].numpy().reshape(total, 4).copy()
        grads = self.rec_grad[base:base + total].numpy().reshape(total, 2).copy()
        flags = self.rec_flags[base:base + total].numpy().reshape(total).copy()
        return rects, grads, flags

    def _update_active(self) -> None:
        """Next pass's work lists: per level, the nodes that hold cells and whose father does not hold a
        single polygon already (the nodes under a single one are never visited again; their stale
        ``single_rec`` entries are never read, as every neighbour search stops at the single ancestor)."""
        sp = self.single_prev.numpy()
        nb = self.node_base_np
        for m in range(self.depth + 1):
            keep = self._inside[m].copy()
            if m < self.depth:
                keep &= np.repeat(sp[nb[m + 1]:nb[m + 2]] == 0, 4)
            idx = np.flatnonzero(keep).astype(np.int32)
            self.n_active[m] = len(idx)
            if len(idx):
                self.active[m][:len(idx)].assign(idx)

    def _record(self) -> list:
        """Recorded launches per level (packing the arguments once; a pass only changes the tolerance)."""
        dev = self.device
        d = self.depth
        cmds = []
        for m in range(d + 1):
            n = self.n_nodes[m]
            cnt = self.count[m]
            if m == 0:
                first = wp.launch(_leaf_count_kernel, dim=n,
                                  inputs=[self.active[m], d, self.ch, self.cw, self.single_prev, self.node_base],
                                  outputs=[cnt], device=dev, record_cmd=True)
            else:
                first = wp.launch(_merge_kernel, dim=n,
                                  inputs=[self.active[m], self.h, m, d, self.ch, self.cw, 0.0, self.single_prev,
                                          self.node_base, self.level_base, self.off[m - 1], self.rec_rect,
                                          self.rec_flags, self.rec_father, self.single_rec],
                                  outputs=[self.sc_rect, self.sc_fwd, self.sc_flags, cnt, self.stats], device=dev,
                                  record_cmd=True)
            emit = wp.launch(_emit_kernel, dim=n,
                             inputs=[self.active[m], self.h, m, d, self.ch, self.cw, self.single_prev, self.node_base,
                                     self.level_base, cnt, self.off[m], self.off[m - 1] if m else self.off[0],
                                     self.sc_rect, self.sc_fwd, self.sc_flags],
                             outputs=[self.sc_out, self.rec_rect, self.rec_grad, self.rec_flags, self.rec_father,
                                      self.single_rec], device=dev, record_cmd=True)
            cmds.append((first, emit))
        return cmds

    def take_stats(self) -> np.ndarray:
        s = self.stats.numpy().copy()
        self.stats.zero_()
        return s


def paint(rects: np.ndarray, shape_cells: tuple[int, int], device: str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """Label map (ch, cw) int32 (polygon index per cell, -1 where none) and hit counts (ch, cw) int32."""
    ch, cw = shape_cells
    label = wp.full((ch, cw), value=-1, dtype=wp.int32, device=device)
    hits = wp.zeros((ch, cw), dtype=wp.int32, device=device)
    if len(rects):
        r = wp.array(np.ascontiguousarray(rects, np.int32), dtype=wp.vec4i, device=device)
        wp.launch(_paint_kernel, dim=len(rects), inputs=[r], outputs=[label, hits], device=device)
    return label.numpy(), hits.numpy()


def triangulate_tiling(heights: np.ndarray, rects: np.ndarray, label: np.ndarray, dx: float, dz: float,
                       device: str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """Triangulate a tiling of the cells by rectangles without gaps or T-junctions.

    Args:
        heights: (H, W) float32.
        rects: (P, 4) int32 (i0, i1, j0, j1) tiling the (H-1) x (W-1) cells.
        label: (H-1, W-1) int32 index into ``rects`` per cell.

    Returns:
        vertices (n, 2) int32 grid (i, j) of the used samples (ascending i*W + j), triangles (m, 3) int32
        indices into them, counter-clockwise seen from +y; m = sum over rectangles of (boundary vertices - 2).
    """
    hh, ww = heights.shape
    p = len(rects)
    h = wp.array(np.ascontiguousarray(heights, np.float32), dtype=wp.float32, device=device)
    lab = wp.array(np.ascontiguousarray(label, np.int32), dtype=wp.int32, device=device)
    r = wp.array(np.ascontiguousarray(rects, np.int32), dtype=wp.vec4i, device=device)
    count = wp.zeros(p + 1, dtype=wp.int32, device=device)
    used = wp.zeros(hh * ww + 1, dtype=wp.int32, device=device)
    wp.launch(_tri_count_kernel, dim=p, inputs=[lab, r, ww], outputs=[count, used], device=device)
    off = wp.empty(p + 1, dtype=wp.int32, device=device)
    wp.utils.array_scan(count, off, inclusive=False)
    remap = wp.empty(hh * ww + 1, dtype=wp.int32, device=device)
    wp.utils.array_scan(used, remap, inclusive=False)
    m = int(off.numpy()[p])
    tri = wp.zeros((max(m, 1), 3), dtype=wp.int32, device=device)
    wp.launch(_tri_emit_kernel, dim=p, inputs=[h, lab, r, off, remap, float(dx), float(dz)], outputs=[tri],
              device=device)
    used_np = used.numpy()[:hh * ww]
    vid = np.flatnonzero(used_np)
    verts = np.stack([vid // ww, vid % ww], 1).astype(np.int32)
    return verts, tri.numpy()[:m]


def morph_targets(src: np.ndarray, coarse_rects: np.ndarray, coarse_label: np.ndarray,
                  device: str = "cpu") -> np.ndarray:
    """(n, 2) int32 grid vertex of the coarse tiling each fine vertex ``src`` (n, 2) int32 morphs to."""
    n = len(src)
    if n == 0:
        return np.zeros((0, 2), np.int32)
    s = wp.array(np.ascontiguousarray(src, np.int32), dtype=wp.vec2i, device=device)
    lab = wp.array(np.ascontiguousarray(coarse_label, np.int32), dtype=wp.int32, device=device)
    r = wp.array(np.ascontiguousarray(coarse_rects, np.int32), dtype=wp.vec4i, device=device)
    out = wp.empty(n, dtype=wp.vec2i, device=device)
    wp.launch(_morph_target_kernel, dim=n, inputs=[s, lab, r], outputs=[out], device=device)
    return out.numpy().reshape(n, 2)


def morph_positions(heights: np.ndarray, src: np.ndarray, dst: np.ndarray, s: float, dx: float, dz: float,
                    rel_origin: tuple[float, float, float], device: str = "cpu") -> np.ndarray:
    """(n, 3) float32 camera-relative positions at morph parameter ``s`` in [0, 1]: x, z interpolated
    linearly from ``src`` to ``dst`` (grid (i, j)), y sampled bilinearly from the heightmap (exact sample
    heights at s = 0 and s = 1)."""
    n = len(src)
    out = wp.empty(max(n, 1), dtype=wp.vec3, device=device)
    if n:
        h = wp.array(np.ascontiguousarray(heights, np.float32), dtype=wp.float32, device=device)
        a = wp.array(np.ascontiguousarray(src, np.int32), dtype=wp.vec2i, device=device)
        b = wp.array(np.ascontiguousarray(dst, np.int32), dtype=wp.vec2i, device=device)
        wp.launch(_morph_positions_kernel, dim=n, inputs=[h, a, b, float(s), float(dx), float(dz),
                                                           wp.vec3(*rel_origin)], outputs=[out], device=device)
    return out.numpy()[:n].reshape(n, 3)

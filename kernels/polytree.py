"""Bottom-up polygon merging of taylor-barrett-continuous-resolution.txt as Warp kernels.

The heightmap's (H-1) x (W-1) cells are the unit polygons; a rectangle is ``(i0, i1, j0, j1)`` in cell
coordinates (half-open), so its corners are the samples ``(i0, j0)`` .. ``(i1, j1)``. The paper's
corners z1..z4 are ``h[i0, j0]``, ``h[i0, j1]``, ``h[i1, j1]``, ``h[i1, j0]`` and its unnormalised
gradients (equations 1-2) are ``Xgr = (z2 - z1) + (z3 - z4)`` and ``Ygr = (z4 - z1) + (z3 - z2)``.

Quadtree: the cells are padded to N x N, N = 2^depth; a node of level ``l`` covers 2^l x 2^l cells and
nodes of a level are numbered in Morton order (bit 2b of the code is bit b of the column, bit 2b+1 of the
row), so the four sons of node k are 4k .. 4k+3 in the order son 1 (low row, low column), son 2 (low row,
high column), son 4 (high row, low column), son 3 (high row, high column) of the paper's figure 6.

A node merges its sons' polygons along border A (son 1 | son 2), then B (son 4 | son 3), then C (top half |
bottom half), walking each border with the neighbour search of section 2.1: descend the quadtree to the
topmost node that holds a single polygon and contains the point, then follow the polytree's father pointers
up to the sons' level and the merge pointers inside the node, O(depth). A pair passes the bounds check
when its extents along the border are equal (the union is a rectangle) and the homogeneity check when
``|dXgr| + |dYgr| <= tolerance`` (the paper says "less than"; ``<=`` lets tolerance 0 merge exactly coplanar
cells). A failed pair sets a flag bit on both polygons (FLAG_* below).

The tolerances come in ascending order, one pass each, and a pass costs what changed since the last one:

* step j of the paper: a node that held a single polygon after a pass keeps it ("frozen") and is never
  merged again (single is hereditary: two polygons of a node are never joined higher up);
* a node merges exactly as in its last merge while neither its sons' polygons changed nor the tolerance
  reached a similarity that failed in it, so each node keeps the smallest failed ``|dXgr| + |dYgr|`` of its
  subtree, and a pass merges again only the unfrozen nodes where that is <= the tolerance (each of them
  changes). Their last merges are undone top-down (each node logs the polygons its merge changed), then
  they merge again bottom-up.

Everything a pass reports is what merging every unfrozen node again would give: the root's polygons in the
paper's order with their flags, and the counters (STAT_*) of all unfrozen nodes (an unchanged node's are
those of its last merge); ``tests/lod/test_polytree.py`` checks every pass against the per-tolerance
algorithm. A pass touches the few nodes a tolerance changes, where launches per level visit all of them
(issue 19: 100 tolerances of a 257^2 map took 0.76 s as three launches a level a pass, 27 a tolerance):

* one thread, one launch (``_pass_kernel``): on one CPU thread, on CUDA, and for a depth below 4;
* on several CPU threads, a pass that merges many nodes (``MergeState.PARALLEL_MIN_NODES``) is three
  launches: mark and undo the top three levels (one thread), then undo and merge again the marked nodes
  inside each of the 64 nodes three levels below the root (``_subtree_kernel``, through the parallel-launch
  helper: a subtree's slots, nodes and undo logs are its own), then merge the top levels again and emit (one
  thread). The counters go to a row per chunk and are summed in a fixed order, and every merge's stamp is
  numbered as the one-thread pass numbers it, so both give the same bits. A pass that merges few nodes runs
  its rest in one thread (two launches).

Section 2.4 (``_tri_count_kernel`` / ``_tri_emit_kernel``) and section 2.5 (``_morph_target_kernel``,
``_morph_positions_kernel``) follow; the host side is :mod:`terrainwarp.lod.polytree`.
"""

from __future__ import annotations

import time

import numpy as np
import warp as wp

from .checks import check_int
from .parallel import launch, launch_one, record, replay, scan, threads

FLAG_LOW_J = 1  # a merge across (part of) the polygon's j0 side was tried and failed
FLAG_HIGH_J = 2  # ... across its j1 side
FLAG_LOW_I = 4  # ... across its i0 side
FLAG_HIGH_I = 8  # ... across its i1 side

# stats counters of a pass
STAT_TESTS, STAT_BOUNDS_FAIL, STAT_SIMILARITY_FAIL, STAT_MERGES, STAT_FIND_STEPS, STAT_FIND_MAX = range(6)
# (two neighbour searches per pair test: mean steps per search = STAT_FIND_STEPS / (2 * STAT_TESTS))

# ------------------------------------------------------------------------------------------------
# merge state
# ------------------------------------------------------------------------------------------------
# Slots: a polygon of any level is named by its corner cell (i0, j0), as the Morton code of that cell in
# the padded N x N grid; the cells of a node of level l are the slots k << 2l .. (k+1) << 2l, and a merge
# keeps the slot of the polygon with the lower corner, so a level's polygons in slot order are its records
# in the paper's order (the sons' lists one after the other, each union where its first part was).
#
# The polygons of every level live in one state: per slot, the polygon whose corner it is after every merge
# so far (_Slot: the root's tiling) and its link, -1 while it is alive, else ``(slot merged into) << 5 |
# level of that merge`` (the polytree's pointers: the polygon of level l containing a cell is found by
# following the links of levels <= l from the cell; slots outside the grid hold _OUTSIDE). Each node
# (_Node) keeps an undo log (_Undo) of the slots its last merge changed, as they were before it (all alive
# then). Arrays of structs, so that one index computation reaches a slot's fields (Warp checks and scales
# every index), and the links, which the searches walk, in their own small array.

_LEVEL_BITS = wp.constant(5)
_LEVEL_MASK = wp.constant(31)
_OUTSIDE = wp.constant(0x7FFFFFFF)


@wp.struct
class _Slot:
    rect: wp.vec4i  # (i0, i1, j0, j1)
    grad: wp.vec2  # (Xgr, Ygr) of rect: equations 1-2, once per rectangle
    flags: wp.int32  # FLAG_*
    stamp: wp.int32  # the node merge that last logged this slot (at logpos[slot] of the undo logs)


@wp.struct
class _Undo:
    rect: wp.vec4i
    grad: wp.vec2
    slot: wp.int32
    flags: wp.int32


@wp.struct
class _Node:
    i0: wp.int32  # the corner cell: the node holds cells when i0 < ch and j0 < cw
    j0: wp.int32
    count: wp.int32  # polygons after its last merge (1 once frozen; a cell: 1)
    frozen: wp.int32  # step j: it held one polygon after a pass and keeps it
    done: wp.int32  # merged at least once
    ulen: wp.int32  # length of its undo log
    sub: wp.float32  # smallest failed |dXgr| + |dYgr| of its last merge and of its subtree's (-inf: never merged)
    tests: wp.int32  # the counters of its last merge (STAT_*)
    bfail: wp.int32
    sfail: wp.int32
    merges: wp.int32
    steps: wp.int32
    smax: wp.int32


@wp.struct
class _MergeArrays:
    """Every array of a :class:`MergeState`: the pass kernel's one argument besides the pass index."""

    h: wp.array2d(dtype=wp.float32)
    tols: wp.array(dtype=wp.float32)  # the tolerances of run_passes
    n_base: wp.array(dtype=wp.int32)  # level l's nodes from n_base[l] in the flat node arrays
    u_base: wp.array(dtype=wp.int32)  # level l's undo logs from u_base[l], _log_room(l) entries a node
    morton_i: wp.array(dtype=wp.int32)  # slot of cell (i, j): morton_i[i] | morton_j[j]
    morton_j: wp.array(dtype=wp.int32)
    nodes: wp.array(dtype=_Node)
    g: wp.array(dtype=_Slot)
    link: wp.array(dtype=wp.int32)
    logpos: wp.array(dtype=wp.int32)
    u: wp.array(dtype=_Undo)
    marks: wp.array(dtype=wp.int32)  # the nodes merged in this pass, level l's from n_base[l]
    n_marked: wp.array(dtype=wp.int32)  # ... how many per level
    stack: wp.array(dtype=wp.int32)  # the output's descent
    totals: wp.array2d(dtype=wp.int64)  # STAT_TESTS .. STAT_FIND_STEPS over the unfrozen nodes, a row per part
    hist: wp.array2d(dtype=wp.int32)  # unfrozen nodes by their most steps of one search (STAT_FIND_MAX), per part
    counter: wp.array(dtype=wp.int32)  # node merges so far (their stamps)
    error: wp.array(dtype=wp.int32)
    out_rect: wp.array(dtype=wp.vec4i)  # every pass's root polygons, appended
    out_grad: wp.array(dtype=wp.vec2)
    out_flags: wp.array(dtype=wp.int32)
    out_used: wp.array(dtype=wp.int32)  # rows written
    out_count: wp.array(dtype=wp.int32)  # per pass: polygons
    out_stats: wp.array2d(dtype=wp.int64)  # per pass: STAT_*
    depth: int
    ch: int
    cw: int
    nc: int  # cells
    nslots: int  # N * N


# ------------------------------------------------------------------------------------------------
# functions
# ------------------------------------------------------------------------------------------------


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
def _log_room(m: int) -> int:
    """Undo log entries of a node of level m: a merge touches each polygon next to a border once, so at most
    the node's cells and at most its border cells."""
    return wp.min(1 << (2 * m), 1 << (m + 2))


@wp.func
def _find(r: int, c: int, m: int, morton_i: wp.array(dtype=wp.int32), morton_j: wp.array(dtype=wp.int32),
          link: wp.array(dtype=wp.int32)) -> wp.vec3i:
    """(slot of the sons' polygon containing cell (r, c), slot of the live polygon it is part of in the merge
    of the node of level m in progress, merge pointers followed inside the node)."""
    x = morton_i[r] | morton_j[c]
    lk = link[x]
    while lk >= 0 and (lk & _LEVEL_MASK) < m:  # up the polytree to the sons' level
        x = lk >> _LEVEL_BITS
        lk = link[x]
    s = x
    hops = int(0)
    while lk >= 0:  # merges of this node (the higher levels' are undone)
        s = lk >> _LEVEL_BITS
        lk = link[s]
        hops = hops + 1
    return wp.vec3i(x, s, hops)


@wp.func
def _top_single(r: int, c: int, x: wp.vec4i, m: int, ch: int, cw: int) -> int:
    """The level of the topmost quadtree node below level m that contains cell (r, c) and holds a single
    polygon, where section 2.1's descent stops: a node holds one polygon exactly when its cells lie in one
    polygon x of level m-1 (two polygons of a node are never joined higher up)."""
    lv = m - 1
    while lv > 0:
        s = 1 << lv
        bi = (r >> lv) << lv
        bj = (c >> lv) << lv
        if bi >= x[0] and wp.min(bi + s, ch) <= x[1] and bj >= x[2] and wp.min(bj + s, cw) <= x[3]:
            break
        lv = lv - 1
    return lv


@wp.func
def _steps(r: int, c: int, f: wp.vec3i, m: int, mid: int, ch: int, cw: int, g: wp.array(dtype=_Slot),
           logpos: wp.array(dtype=wp.int32), u: wp.array(dtype=_Undo)) -> int:
    """Pointer steps of section 2.1's search for cell (r, c), found as ``f`` (:func:`_find`): the descent to
    the topmost single node reads m - top nodes, the father pointers up take m - 1 - top, then the merge
    pointers inside the node."""
    steps = 1 + f[2]
    if m > 1:
        x = g[f[0]].rect  # the sons' polygon as it was before this merge
        if g[f[0]].stamp == mid:
            x = u[logpos[f[0]]].rect
        steps = steps + 2 * (m - 1 - _top_single(r, c, x, m, ch, cw))
    return steps


@wp.func
def _log(s: int, mid: int, at: int, g: wp.array(dtype=_Slot), logpos: wp.array(dtype=wp.int32),
         u: wp.array(dtype=_Undo)) -> int:
    """Before the node merge ``mid`` first changes slot s, save it at ``at`` in its undo log; returns the log's
    new length."""
    if g[s].stamp == mid:
        return at
    g[s].stamp = mid
    logpos[s] = at
    u[at].rect = g[s].rect
    u[at].grad = g[s].grad
    u[at].slot = s
    u[at].flags = g[s].flags
    return at + 1


@wp.func
def _merge_border(h: wp.array2d(dtype=wp.float32), vertical: int, fixed: int, start: int, end: int, tol: float,
                  m: int, node: int, mid: int, at: int, st: _MergeArrays) -> wp.vec2i:
    """Walk one border (column ``fixed`` if vertical, else row ``fixed``) from ``start`` to ``end`` and merge
    every passing pair, logging from ``at``; returns (merges, the log's new length). Adds to the node's
    counters and smallest failure."""
    g = st.g
    link = st.link
    k0 = 2  # extent along the border: rows for a vertical border, columns for a horizontal one
    if vertical != 0:
        k0 = 0
    merges = int(0)
    tests = int(0)
    bfail = int(0)
    sfail = int(0)
    steps = int(0)
    max_steps = int(0)
    thr = float(st.nodes[node].sub)
    p = start
    while p < end:
        ra_i = fixed - 1  # the two cells: (ra_i, ra_j) on the low side, (rb_i, rb_j) on the high side
        ra_j = p
        rb_i = fixed
        rb_j = p
        if vertical != 0:
            ra_i = p
            ra_j = fixed - 1
            rb_i = p
            rb_j = fixed
        fa = _find(ra_i, ra_j, m, st.morton_i, st.morton_j, link)
        fb = _find(rb_i, rb_j, m, st.morton_i, st.morton_j, link)
        sa = _steps(ra_i, ra_j, fa, m, mid, st.ch, st.cw, g, st.logpos, st.u)
        sb = _steps(rb_i, rb_j, fb, m, mid, st.ch, st.cw, g, st.logpos, st.u)
        steps = steps + sa + sb
        max_steps = wp.max(max_steps, wp.max(sa, sb))
        a = fa[1]
        b = fb[1]
        at = _log(a, mid, at, g, st.logpos, st.u)
        at = _log(b, mid, at, g, st.logpos, st.u)
        ra = g[a].rect
        rb = g[b].rect
        ea = ra[k0 + 1]
        eb = rb[k0 + 1]
        fla = g[a].flags
        flb = g[b].flags
        tests = tests + 1
        ok = int(0)
        if ra[k0] == rb[k0] and ea == eb:
            ga = g[a].grad
            gb = g[b].grad
            d = wp.abs(ga[0] - gb[0]) + wp.abs(ga[1] - gb[1])
            if d <= tol:
                un = wp.vec4i(ra[0], rb[1], ra[2], rb[3])  # a is on the low side of the border
                g[a].rect = un
                g[a].grad = _grads(h, un)
                link[b] = (a << _LEVEL_BITS) | m
                # the union keeps the failures of its outer sides (the shared side is gone)
                if vertical != 0:
                    g[a].flags = (fla & 13) | (flb & 14)
                else:
                    g[a].flags = (fla & 7) | (flb & 11)
                merges = merges + 1
                ok = 1
            else:
                sfail = sfail + 1
                thr = wp.min(thr, d)
        else:
            bfail = bfail + 1
        if ok == 0:
            if vertical != 0:
                g[a].flags = fla | 2
                g[b].flags = flb | 1
            else:
                g[a].flags = fla | 8
                g[b].flags = flb | 4
        p = wp.min(ea, eb)
    st.nodes[node].sub = thr
    st.nodes[node].tests = st.nodes[node].tests + tests
    st.nodes[node].bfail = st.nodes[node].bfail + bfail
    st.nodes[node].sfail = st.nodes[node].sfail + sfail
    st.nodes[node].merges = st.nodes[node].merges + merges
    st.nodes[node].steps = st.nodes[node].steps + steps
    st.nodes[node].smax = wp.max(st.nodes[node].smax, max_steps)
    return wp.vec2i(merges, at)


@wp.func
def _add_totals(n: _Node, sign: int, part: int, st: _MergeArrays):
    """Add (sign 1) or take out (-1) a node's counters from the pass totals, in row ``part`` (the parallel
    subtree launch's chunk; the totals are the sums over the rows, so a row alone may be negative)."""
    st.totals[part, 0] = st.totals[part, 0] + wp.int64(sign * n.tests)
    st.totals[part, 1] = st.totals[part, 1] + wp.int64(sign * n.bfail)
    st.totals[part, 2] = st.totals[part, 2] + wp.int64(sign * n.sfail)
    st.totals[part, 3] = st.totals[part, 3] + wp.int64(sign * n.merges)
    st.totals[part, 4] = st.totals[part, 4] + wp.int64(sign * n.steps)
    st.hist[part, n.smax] = st.hist[part, n.smax] + sign


@wp.func
def _merge_node(m: int, k: int, tol: float, mid: int, part: int, st: _MergeArrays):
    """Merge node k of level m (m >= 1; its slots hold its sons' polygons) at ``tol``: borders A, B, C of the
    paper's order, then its count, counters (into row ``part``) and smallest failure. ``mid`` is this merge's
    stamp: unique to it (:func:`_stamp_base`)."""
    nodes = st.nodes
    ch = st.ch
    cw = st.cw
    node = st.n_base[m] + k
    at = st.u_base[m] + k * _log_room(m)
    ulog = at
    nd = nodes[node]
    if nd.done != 0:  # its last counters leave the totals
        _add_totals(nd, -1, part, st)
    nodes[node].tests = 0
    nodes[node].bfail = 0
    nodes[node].sfail = 0
    nodes[node].merges = 0
    nodes[node].steps = 0
    nodes[node].smax = 0
    nodes[node].sub = float(wp.inf)
    sons = st.n_base[m - 1] + 4 * k
    count = int(0)
    sub = float(wp.inf)
    for j in range(4):
        son = nodes[sons + j]
        if son.i0 < ch and son.j0 < cw:
            count = count + son.count
            sub = wp.min(sub, son.sub)
    half = 1 << (m - 1)
    i0 = nd.i0
    j0 = nd.j0
    i1 = wp.min(i0 + 2 * half, ch)
    j1 = wp.min(j0 + 2 * half, cw)
    jm = j0 + half
    im = i0 + half
    r = wp.vec2i()
    if jm < cw:
        # border A (son 1 | son 2), then B (son 4 | son 3)
        r = _merge_border(st.h, 1, jm, i0, wp.min(im, i1), tol, m, node, mid, at, st)
        count = count - r[0]
        at = r[1]
        if im < ch:
            r = _merge_border(st.h, 1, jm, im, i1, tol, m, node, mid, at, st)
            count = count - r[0]
            at = r[1]
    if im < ch:
        # border C (sons 1-2 | sons 4-3)
        r = _merge_border(st.h, 0, im, j0, j1, tol, m, node, mid, at, st)
        count = count - r[0]
        at = r[1]
    nodes[node].ulen = at - ulog
    nodes[node].count = count
    nodes[node].sub = wp.min(nodes[node].sub, sub)
    nodes[node].done = 1
    _add_totals(nodes[node], 1, part, st)
    if count == 1:  # a single polygon is its node, without failures (internal check)
        s0 = k << (2 * m)
        q = st.g[s0]
        if q.rect[0] != i0 or q.rect[1] != i1 or q.rect[2] != j0 or q.rect[3] != j1 or q.flags != 0:
            st.error[0] = 1
        if st.link[s0] != -1:
            st.error[0] = 1


@wp.func
def _mark(tol: float, st: _MergeArrays):
    """The nodes to merge at ``tol``, per level: the unfrozen ones whose subtree's smallest failure is <= tol
    (every one of them changes, and every ancestor of one is one), found top-down."""
    n_base = st.n_base
    marks = st.marks
    depth = st.depth
    for m in range(depth + 1):
        st.n_marked[m] = 0
    root = st.nodes[n_base[depth]]
    if depth > 0 and root.frozen == 0 and root.sub <= tol:
        marks[n_base[depth]] = 0
        st.n_marked[depth] = 1
    m = depth
    while m > 1:
        c = int(0)
        for i in range(st.n_marked[m]):
            k = marks[n_base[m] + i]
            for j in range(4):
                son = st.nodes[n_base[m - 1] + 4 * k + j]
                if son.i0 < st.ch and son.j0 < st.cw and son.frozen == 0 and son.sub <= tol:
                    marks[n_base[m - 1] + c] = 4 * k + j
                    c = c + 1
        st.n_marked[m - 1] = c
        m = m - 1


@wp.func
def _undo_node(m: int, k: int, st: _MergeArrays):
    """Undo the last merge of node k of level m: its slots go back to its sons' polygons."""
    g = st.g
    ulog = st.u_base[m] + k * _log_room(m)
    for e in range(ulog, ulog + st.nodes[st.n_base[m] + k].ulen):
        w = st.u[e]
        g[w.slot].rect = w.rect
        g[w.slot].grad = w.grad
        g[w.slot].flags = w.flags
        st.link[w.slot] = -1


@wp.func
def _first_at_least(st: _MergeArrays, m: int, lo_in: int, key: int) -> int:
    """Position of the first mark >= ``key`` in level m's sorted mark list, from position ``lo_in`` on."""
    base = st.n_base[m]
    lo = lo_in
    hi = st.n_marked[m]
    while lo < hi:
        mid = (lo + hi) >> 1
        if st.marks[base + mid] < key:
            lo = mid + 1
        else:
            hi = mid
    return lo


@wp.func
def _run_of(m: int, s: int, split: int, st: _MergeArrays) -> wp.vec2i:
    """The marked nodes of level m (<= split) inside node s of level ``split``: positions [lo, hi) of level m's
    mark list, which is sorted (marks are appended son by son under marked fathers in order); all of them when
    s < 0."""
    if s < 0:
        return wp.vec2i(0, st.n_marked[m])
    lo = _first_at_least(st, m, 0, s << (2 * (split - m)))
    return wp.vec2i(lo, _first_at_least(st, m, lo, (s + 1) << (2 * (split - m))))


@wp.func
def _undo_levels(top: int, bottom: int, s: int, split: int, st: _MergeArrays):
    """Undo the last merges of the marked nodes of levels ``top`` down to ``bottom`` (those inside node s of level
    ``split``, or all with s < 0), top-down (a slot logged at several levels ends as the lowest one logged it)."""
    m = top
    while m >= bottom:
        r = _run_of(m, s, split, st)
        for i in range(r[0], r[1]):
            _undo_node(m, st.marks[st.n_base[m] + i], st)
        m = m - 1


@wp.func
def _stamp_base(m: int, st: _MergeArrays) -> int:
    """Stamp of the merge before the first marked node of level m in this pass: the merges are numbered on from
    every earlier pass's (``counter``), level by level from level 1, each level in mark order, so that the
    one-thread pass and the subtree launches (:func:`_subtree`) give every merge the same stamp."""
    b = st.counter[0]
    for lv in range(1, m):
        b = b + st.n_marked[lv]
    return b


@wp.func
def _merge_levels(lo: int, hi: int, s: int, split: int, tol: float, part: int, st: _MergeArrays):
    """Merge the marked nodes of levels ``lo`` up to ``hi`` (those inside node s of level ``split``, or all with
    s < 0) again, bottom-up, counters into row ``part``."""
    for lv in range(lo, hi + 1):
        r = _run_of(lv, s, split, st)
        b = _stamp_base(lv, st)
        for i in range(r[0], r[1]):
            _merge_node(lv, st.marks[st.n_base[lv] + i], tol, b + i + 1, part, st)


@wp.func
def _subtree(s: int, split: int, tol: float, part: int, st: _MergeArrays):
    """Undo and merge again the marked nodes of levels ``split`` down to 1 inside node s of level ``split``,
    after the levels above were undone: its slots, nodes and undo logs are its own, so subtrees run on
    different threads (counters into row ``part``, stamps as the one-thread pass numbers them)."""
    _undo_levels(split, 1, s, split, st)
    _merge_levels(1, split, s, split, tol, part, st)


@wp.func
def _emit(s: int, at: int, st: _MergeArrays):
    q = st.g[s]
    st.out_rect[at] = q.rect
    st.out_grad[at] = q.grad
    st.out_flags[at] = q.flags


@wp.func
def _emit_root(st: _MergeArrays) -> int:
    """Append the root's polygons in slot order to ``out_*`` from ``out_used[0]``: a scan of the slots, or,
    with few polygons, a descent that stops at nodes holding one; returns how many."""
    base = st.out_used[0]
    n = int(0)
    depth = st.depth
    if 4 * st.nodes[st.n_base[depth]].count >= st.nc or depth == 0:
        for s in range(st.nslots):
            if st.link[s] == -1:
                _emit(s, base + n, st)
                n = n + 1
    else:
        stack = st.stack
        stack[0] = depth  # entries: k << 5 | level
        top = int(1)
        while top > 0:
            top = top - 1
            lv = stack[top] & 31
            k = stack[top] >> 5
            nd = st.nodes[st.n_base[lv] + k]
            if lv == 0 or nd.count == 1:
                s = k << (2 * lv)
                if st.link[s] == -1:
                    _emit(s, base + n, st)
                    n = n + 1
            else:
                for z in range(4):
                    kk = 4 * k + 3 - z  # pushed last to first: popped in slot order
                    sn = st.nodes[st.n_base[lv - 1] + kk]
                    if sn.i0 < st.ch and sn.j0 < st.cw:
                        stack[top] = (kk << 5) | (lv - 1)
                        top = top + 1
    st.out_used[0] = base + n
    return n


@wp.func
def _freeze(st: _MergeArrays):
    """Step j: the nodes merged into one polygon in this pass keep it from the next pass on (and their
    counters leave the totals)."""
    for lv in range(1, st.depth + 1):
        for i in range(st.n_marked[lv]):
            node = st.n_base[lv] + st.marks[st.n_base[lv] + i]
            nd = st.nodes[node]
            if nd.count == 1:
                st.nodes[node].frozen = 1
                st.nodes[node].sub = float(wp.inf)
                _add_totals(nd, -1, 0, st)


@wp.func
def _finish(row: int, st: _MergeArrays):
    """After the merges of pass ``row``: append the root's polygons, write the pass's counters (the sums over
    the part rows), freeze, and number on the stamps past this pass's merges."""
    st.out_count[row] = _emit_root(st)
    parts = st.totals.shape[0]
    for i in range(5):
        acc = wp.int64(0)
        for p in range(parts):
            acc = acc + st.totals[p, i]
        st.out_stats[row, i] = acc
    high = int(0)
    for v in range(st.hist.shape[1]):
        c = int(0)
        for p in range(parts):
            c = c + st.hist[p, v]
        if c > 0:
            high = v
    st.out_stats[row, 5] = wp.int64(high)
    _freeze(st)
    st.counter[0] = _stamp_base(st.depth + 1, st)


# ------------------------------------------------------------------------------------------------
# kernels
# ------------------------------------------------------------------------------------------------


@wp.kernel(enable_backward=False)
def _init_kernel(
    offset: int,
    depth: int,
    ch: int,
    cw: int,
    h: wp.array2d(dtype=wp.float32),
    n_base: wp.array(dtype=wp.int32),
    # outputs
    out_nodes: wp.array(dtype=_Node),
    out_g: wp.array(dtype=_Slot),
    out_link: wp.array(dtype=wp.int32),
):
    """Node ``tid`` (flat index; the cells' nodes are the slots) before any pass: a cell holds one polygon
    and nothing to merge, other nodes were never merged."""
    t = wp.tid() + offset
    m = int(0)
    while t >= n_base[m + 1]:
        m = m + 1
    o = _demorton(t - n_base[m], depth - m)
    n = _Node()
    n.i0 = o[0] << m
    n.j0 = o[1] << m
    n.sub = -wp.inf
    if m == 0:
        n.sub = wp.inf
        q = _Slot()
        out_link[t] = _OUTSIDE
        if n.i0 < ch and n.j0 < cw:
            n.count = 1
            q.rect = wp.vec4i(n.i0, n.i0 + 1, n.j0, n.j0 + 1)
            q.grad = _grads(h, q.rect)
            out_link[t] = -1
        out_g[t] = q
    out_nodes[t] = n


@wp.kernel(enable_backward=False)
def _pass_kernel(st: _MergeArrays, row: int):
    """Pass ``row``, at tolerance ``st.tols[row]``, one thread (the state is ``st``'s arrays, read and
    written): undo the marked nodes' last merges top-down, merge them again bottom-up, append the root's
    polygons to ``st.out_*``, write the pass's counters to ``st.out_stats[row]``, freeze."""
    tol = st.tols[row]
    _mark(tol, st)
    _undo_levels(st.depth, 1, -1, 0, st)
    _merge_levels(1, st.depth, -1, 0, tol, 0, st)
    _finish(row, st)


@wp.kernel(enable_backward=False)
def _mark_top_kernel(st: _MergeArrays, row: int, split: int):
    """Pass ``row`` split across threads, first launch (one thread): mark, and undo the levels above ``split``."""
    _mark(st.tols[row], st)
    _undo_levels(st.depth, split + 1, -1, 0, st)


@wp.kernel(enable_backward=False)
def _subtree_kernel(offset: int, part: int, st: _MergeArrays, row: int, split: int):
    """Second launch, one item per node of level ``split`` (:func:`_subtree`), split across threads."""
    _subtree(wp.tid() + offset, split, st.tols[row], part, st)


@wp.kernel(enable_backward=False)
def _top_finish_kernel(st: _MergeArrays, row: int, split: int, rest: int):
    """Third launch (one thread): merge the levels above ``split`` again, then :func:`_finish`. With ``rest``
    = 1 instead of the subtree launch (a pass that merges few nodes): undo levels ``split`` to 1 and merge every
    level again."""
    lo = split + 1
    if rest != 0:
        _undo_levels(split, 1, -1, 0, st)
        lo = 1
    _merge_levels(lo, st.depth, -1, 0, st.tols[row], 0, st)
    _finish(row, st)


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
    """The quadtree of the paper and the merge state of every node, reused across tolerances (ascending).

    ``arrays`` (a ``_MergeArrays``) holds every array the pass kernel reads and writes: ``g`` and ``link``,
    one ``_Slot`` and link per cell of the padded N x N grid by Morton code, ``nodes``, one ``_Node`` per
    quadtree node (flat index ``node_base[l] + k``), and ``u``, the nodes' undo logs.

    Attributes:
        depth: quadtree depth (N = 2^depth cells a side).
        n_nodes: nodes per level, level 0 (cells) .. depth (root).
        node_base: (depth+2,) int64 offsets of each level in the flat per-node arrays.
    """

    OUT_ROWS = 1 << 23  # output rows held at once on the CPU (untouched rows cost address space only)
    # A pass that merges at least this many nodes at the subtree levels runs them on every thread (CPU, depth >= 4):
    # one launch marks and undoes the top levels, one undoes and merges the 4^SPLIT_BELOW subtrees below them, in
    # parallel, one merges the top levels and emits. Smaller passes run in one thread (two launches).
    PARALLEL_MIN_NODES = 1024
    SPLIT_BELOW = 3  # the subtrees are the nodes this many levels below the root
    PARTS = 4 ** SPLIT_BELOW  # counter rows: one per subtree at most, so enough for the subtree launch's chunks

    def __init__(self, heights: np.ndarray, device: str = "cpu"):
        hh, ww = heights.shape
        self.ch, self.cw = hh - 1, ww - 1
        self.ncells = self.ch * self.cw
        n = max(self.ch, self.cw)
        self.depth = d = int(max(0, int(np.ceil(np.log2(n))))) if n > 1 else 0
        self.n_nodes = [4 ** (d - m) for m in range(d + 1)]
        nb = np.zeros(d + 2, np.int64)
        nb[1:] = np.cumsum(self.n_nodes)
        self.node_base = nb
        self.device = device
        total, ns = int(nb[-1]), self.n_nodes[0]
        u_base = np.zeros(d + 2, np.int64)
        u_base[2:] = np.cumsum([c * min(4 ** m, 2 ** (m + 2)) for m, c in enumerate(self.n_nodes) if m > 0])
        if max(u_base[-1], total) >= 2 ** 31 or ns > 2 ** (31 - 5):  # links hold slot << 5
            raise ValueError(f"heightmap: {hh} x {ww} samples is too large for the polytree's int32 indices")

        def arr(a, dtype):
            return wp.array(a, dtype=dtype, device=device)

        def zeros(n, dtype):
            return wp.zeros(max(int(n), 1), dtype=dtype, device=device)

        def empty(n, dtype):  # written before it is read
            return wp.empty(max(int(n), 1), dtype=dtype, device=device)

        a = _MergeArrays()
        a.h = arr(np.ascontiguousarray(heights, np.float32), wp.float32)
        a.tols = zeros(1, wp.float32)
        a.n_base, a.u_base = arr(nb.astype(np.int32), wp.int32), arr(u_base[:-1].astype(np.int32), wp.int32)
        a.morton_i = arr((_spread(np.arange(max(self.ch, 1))) << 1).astype(np.int32), wp.int32)
        a.morton_j = arr(_spread(np.arange(max(self.cw, 1))).astype(np.int32), wp.int32)
        a.nodes, a.g, a.link, a.logpos = empty(total, _Node), empty(ns, _Slot), empty(ns, wp.int32), empty(ns, wp.int32)
        a.u = empty(u_base[-1], _Undo)
        a.marks, a.n_marked, a.stack = empty(total, wp.int32), zeros(d + 1, wp.int32), empty(3 * d + 4, wp.int32)
        # a search takes <= 2 * depth + 1 steps (the histogram's bins)
        a.totals = wp.zeros((self.PARTS, 5), dtype=wp.int64, device=device)
        a.hist = wp.zeros((self.PARTS, 2 * d + 8), dtype=wp.int32, device=device)
        a.counter, a.error, a.out_used = zeros(1, wp.int32), zeros(1, wp.int32), zeros(1, wp.int32)
        a.out_count, a.out_stats = zeros(1, wp.int32), wp.zeros((1, 6), dtype=wp.int64, device=device)
        a.depth, a.ch, a.cw, a.nc, a.nslots = d, self.ch, self.cw, self.ncells, ns
        launch(_init_kernel, total, inputs=[d, self.ch, self.cw, a.h, a.n_base], outputs=[a.nodes, a.g, a.link],
               device=device)
        self.arrays = a
        self._used = a.out_used.numpy() if device == "cpu" else None  # on the CPU a view: read after each pass
        self._marked = a.n_marked.numpy() if device == "cpu" else None  # likewise, read after marking
        self._pending = np.zeros(6, np.int64)

    def run_passes(self, tolerances, stop_at_one: bool = False) -> tuple[np.ndarray, ...]:
        """Merge at each tolerance (ascending, metres), stopping after the first pass whose root holds one
        polygon when ``stop_at_one``. One launch a pass (each pass is timed).

        Returns:
            rects (P, 4) int32, grads (P, 2) float32, flags (P,) int32: every pass's root polygons one after
            the other, each pass in the paper's order; counts (T,) int64 polygons per pass; stats (T, 6)
            int64 per pass (STAT_*); ms (T,) float64 wall time per pass.
        """
        tol = np.asarray(tolerances, np.float64).reshape(-1)
        a, dev, nc = self.arrays, self.device, max(self.ncells, 1)
        t_n = len(tol)
        if t_n:
            a.tols = wp.array(tol.astype(np.float32), dtype=wp.float32, device=dev)
        a.out_count = wp.zeros(max(t_n, 1), dtype=wp.int32, device=dev)
        a.out_stats = wp.zeros((max(t_n, 1), 6), dtype=wp.int64, device=dev)
        # room for every pass at once where that is cheap (CPU pages are touched only when written)
        rows = nc * max(2, min(t_n, self.OUT_ROWS // nc)) if dev == "cpu" else 2 * nc
        self._new_out(rows)
        split = self.depth - self.SPLIT_BELOW
        split_up = self._marked is not None and threads() > 1 and split >= 1
        if split_up:
            cmds = [record(_mark_top_kernel, dim=1, inputs=[a, 0, split], device=dev),
                    record(_top_finish_kernel, dim=1, inputs=[a, 0, split, 0], device=dev)]
        else:
            cmds = [record(_pass_kernel, dim=1, inputs=[a, 0], device=dev)]
        chunks, ms = [], []
        used = 0
        for t in range(t_n):
            if used + nc > rows:  # a pass writes at most one row a cell
                chunks.append(self._take(used))
                self._new_out(rows)
                for cmd in cmds:
                    cmd.set_param_at_index(0, a)
                used = 0
            t0 = time.perf_counter()
            for cmd in cmds:
                cmd.set_param_at_index(1, t)
            if split_up:
                self._split_pass(cmds, t, split)
            else:
                replay(cmds[0])
            new = int(self._used[0]) if self._used is not None else int(a.out_used.numpy()[0])
            ms.append((time.perf_counter() - t0) * 1e3)
            last, used = new - used, new
            if stop_at_one and last == 1:
                break
        if int(a.error.numpy()[0]):
            raise RuntimeError("polytree merge: a single polygon is not its node's rectangle")  # an internal error
        chunks.append(self._take(used))
        done = len(ms)
        rects, grads, flags = (np.concatenate([c[q] for c in chunks]) if len(chunks) > 1 else chunks[0][q]
                               for q in range(3))
        return (rects, grads, flags, a.out_count.numpy()[:done].astype(np.int64), a.out_stats.numpy()[:done].copy(),
                np.asarray(ms, np.float64))

    def _split_pass(self, cmds, t: int, split: int) -> None:
        """Pass t on every thread when it merges enough nodes at the subtree levels, else in one."""
        mark, finish = cmds
        replay(mark)
        parallel = int(self._marked[1:split + 1].sum()) >= self.PARALLEL_MIN_NODES
        if parallel:
            launch(_subtree_kernel, 4 ** self.SPLIT_BELOW, [self.arrays, t, split], device=self.device, parts=True,
                   min_items=1, oversplit=4)  # subtrees differ in how many of their nodes a pass merges
        finish.set_param_at_index(3, 0 if parallel else 1)
        replay(finish)

    def run_pass(self, tol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Merge at ``tol`` (not below the last tolerance); returns the root's polygons: rects (P, 4) int32
        (i0, i1, j0, j1), gradients (P, 2) float32 (Xgr, Ygr), flags (P,) int32. Its counters add to
        :meth:`take_stats`."""
        rects, grads, flags, _, stats, _ = self.run_passes([tol])
        self._pending[:STAT_FIND_MAX] += stats[0, :STAT_FIND_MAX]
        self._pending[STAT_FIND_MAX] = max(self._pending[STAT_FIND_MAX], stats[0, STAT_FIND_MAX])
        return rects, grads, flags

    def take_stats(self) -> np.ndarray:
        """(6,) int64 counters of the passes of :meth:`run_pass` since the last call (STAT_*)."""
        s = self._pending.copy()
        self._pending[:] = 0
        return s

    def level(self, m: int) -> tuple[np.ndarray, np.ndarray]:
        """The tiling of quadtree level m as each node's last merge left it (the polytree's level m): rects
        (P, 4) int32 in the paper's order and father (P,) int64, the index in level m+1's rects of the
        polygon each one is part of (-1 at the root). For inspection: undoes the higher levels' merges on a
        host copy."""
        m = check_int("m", m, 0, self.depth)
        a = self.arrays
        nb, nodes, u = self.node_base, a.nodes.numpy(), a.u.numpy()
        u_base = a.u_base.numpy()
        rect, alive = a.g.numpy()["rect"].copy(), a.link.numpy() == -1
        tiling = {self.depth: rect[alive]}
        for lv in range(self.depth, m, -1):
            room = min(4 ** lv, 2 ** (lv + 2))
            for k in range(self.n_nodes[lv]):
                e = u[u_base[lv] + k * room:][:nodes["ulen"][nb[lv] + k]]
                rect[e["slot"]], alive[e["slot"]] = e["rect"], True
            tiling[lv - 1] = rect[alive]
        rects = tiling[m].reshape(-1, 4).astype(np.int32)
        if m == self.depth:
            return rects, np.full(len(rects), -1, np.int64)
        label, _ = paint(tiling[m + 1], (self.ch, self.cw), device="cpu")
        return rects, label[rects[:, 0], rects[:, 2]].astype(np.int64)

    def _new_out(self, rows: int) -> None:
        a, dev = self.arrays, self.device
        a.out_rect = wp.empty(rows, dtype=wp.vec4i, device=dev)
        a.out_grad = wp.empty(rows, dtype=wp.vec2, device=dev)
        a.out_flags = wp.empty(rows, dtype=wp.int32, device=dev)
        a.out_used.zero_()

    def _take(self, used: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The first ``used`` output rows as host arrays (views on the CPU: those rows are not written again)."""
        a = self.arrays
        return (a.out_rect.numpy()[:used].reshape(used, 4), a.out_grad.numpy()[:used].reshape(used, 2),
                a.out_flags.numpy()[:used].reshape(used))


def _spread(v: np.ndarray) -> np.ndarray:
    """Bits of v (< 2^31) spread to the even bit positions (Morton interleave)."""
    v = np.asarray(v, np.int64)
    out = np.zeros_like(v)
    b = 0
    while (v >> b).any():
        out |= ((v >> b) & 1) << (2 * b)
        b += 1
    return out


def paint(rects: np.ndarray, shape_cells: tuple[int, int], device: str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """Label map (ch, cw) int32 (polygon index per cell, -1 where none) and hit counts (ch, cw) int32."""
    ch, cw = shape_cells
    label = wp.full((ch, cw), value=-1, dtype=wp.int32, device=device)
    hits = wp.zeros((ch, cw), dtype=wp.int32, device=device)
    if len(rects):
        r = wp.array(np.ascontiguousarray(rects, np.int32), dtype=wp.vec4i, device=device)
        launch_one(_paint_kernel, dim=len(rects), inputs=[r], outputs=[label, hits], device=device)
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
    launch_one(_tri_count_kernel, dim=p, inputs=[lab, r, ww], outputs=[count, used], device=device)
    off = wp.empty(p + 1, dtype=wp.int32, device=device)
    scan(count, off, inclusive=False)
    remap = wp.empty(hh * ww + 1, dtype=wp.int32, device=device)
    scan(used, remap, inclusive=False)
    m = int(off.numpy()[p])
    tri = wp.zeros((max(m, 1), 3), dtype=wp.int32, device=device)
    launch_one(_tri_emit_kernel, dim=p, inputs=[h, lab, r, off, remap, float(dx), float(dz)], outputs=[tri],
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
    launch_one(_morph_target_kernel, dim=n, inputs=[s, lab, r], outputs=[out], device=device)
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
        launch_one(_morph_positions_kernel, dim=n, inputs=[h, a, b, float(s), float(dx), float(dz),
                                                           wp.vec3(*rel_origin)], outputs=[out], device=device)
    return out.numpy()[:n].reshape(n, 3)


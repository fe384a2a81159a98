"""Right-triangle bisection tree (MRBSP, mrbsp-lod-visibility.txt sections 2-3) on the device.

The tree is stored as a heap: node ``g`` at level ``L`` (``2**L - 1 <= g < 2**(L+1) - 1``) has children
``2g + 1`` and ``2g + 2``; node 0 is the root square, level 1 its two triangles. A triangle is three
vertex ids ``(apex, b0, b1)`` on an integer grid of ``(G + 1) x (G + 1)`` points (id ``gz * (G + 1) +
gx``), the apex is the right angle and ``(apex, b0, b1)`` is counter-clockwise seen from above (+y).
Splitting from the apex to the hypotenuse midpoint ``c`` gives ``(c, apex, b0)`` and ``(c, b1, apex)``,
both counter-clockwise again.

Build kernels, one launch per level (never a loop over nodes):

* vertex heights: per grid point, from the heightmap by the paper's "three closest samples" (the
  plane through the three of the four surrounding samples nearest to the point; the farthest is
  dropped, ties broken in the fixed order (1,1), (0,0), (0,1), (1,0)) or bilinear; clamp to edge.
* split: the children of every node of a level.
* links: the base neighbour (the node of the same level sharing the hypotenuse, -1 on the border)
  through a dense map keyed by the hypotenuse midpoint and direction.
* bounds: per node min/max height of its subtree, bottom-up.

Selection, per frame, is one launch of one thread (:class:`Walk`): a ground view touches a few
thousand of a 65,536-triangle tree's 131,071 nodes, where launches per level and per propagation pass
visit all of them (issue 19: 8.7 ms a frame on the bench path, about 30 launches; the walk is well under
1 ms). It is sequential, so it does not go through the parallel-launch helper; on a GPU the per-level
passes (kept as the reference in tests/lod/test_bintree.py) are the shape to launch. The walk:
breadth-first from the root, the cull and split decisions of the children of split nodes, with
per-vertex LOD thresholds ``ceil(M - log2(D / S))`` clamped to [1, M] worked out on first use; the
forced-split propagation (ROAM: a split node's base neighbour is split too) as the same sequential
passes, visiting only the nodes each pass can change; the leaves in heap order by a second
breadth-first pass; the mesh with its vertices compacted in id order.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .checks import check_choice
from .parallel import launch_one, record, replay
from .sampling import sample_bilinear

# ------------------------------------------------------------------------------------------------
# functions
# ------------------------------------------------------------------------------------------------

HEIGHT_METHODS = {"nearest3": 0, "bilinear": 1}


@wp.func
def _fetch(h: wp.array2d(dtype=wp.float32), i: int, j: int) -> float:
    return h[wp.clamp(i, 0, h.shape[0] - 1), wp.clamp(j, 0, h.shape[1] - 1)]


@wp.func
def _nearest3(h: wp.array2d(dtype=wp.float32), u: float, v: float) -> float:
    """Plane through the three of the four samples around (u, v) closest to it (clamped to the grid)."""
    uc = wp.clamp(u, 0.0, float(h.shape[1] - 1))
    vc = wp.clamp(v, 0.0, float(h.shape[0] - 1))
    j0 = wp.clamp(int(wp.floor(uc)), 0, wp.max(h.shape[1] - 2, 0))
    i0 = wp.clamp(int(wp.floor(vc)), 0, wp.max(h.shape[0] - 2, 0))
    fu = uc - float(j0)
    fv = vc - float(i0)
    h00 = _fetch(h, i0, j0)
    h10 = _fetch(h, i0, j0 + 1)  # (u+1, v)
    h01 = _fetch(h, i0 + 1, j0)  # (u, v+1)
    h11 = _fetch(h, i0 + 1, j0 + 1)
    r = float(0.0)
    if fu <= 0.5 and fv <= 0.5:  # (1,1) farthest
        r = h00 + fu * (h10 - h00) + fv * (h01 - h00)
    elif fu >= 0.5 and fv >= 0.5:  # (0,0) farthest
        r = h11 + (1.0 - fu) * (h01 - h11) + (1.0 - fv) * (h10 - h11)
    elif fu >= 0.5:  # (0,1) farthest: triangle (0,0), (1,0), (1,1)
        r = h00 + fu * (h10 - h00) + fv * (h11 - h10)
    else:  # (1,0) farthest: triangle (0,0), (0,1), (1,1)
        r = h00 + fv * (h01 - h00) + fu * (h11 - h01)
    return r


# ------------------------------------------------------------------------------------------------
# kernels: build
# ------------------------------------------------------------------------------------------------


@wp.kernel(enable_backward=False)
def _heights_kernel(h: wp.array2d(dtype=wp.float32), g1: int, x0: float, z0: float, step: float, ox: float,
                    oz: float, dx: float, dz: float, method: int,
                    # outputs
                    out_h: wp.array(dtype=wp.float32)):
    t = wp.tid()
    gz = t / g1
    gx = t - gz * g1
    u = (x0 + float(gx) * step - ox) / dx
    v = (z0 + float(gz) * step - oz) / dz
    if method == 0:
        out_h[t] = _nearest3(h, u, v)
    else:
        out_h[t] = sample_bilinear(h, u, v)


@wp.kernel(enable_backward=False)
def _split_kernel(off: int, g1: int,
                  # outputs (read at level L, written at level L + 1)
                  out_apex: wp.array(dtype=wp.int32), out_b0: wp.array(dtype=wp.int32),
                  out_b1: wp.array(dtype=wp.int32)):
    k = wp.tid()
    g = off + k
    a = out_apex[g]
    p = out_b0[g]
    q = out_b1[g]
    pz = p / g1
    qz = q / g1
    cx = (p - pz * g1 + q - qz * g1) / 2
    cz = (pz + qz) / 2
    c = cz * g1 + cx
    l = 2 * g + 1
    out_apex[l] = c
    out_b0[l] = a
    out_b1[l] = p
    out_apex[l + 1] = c
    out_b0[l + 1] = q
    out_b1[l + 1] = a


@wp.func
def _mid_slot(p: int, q: int, g1: int) -> int:
    pz = p / g1
    qz = q / g1
    c = ((pz + qz) / 2) * g1 + (p - pz * g1 + q - qz * g1) / 2
    s = int(0)
    if p > q:
        s = 1
    return 2 * c + s


@wp.kernel(enable_backward=False)
def _link_write_kernel(off: int, g1: int, b0: wp.array(dtype=wp.int32), b1: wp.array(dtype=wp.int32),
                       # outputs
                       out_map: wp.array(dtype=wp.int32)):
    g = off + wp.tid()
    out_map[_mid_slot(b0[g], b1[g], g1)] = g


@wp.kernel(enable_backward=False)
def _link_read_kernel(off: int, g1: int, b0: wp.array(dtype=wp.int32), b1: wp.array(dtype=wp.int32),
                      slots: wp.array(dtype=wp.int32),
                      # outputs
                      out_bn: wp.array(dtype=wp.int32)):
    g = off + wp.tid()
    out_bn[g] = slots[_mid_slot(b1[g], b0[g], g1)]  # the same edge traversed the other way


@wp.kernel(enable_backward=False)
def _bounds_leaf_kernel(off: int, apex: wp.array(dtype=wp.int32), b0: wp.array(dtype=wp.int32),
                        b1: wp.array(dtype=wp.int32), vh: wp.array(dtype=wp.float32),
                        # outputs
                        out_lo: wp.array(dtype=wp.float32), out_hi: wp.array(dtype=wp.float32)):
    g = off + wp.tid()
    ha = vh[apex[g]]
    h0 = vh[b0[g]]
    h1 = vh[b1[g]]
    out_lo[g] = wp.min(ha, wp.min(h0, h1))
    out_hi[g] = wp.max(ha, wp.max(h0, h1))


@wp.kernel(enable_backward=False)
def _bounds_up_kernel(off: int,
                      # outputs (children read, parents written)
                      out_lo: wp.array(dtype=wp.float32), out_hi: wp.array(dtype=wp.float32)):
    g = off + wp.tid()
    out_lo[g] = wp.min(out_lo[2 * g + 1], out_lo[2 * g + 2])
    out_hi[g] = wp.max(out_hi[2 * g + 1], out_hi[2 * g + 2])


# ------------------------------------------------------------------------------------------------
# kernels: selection (one walk per frame)
# ------------------------------------------------------------------------------------------------

# per-node flags in the walk's scratch
_SPLIT = wp.constant(1)
_DECIDED = wp.constant(2)  # culling decided for this node
_CULLED = wp.constant(4)


@wp.struct
class _Frame:
    """What one frame's walk reads: the tree (heap-indexed arrays) and the observer."""

    apex: wp.array(dtype=wp.int32)
    b0: wp.array(dtype=wp.int32)
    b1: wp.array(dtype=wp.int32)
    bn: wp.array(dtype=wp.int32)
    lo: wp.array(dtype=wp.float32)
    hi: wp.array(dtype=wp.float32)
    vh: wp.array(dtype=wp.float32)
    planes: wp.array(dtype=wp.vec4)
    vis: wp.array(dtype=wp.uint8)
    g1: int
    max_level: int
    mode: int
    hole_fix: int
    propagate: int
    use_frustum: int
    use_vis: int
    rx0: float
    rz0: float
    step: float
    eye_y: float
    inv_s: float


@wp.func
def _threshold(f: _Frame, t: int) -> int:
    """The paper's LOD threshold ``ceil(M - log2(D / S))`` clamped to [1, M] of grid vertex t."""
    gz = t / f.g1
    gx = t - gz * f.g1
    d = wp.length(wp.vec3(f.rx0 + float(gx) * f.step, f.vh[t] - f.eye_y, f.rz0 + float(gz) * f.step))
    r = f.max_level
    x = d * f.inv_s
    if x > 1.0:  # M - log2(D / S) < M
        r = int(wp.ceil(float(f.max_level) - wp.log2(x)))
    return wp.clamp(r, 1, f.max_level)


@wp.func
def _cached_threshold(f: _Frame, t: int, cache: wp.array(dtype=wp.uint8)) -> int:
    """:func:`_threshold`, computed once per vertex and frame (thresholds are >= 1, so 0 = not yet)."""
    r = int(cache[t])
    if r == 0:
        r = _threshold(f, t)
        cache[t] = wp.uint8(r)
    return r


@wp.func
def _outside(f: _Frame, g: int) -> int:
    """1 when node g's own box (triangle footprint x subtree heights) is outside the frustum or the
    visibility table hides it."""
    c = int(0)
    if f.use_frustum != 0:
        g1 = f.g1
        a = f.apex[g]
        p = f.b0[g]
        q = f.b1[g]
        az = a / g1
        pz = p / g1
        qz = q / g1
        ax = a - az * g1
        px = p - pz * g1
        qx = q - qz * g1
        xmin = f.rx0 + float(wp.min(ax, wp.min(px, qx))) * f.step
        xmax = f.rx0 + float(wp.max(ax, wp.max(px, qx))) * f.step
        zmin = f.rz0 + float(wp.min(az, wp.min(pz, qz))) * f.step
        zmax = f.rz0 + float(wp.max(az, wp.max(pz, qz))) * f.step
        ymin = f.lo[g] - f.eye_y
        ymax = f.hi[g] - f.eye_y
        for i in range(6):
            pl = f.planes[i]
            vx = wp.where(pl[0] > 0.0, xmax, xmin)
            vy = wp.where(pl[1] > 0.0, ymax, ymin)
            vz = wp.where(pl[2] > 0.0, zmax, zmin)
            if pl[0] * vx + pl[1] * vy + pl[2] * vz + pl[3] < 0.0:
                c = 1
    if c == 0 and f.use_vis != 0:
        if f.vis[g] == wp.uint8(0):
            c = 1
    return c


@wp.func
def _culled(f: _Frame, g: int, flags: wp.array(dtype=wp.uint8)) -> int:
    """Nonzero when node g or an ancestor is culled. Decides (and stores) it for g and its undecided
    ancestors top down, testing a node only below a kept parent, as a level-by-level pass would; the
    root is decided (kept) before the walk starts."""
    k = int(0)  # levels up from g to its nearest decided ancestor (or g itself)
    a = g
    while (int(flags[a]) & _DECIDED) == 0:
        a = (a - 1) / 2
        k += 1
    c = int(flags[a]) & _CULLED
    while k > 0:
        k -= 1
        a = ((g + 1) >> k) - 1  # g's ancestor k levels up
        if c == 0:
            c = _outside(f, a) * _CULLED
        flags[a] = wp.uint8(int(flags[a]) | _DECIDED | c)
    return c


@wp.func
def _wants_split(f: _Frame, g: int, level: int, cache: wp.array(dtype=wp.uint8)) -> int:
    """The selection rule for a kept node whose parent is split: brute force splits to depth M; the
    LOD rule splits above the smallest vertex threshold, and the paper's hole fix splits once more
    when the right-angle vertex alone has the lowest threshold."""
    s = int(0)
    if level < f.max_level:
        if f.mode == 0:
            s = 1
        else:
            ta = _cached_threshold(f, f.apex[g], cache)
            t0 = _cached_threshold(f, f.b0[g], cache)
            t1 = _cached_threshold(f, f.b1[g], cache)
            if level < wp.min(ta, wp.min(t0, t1)):
                s = 1
            elif f.hole_fix != 0 and ta < t0 and ta < t1:
                s = 1
    return s


@wp.func
def _is_split(flags: wp.array(dtype=wp.uint8), g: int) -> int:
    return int(flags[g]) & _SPLIT


@wp.func
def _set_split(flags: wp.array(dtype=wp.uint8), g: int):
    flags[g] = wp.uint8(int(flags[g]) | _SPLIT)


@wp.func
def _heap_push(h: wp.array(dtype=wp.int32), size: int, v: int) -> int:
    """Push v on the binary min-heap h[:size]; returns the new size."""
    i = int(size)
    go = int(1)
    while go != 0 and i > 0:
        p = (i - 1) / 2
        if h[p] <= v:
            go = 0
        else:
            h[i] = h[p]
            i = p
    h[i] = v
    return size + 1


@wp.func
def _heap_pop(h: wp.array(dtype=wp.int32), size: int) -> int:
    """Remove the minimum h[0] from the binary min-heap h[:size] (size > 0); returns the new size."""
    n = size - 1
    v = h[n]
    i = int(0)
    go = int(1)
    while go != 0:
        c = 2 * i + 1
        if c >= n:
            go = 0
        else:
            if c + 1 < n and h[c + 1] < h[c]:
                c = c + 1
            if v <= h[c]:
                go = 0
            else:
                h[i] = h[c]
                i = c
    if n > 0:
        h[i] = v
    return n


@wp.func
def _select(f: _Frame, flags: wp.array(dtype=wp.uint8), cache: wp.array(dtype=wp.uint8),
            queue: wp.array(dtype=wp.int32), out_split: wp.array(dtype=wp.int32)) -> int:
    """Breadth-first from the root through split nodes: decide culling and splitting of every child
    of a split node. A FIFO over a complete binary tree visits nodes in heap order, so the split nodes
    come out ascending (a valid min-heap). Returns their count."""
    queue[0] = 1
    queue[1] = 2
    head = int(0)
    tail = int(2)
    count = int(0)
    level = int(1)
    level_end = int(3)  # heap indices of level L end at 2**(L+1) - 1
    while head < tail:
        g = queue[head]
        head += 1
        while g >= level_end:
            level += 1
            level_end = 2 * level_end + 1
        if _culled(f, g, flags) == 0:
            if _wants_split(f, g, level, cache) != 0:
                _set_split(flags, g)
                out_split[count] = g
                count += 1
                queue[tail] = 2 * g + 1
                queue[tail + 1] = 2 * g + 2
                tail += 2
    return count


@wp.func
def _propagate(f: _Frame, flags: wp.array(dtype=wp.uint8), heap: wp.array(dtype=wp.int32), n_split: int,
               later: wp.array(dtype=wp.int32)) -> wp.vec2i:
    """ROAM's forced split propagation, node for node the sequential passes "for every split node g in
    heap order: split its base neighbour n (and n's ancestors) if n is not split" until a pass changes
    nothing. Only nodes split by a pass need the next one: a node a pass has met keeps its neighbour
    split for good, and base neighbours are mutual, so a node split as g's neighbour has g, split, as
    its own. That leaves the ancestors split on the way (``later``), all behind g, so next pass's. In a
    pass, order matters (an ancestor split for one node may be another's neighbour, which is then not
    counted as forced): the heap gives heap order. Returns (forced splits, passes)."""
    size = int(n_split)
    forced = int(0)
    passes = int(0)
    go = int(1)
    while go != 0:
        passes += 1
        changed = int(0)
        n_later = int(0)
        while size > 0:
            g = heap[0]
            size = _heap_pop(heap, size)
            n = f.bn[g]
            if n >= 0:
                if _is_split(flags, n) == 0:
                    changed += 1
                    _set_split(flags, n)
                    a = (n - 1) / 2  # its ancestors too: the split nodes stay a tree
                    while _is_split(flags, a) == 0:
                        _set_split(flags, a)
                        later[n_later] = a
                        n_later += 1
                        a = (a - 1) / 2
        forced += changed
        if changed == 0:
            go = 0
        for i in range(n_later):
            size = _heap_push(heap, size, later[i])
    return wp.vec2i(forced, passes)


@wp.func
def _emit_leaves(f: _Frame, flags: wp.array(dtype=wp.uint8), queue: wp.array(dtype=wp.int32),
                 out_node: wp.array(dtype=wp.int32), out_tri: wp.array(dtype=wp.int32),
                 out_used: wp.array(dtype=wp.int32), out_grid: wp.array(dtype=wp.int32)) -> wp.vec3i:
    """The kept children of split nodes that are not split, in heap order (breadth-first again), with
    their grid vertex ids; marks the vertices used and lists them in out_grid as first met. Returns
    (triangles, nodes visited (queue[:visited]), distinct vertices)."""
    queue[0] = 1
    queue[1] = 2
    head = int(0)
    tail = int(2)
    count = int(0)
    nv = int(0)
    while head < tail:
        g = queue[head]
        head += 1
        if _is_split(flags, g) != 0:
            queue[tail] = 2 * g + 1
            queue[tail + 1] = 2 * g + 2
            tail += 2
        elif _culled(f, g, flags) == 0:
            out_node[count] = g
            out_tri[3 * count + 0] = f.apex[g]
            out_tri[3 * count + 1] = f.b0[g]
            out_tri[3 * count + 2] = f.b1[g]
            count += 1
            for k in range(3):
                v = out_tri[3 * count - 3 + k]
                if out_used[v] == 0:
                    out_used[v] = 1
                    out_grid[nv] = v
                    nv += 1
    return wp.vec3i(count, tail, nv)


@wp.func
def _emit_vertices(f: _Frame, count: int, nv: int, heap: wp.array(dtype=wp.int32),
                   out_tri: wp.array(dtype=wp.int32), out_used: wp.array(dtype=wp.int32),
                   out_pos: wp.array(dtype=wp.vec3), out_grid: wp.array(dtype=wp.int32)):
    """Put the used grid vertices in id order (few: a heap sort of the list; many: a scan of the
    marks over the whole grid), emit their camera-relative positions, point the triangles at them and
    clear the marks."""
    n_grid = f.g1 * f.g1
    if 32 * nv < n_grid:
        size = int(0)
        for i in range(nv):
            size = _heap_push(heap, size, out_grid[i])
        for i in range(nv):
            out_grid[i] = heap[0]
            size = _heap_pop(heap, size)
    else:
        i = int(0)
        for t in range(n_grid):
            if out_used[t] != 0:
                out_grid[i] = t
                i += 1
    for i in range(nv):
        t = out_grid[i]
        gz = t / f.g1
        gx = t - gz * f.g1
        out_pos[i] = wp.vec3(f.rx0 + float(gx) * f.step, f.vh[t] - f.eye_y, f.rz0 + float(gz) * f.step)
        out_used[t] = i
    for i in range(3 * count):
        out_tri[i] = out_used[out_tri[i]]
    for i in range(nv):
        out_used[out_grid[i]] = 0


@wp.kernel(enable_backward=False)
def _walk_kernel(f: _Frame,
                 # scratch, zero before and after: flags (n_nodes,), cache ((G+1)**2,); any: queue (n_nodes,),
                 # heap (max(n_nodes, (G+1)**2),), later (n_nodes,)
                 flags: wp.array(dtype=wp.uint8), cache: wp.array(dtype=wp.uint8), queue: wp.array(dtype=wp.int32),
                 heap: wp.array(dtype=wp.int32), later: wp.array(dtype=wp.int32),
                 # outputs (out_used: zero before and after)
                 out_node: wp.array(dtype=wp.int32), out_tri: wp.array(dtype=wp.int32),
                 out_used: wp.array(dtype=wp.int32), out_pos: wp.array(dtype=wp.vec3),
                 out_grid: wp.array(dtype=wp.int32), out_counts: wp.array(dtype=wp.int32)):
    flags[0] = wp.uint8(_SPLIT | _DECIDED)  # the root square: always split, never culled
    n_split = _select(f, flags, cache, queue, heap)
    r = wp.vec2i(0, 0)
    if f.propagate != 0:
        r = _propagate(f, flags, heap, n_split, later)
    e = _emit_leaves(f, flags, queue, out_node, out_tri, out_used, out_grid)
    _emit_vertices(f, e[0], e[2], heap, out_tri, out_used, out_pos, out_grid)
    # clean up: every node whose flags or vertex thresholds the walk touched is in queue[:visited]
    for i in range(e[1]):
        g = queue[i]
        flags[g] = wp.uint8(0)
        cache[f.apex[g]] = wp.uint8(0)
        cache[f.b0[g]] = wp.uint8(0)
        cache[f.b1[g]] = wp.uint8(0)
    flags[0] = wp.uint8(0)
    out_counts[0] = e[0]
    out_counts[1] = e[2]
    out_counts[2] = r[0]
    out_counts[3] = r[1]


# ------------------------------------------------------------------------------------------------
# host drivers
# ------------------------------------------------------------------------------------------------


def build_tree(heights: np.ndarray, origin: tuple[float, float], spacing: tuple[float, float],
               x0: float, z0: float, side: float, depth: int, method: str = "nearest3",
               device: str = "cpu") -> dict[str, np.ndarray]:
    """Build the whole tree to ``depth`` levels, one launch per level and stage.

    Args:
        heights: (H, W) float32 heightmap, row i along +z, column j along +x.
        origin, spacing: world (x, z) of sample (0, 0) and (dx, dz).
        x0, z0, side: the root square [x0, x0 + side] x [z0, z0 + side] in world metres.
        depth: M >= 1, the deepest level (2**M triangles).
        method: ``"nearest3"`` (paper) or ``"bilinear"`` vertex heights.

    Returns:
        dict with ``apex``, ``b0``, ``b1``: (2**(M+1) - 1,) int32 grid vertex ids per heap node (-1 for
        the root square); ``base_neighbour``: (same,) int32 (-1 on the border and for the root);
        ``lo``, ``hi``: (same,) float32 subtree height bounds; ``vertex_height``: ((G+1)**2,) float32;
        ``grid``: G = 2**floor(M/2) cells per side of the vertex grid.
    """
    check_choice("method", method, HEIGHT_METHODS)
    m = int(depth)
    grid = 1 << (m // 2)
    g1 = grid + 1
    n = (1 << (m + 1)) - 1
    step = float(side) / grid
    h = wp.array(np.ascontiguousarray(heights, np.float32), dtype=wp.float32, device=device)
    vh = wp.empty(g1 * g1, dtype=wp.float32, device=device)
    launch_one(_heights_kernel, dim=g1 * g1, inputs=[h, g1, float(x0), float(z0), step, float(origin[0]),
                                                     float(origin[1]), float(spacing[0]), float(spacing[1]),
                                                     HEIGHT_METHODS[method]], outputs=[vh], device=device)
    init = np.full(n, -1, np.int32)
    c00, c10, c01, c11 = 0, grid, grid * g1, grid * g1 + grid
    apex0, b00, b10 = init.copy(), init.copy(), init.copy()
    apex0[1], b00[1], b10[1] = c10, c00, c11  # the root square's diagonal (0,0)-(G,G)
    apex0[2], b00[2], b10[2] = c01, c11, c00
    apex, b0, b1 = (wp.array(a, dtype=wp.int32, device=device) for a in (apex0, b00, b10))
    bn = wp.array(init, dtype=wp.int32, device=device)
    slots = wp.empty(2 * g1 * g1, dtype=wp.int32, device=device)
    for level in range(1, m + 1):
        off = (1 << level) - 1
        cnt = 1 << level
        if level < m:
            launch_one(_split_kernel, dim=cnt, inputs=[off, g1], outputs=[apex, b0, b1], device=device)
        slots.fill_(-1)
        launch_one(_link_write_kernel, dim=cnt, inputs=[off, g1, b0, b1], outputs=[slots], device=device)
        launch_one(_link_read_kernel, dim=cnt, inputs=[off, g1, b0, b1, slots], outputs=[bn], device=device)
    lo = wp.zeros(n, dtype=wp.float32, device=device)
    hi = wp.zeros(n, dtype=wp.float32, device=device)
    off = (1 << m) - 1
    launch_one(_bounds_leaf_kernel, dim=1 << m, inputs=[off, apex, b0, b1, vh], outputs=[lo, hi], device=device)
    for level in range(m - 1, -1, -1):
        launch_one(_bounds_up_kernel, dim=1 << level, inputs=[(1 << level) - 1], outputs=[lo, hi], device=device)
    return {"apex": apex, "b0": b0, "b1": b1, "base_neighbour": bn, "lo": lo, "hi": hi, "vertex_height": vh,
            "grid": grid}


class Walk:
    """One tree's per-frame selection, for one thread: the buffers of :func:`_walk_kernel` and its
    launch, recorded once and replayed each frame (allocating a dozen arrays and packing a launch of
    them each frame took longer than the walk itself). The walk leaves its scratch zeroed again, so no
    frame depends on the one before (tested); :meth:`__call__` returns copies.

    Args:
        tree: :func:`build_tree`'s output. depth: its M.
    """

    def __init__(self, tree: dict, depth: int, device: str = "cpu"):
        m = int(depth)
        g1 = int(tree["grid"]) + 1
        n = (1 << (m + 1)) - 1
        self.device = wp.get_device(device)
        f = _Frame()
        f.apex, f.b0, f.b1, f.bn = tree["apex"], tree["b0"], tree["b1"], tree["base_neighbour"]
        f.lo, f.hi, f.vh = tree["lo"], tree["hi"], tree["vertex_height"]
        f.g1, f.max_level = g1, m
        self.planes = f.planes = wp.zeros(6, dtype=wp.vec4, device=device)
        self.vis = f.vis = wp.zeros(n, dtype=wp.uint8, device=device)
        self.frame = f
        self.scratch = [wp.zeros(n, dtype=wp.uint8, device=device), wp.zeros(g1 * g1, dtype=wp.uint8, device=device),
                        wp.empty(n, dtype=wp.int32, device=device),
                        wp.empty(max(n, g1 * g1), dtype=wp.int32, device=device),
                        wp.empty(n, dtype=wp.int32, device=device)]
        leaves = 1 << m  # at most: the leaves of a depth-M binary tree
        self.out = {"node": wp.empty(leaves, dtype=wp.int32, device=device),
                    "triangles": wp.empty(3 * leaves, dtype=wp.int32, device=device),
                    "used": wp.zeros(g1 * g1, dtype=wp.int32, device=device),
                    "positions": wp.empty(g1 * g1, dtype=wp.vec3, device=device),
                    "grid_id": wp.empty(g1 * g1, dtype=wp.int32, device=device),
                    "counts": wp.zeros(4, dtype=wp.int32, device=device)}
        self.launch = record(_walk_kernel, dim=1, inputs=[f, *self.scratch], outputs=list(self.out.values()),
                             device=device)
        self._views = None  # on the CPU, numpy views of the arrays: uploads and read-backs skip Warp
        if self.device.is_cpu:
            self._views = {k: a.numpy() for k, a in [*self.out.items(), ("planes", self.planes), ("vis", self.vis)]}

    def _upload(self, name: str, a: np.ndarray) -> None:
        if self._views is not None:
            self._views[name][...] = a
        else:
            getattr(self, name).assign(a)

    def _host(self, name: str, k: int) -> np.ndarray:
        """A copy of the first k items of output ``name``."""
        if self._views is not None:
            return self._views[name][:k].copy()
        return self.out[name][:k].numpy()

    def __call__(self, rel_origin: tuple[float, float], step: float, eye_y: float, short_side: float, *,
                 mode: int, hole_fix: bool, propagate: bool, planes: np.ndarray | None,
                 vis: np.ndarray | None) -> dict:
        """:func:`select_nodes` for this walk's tree."""
        f = self.frame
        f.mode, f.hole_fix, f.propagate = int(mode), int(bool(hole_fix)), int(bool(propagate))
        f.use_frustum, f.use_vis = int(planes is not None), int(vis is not None)
        f.rx0, f.rz0, f.step, f.eye_y = float(rel_origin[0]), float(rel_origin[1]), float(step), float(eye_y)
        f.inv_s = 1.0 / float(short_side)
        if planes is not None:
            self._upload("planes", np.asarray(planes, np.float32).reshape(6, 4))
        if vis is not None:
            self._upload("vis", vis)
        self.launch.set_param_at_index(0, f)
        replay(self.launch)
        count, nv, forced, iters = (int(v) for v in self._host("counts", 4))
        return {"node": self._host("node", count), "triangles": self._host("triangles", 3 * count).reshape(-1, 3),
                "positions": self._host("positions", nv).reshape(-1, 3), "grid_id": self._host("grid_id", nv),
                "forced": forced, "iterations": iters}


def select_nodes(tree: dict, depth: int, rel_origin: tuple[float, float], step: float, eye_y: float,
                 short_side: float, *, mode: int, hole_fix: bool, propagate: bool,
                 planes: np.ndarray | None, vis: np.ndarray | None, device: str = "cpu",
                 walk: Walk | None = None) -> dict:
    """One frame's selection: split/cull decisions from the root down, optional forced splits, the
    leaves and the compacted mesh, in one launch.

    The walk is one sequential thread (``dim=1``): it visits only the children of split nodes (some
    thousand for a ground view of a 65,536-triangle tree) and works out a vertex's threshold when a
    node first needs it, where level-by-level passes launch once per level over every node. Its output
    is, bit for bit, that of those passes (kept as the reference in tests/lod/test_bintree.py),
    forced-split and pass counts included.

    Args:
        tree: :func:`build_tree`'s output.
        rel_origin: (x0 - eye_x, z0 - eye_z), the root square's corner relative to the eye (float64 on the
            host, cast once). eye_y: the eye's height. step: grid spacing in metres.
        short_side: S, the leg of a level-M triangle, metres.
        mode: 0 every node to depth M (brute force), 1 the LOD rule.
        hole_fix: the paper's rule (split a triangle whose right-angle vertex alone has the lowest threshold).
        propagate: forced split propagation (a split node's base neighbour is split) until stable.
        planes: (6, 4) float32 camera-relative frustum planes, or None for no culling.
        vis: (2**(M+1) - 1,) uint8 per-node visibility (0 = hidden: culled with its subtree), or None.
        walk: a :class:`Walk` of this tree to reuse (one per thread); None makes one for this call.

    Returns:
        dict: ``node`` (m,) int32 heap index per triangle, ascending; ``positions`` (n, 3) float32
        camera-relative; ``triangles`` (m, 3) int32 ccw from above; ``grid_id`` (n,) int32 grid vertex id
        per vertex, ascending; ``forced`` number of forced splits; ``iterations``: propagation passes (the
        last one changes nothing; 0 without propagation).
    """
    w = walk if walk is not None else Walk(tree, depth, device)
    return w(rel_origin, step, eye_y, short_side, mode=mode, hole_fix=hole_fix, propagate=propagate, planes=planes,
             vis=vis)

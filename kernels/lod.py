"""Per-node LOD maths for quadtree selection, and the quadtree walked in one launch.

Two ways to select: :func:`select_level`, one launch per level over that level's candidate nodes (the path of a
streamed terrain, whose node stats are worked out on demand), and :class:`TreeWalk` (:class:`QuadtreeWalk`, and
CDLOD's and chunked LOD's in :mod:`terrainwarp.kernels.schemes`): one thread walks the whole tree in one
recorded, replayed launch, with the same per-node maths (:func:`node_box`, :func:`box_distance`,
:func:`screen_error`, :func:`box_outside`), so both make the same selection.

For each node: its box (x/z extent, min/max height) relative to the eye, the distance from the eye to
the box (0 when the eye is inside it: a defined case, never a division by zero), a frustum test of
the box against the six planes of the view-projection matrix (Gribb-Hartmann extraction, p-vertex
test), and the policy's split decision:

* policy 0, distance (deaconu2021 "Rendering"): split while ``dist < threshold[level]``;
* policy 1, screen-space error (malafeev2014, Cesium's maximumScreenSpaceError):
  ``sse = geometric_error * focal_px / dist`` with ``focal_px = viewport_height / (2 tan(fovy/2))``,
  split while ``sse > tolerance_px``; at ``dist == 0`` a node with any error splits and a node with
  zero error does not (0 * inf is defined as 0).

Hysteresis (malafeev2014: separate thresholds for going to a finer and to a coarser level): with band
``h``, a node that was split in the previous frame stays split until the metric crosses the *merge*
threshold (``tolerance * (1 - h)`` for sse, ``threshold * (1 + h)`` for distance), and a node that was
not split splits only past the *split* threshold (``tolerance * (1 + h)``, ``threshold * (1 - h)``).
"Was split" is looked up by binary search in the sorted keys of the previous frame's split nodes.

The tree map (:func:`tree_map`, :func:`mark_nodes`, :func:`neighbour_levels`): one int32 cell per node of
every level of the complete tree (a hash table of the nodes in the tree when the complete tree would
exceed ``DENSE_MAX_CELLS`` cells: a streamed 2^20-sample terrain) (level L's ``(nz << L) x (nx << L)``
nodes row-major after the levels above it, like the terrain's per-level pyramids), holding ``leaf index + 1``
for a leaf, ``-1`` for a split node and 0 for a node inside a coarser leaf. The leaf containing any
finest-level cell is then found by walking from a guessed level: down through split nodes, up through nodes
that are not in the tree. Neighbour levels cost a few lookups per edge, linear in the number of leaves.
:class:`QuadtreeWalk` keeps one dense map per terrain, all 0 between frames (each walk clears what it marked).
"""

from __future__ import annotations

import threading
import time

import numpy as np
import warp as wp

from .parallel import empty, launch, record, replay


@wp.func
def _was_split(keys: wp.array(dtype=wp.int64), n: int, key: wp.int64) -> wp.bool:
    lo = int(0)
    hi = n
    while lo < hi:
        mid = (lo + hi) / 2
        if keys[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    return lo < n and keys[lo] == key


@wp.func
def box_outside(planes: wp.array(dtype=wp.vec4), lo: wp.vec3, hi: wp.vec3) -> int:
    """1 when the box [lo, hi] lies outside one of the six frustum planes (p-vertex test)."""
    out = int(0)
    for p in range(6):
        pl = planes[p]
        vx = wp.where(pl[0] >= 0.0, hi[0], lo[0])
        vy = wp.where(pl[1] >= 0.0, hi[1], lo[1])
        vz = wp.where(pl[2] >= 0.0, hi[2], lo[2])
        if pl[0] * vx + pl[1] * vy + pl[2] * vz + pl[3] < 0.0:
            out = 1
    return out


@wp.func
def node_box(rel_origin: wp.vec3, node_size: wp.vec2, x: int, y: int, hmin: float, hmax: float):
    """The box of node (x, y) of a level whose nodes are ``node_size`` metres, relative to the eye: (lo, hi)."""
    lo = wp.vec3(rel_origin[0] + float(x) * node_size[0], hmin - rel_origin[1],
                 rel_origin[2] + float(y) * node_size[1])
    hi = wp.vec3(lo[0] + node_size[0], hmax - rel_origin[1], lo[2] + node_size[1])
    return lo, hi


@wp.func
def box_distance(lo: wp.vec3, hi: wp.vec3) -> float:
    """The distance from the eye (the origin) to the box [lo, hi]; 0 inside it."""
    dx = wp.max(wp.max(lo[0], -hi[0]), 0.0)
    dy = wp.max(wp.max(lo[1], -hi[1]), 0.0)
    dz = wp.max(wp.max(lo[2], -hi[2]), 0.0)
    return wp.sqrt(dx * dx + dy * dy + dz * dz)


@wp.func
def screen_error(e: float, dist: float, focal_px: float) -> float:
    """A node's screen-space error in pixels: ``e * focal_px / dist``; at ``dist == 0`` 3e38 when ``e > 0``, 0
    otherwise."""
    sse = float(0.0)
    if e > 0.0:
        if dist > 0.0:
            sse = e * focal_px / dist
        else:
            sse = 3.0e38
    return sse


@wp.func
def splits(code: int, metric: float, threshold: float, hysteresis: float, was_split: wp.bool) -> wp.bool:
    """The quadtree policies' split rule, with hysteresis: code 0 (distance) splits while the distance ``metric`` is
    below ``threshold * (1 + h)`` for a node split in the previous frame and ``threshold * (1 - h)`` for another;
    code 1 (screen error) while the error is above ``threshold * (1 - h)`` or ``threshold * (1 + h)``."""
    if code == 0:
        return metric < threshold * wp.where(was_split, 1.0 + hysteresis, 1.0 - hysteresis)
    return metric > threshold * wp.where(was_split, 1.0 - hysteresis, 1.0 + hysteresis)


@wp.kernel(enable_backward=False)
def _select_kernel(
    offset: int,
    node_x: wp.array(dtype=wp.int32),
    node_y: wp.array(dtype=wp.int32),
    node_key: wp.array(dtype=wp.int64),
    hmin: wp.array(dtype=wp.float32),
    hmax: wp.array(dtype=wp.float32),
    gerr: wp.array(dtype=wp.float32),
    rel_origin: wp.vec3,
    node_size: wp.vec2,
    planes: wp.array(dtype=wp.vec4),
    policy: int,
    threshold: float,
    focal_px: float,
    hysteresis: float,
    can_split: int,
    prev_split: wp.array(dtype=wp.int64),
    n_prev: int,
    # outputs
    out_split: wp.array(dtype=wp.int32),
    out_culled: wp.array(dtype=wp.int32),
    out_dist: wp.array(dtype=wp.float32),
    out_metric: wp.array(dtype=wp.float32),
):
    k = wp.tid() + offset
    x = node_x[k]
    y = node_y[k]
    lo, hi = node_box(rel_origin, node_size, x, y, hmin[k], hmax[k])
    dist = box_distance(lo, hi)
    out_dist[k] = dist
    culled = box_outside(planes, lo, hi)
    out_culled[k] = culled
    prev = False
    if n_prev > 0:  # keys are read only with a previous frame to look them up in
        prev = _was_split(prev_split, n_prev, node_key[k])
    metric = dist
    if policy != 0:
        metric = screen_error(gerr[k], dist, focal_px)
    out_metric[k] = metric
    split = int(0)
    if splits(policy, metric, threshold, hysteresis, prev) and culled == 0 and can_split != 0:
        split = 1
    out_split[k] = split


_PLANE_ROWS = np.array([0, 0, 1, 1, 2, 2])
_PLANE_SIGNS = np.array([[1.0], [-1.0], [1.0], [-1.0], [1.0], [-1.0]])


def frustum_planes(view_proj: np.ndarray) -> np.ndarray:
    """The six planes (a, b, c, d), inside where a x + b y + c z + d >= 0, of an OpenGL view-projection
    matrix (Gribb & Hartmann), normalised, float32 (6, 4): left, right, bottom, top, near, far."""
    m = np.asarray(view_proj, dtype=np.float64)
    pl = m[3] + m[_PLANE_ROWS] * _PLANE_SIGNS  # r3 + r0, r3 - r0, r3 + r1, r3 - r1, r3 + r2, r3 - r2 (exactly)
    xyz = pl[:, :3]
    pl /= np.sqrt(np.add.reduce(xyz * xyz, axis=1, keepdims=True))  # np.linalg.norm's sum, without its dispatch
    return pl.astype(np.float32)


def _dev(a, device: str) -> wp.array:
    return a if isinstance(a, wp.array) else wp.array(np.ascontiguousarray(a, np.float32), dtype=wp.float32,
                                                      device=device)


def select_level(node_x: np.ndarray, node_y: np.ndarray, node_key: np.ndarray | None, stats: tuple, rel_origin,
                 node_size_world, planes: np.ndarray, policy: int, threshold: float, focal_px: float,
                 hysteresis: float, can_split: bool, prev_split: np.ndarray, device: str = "cpu"):
    """Evaluate one level's candidate nodes. Returns (split, culled, dist, metric) numpy arrays.

    ``stats``: the candidates' (min, max, geometric error), each (N,) float32 in candidate order (a Terrain's
    ``stats_at``: gathered from its pyramids, or worked out on demand for a streamed heightmap).
    ``node_key`` may be None when ``prev_split`` is empty (nothing to look the keys up in)."""
    n = len(node_x)
    hmin, hmax, gerr = (np.ascontiguousarray(a, dtype=np.float32).reshape(-1) for a in stats)
    if not len(hmin) == len(hmax) == len(gerr) == n:
        raise ValueError(f"stats: expected 3 arrays of {n} per-candidate values, got {len(hmin)}, {len(hmax)}, "
                         f"{len(gerr)}")
    prev = np.ascontiguousarray(prev_split, dtype=np.int64)
    if node_key is None or len(prev) == 0:
        node_key = np.zeros(1, np.int64)
    arrs = [wp.empty(n, dtype=wp.int32, device=device), wp.empty(n, dtype=wp.int32, device=device),
            wp.empty(n, dtype=wp.float32, device=device), wp.empty(n, dtype=wp.float32, device=device)]
    if n == 0:
        return tuple(a.numpy() for a in arrs)
    launch(_select_kernel, n, inputs=[
        _i32(node_x, device), _i32(node_y, device),
        wp.array(node_key.astype(np.int64), dtype=wp.int64, device=device),
        _dev(hmin, device), _dev(hmax, device), _dev(gerr, device),
        wp.vec3(*[float(v) for v in rel_origin]), wp.vec2(*[float(v) for v in node_size_world]),
        wp.array(planes, dtype=wp.vec4, device=device), int(policy), float(threshold), float(focal_px),
        float(hysteresis), int(bool(can_split)),
        wp.array(prev if len(prev) else np.zeros(1, np.int64), dtype=wp.int64, device=device), int(len(prev))],
        outputs=arrs, device=device)
    return tuple(a.numpy() for a in arrs)


# ------------------------------------------------------------------------------------------------
# the tree map: point location in a quadtree tiling, linear in the leaves
# ------------------------------------------------------------------------------------------------
@wp.struct
class TreeMap:
    """The tree map as kernels see it: a dense array of every node's cell, or (a tree too deep for that: the
    complete tree of a 2^20-sample terrain has 10^9 leaves) an open-addressing hash table of the nodes in
    the tree, keyed like tile keys (level << 58 | y << 29 | x); a node not in it reads 0."""

    dense: wp.array(dtype=wp.int32)
    keys: wp.array(dtype=wp.int64)  # -1: empty slot
    vals: wp.array(dtype=wp.int32)
    mask: wp.int64
    sparse: int
    nx: int
    n_roots: int


@wp.func
def _tree_cell(level: int, x: int, y: int, nx: int, n_roots: int) -> int:
    """Index of node (level, x, y) in the dense tree map: the levels above, then row-major in the level."""
    return n_roots * (((1 << (2 * level)) - 1) / 3) + y * (nx << level) + x


@wp.func
def _hash_slot(key: wp.int64, mask: wp.int64) -> wp.int64:
    """Fibonacci hashing of a tile key (as :func:`_slots` on the host)."""
    h = wp.uint64(key) * wp.uint64(11400714819323198485)
    return wp.int64(h >> wp.uint64(24)) & mask


@wp.func
def _cell(t: TreeMap, level: int, x: int, y: int) -> int:
    if t.sparse == 0:
        return t.dense[_tree_cell(level, x, y, t.nx, t.n_roots)]
    key = (wp.int64(level) << wp.int64(58)) | (wp.int64(y) << wp.int64(29)) | wp.int64(x)
    slot = _hash_slot(key, t.mask)
    k = t.keys[slot]
    while k != key and k != wp.int64(-1):
        slot = (slot + wp.int64(1)) & t.mask
        k = t.keys[slot]
    if k == key:
        return t.vals[slot]
    return 0


@wp.func
def _leaf_at(tree: TreeMap, fx: int, fy: int, start: int, depth: int) -> int:
    """Index of the leaf containing finest-level cell (fx, fy) of the root grid, walking from level
    ``start``: down through split nodes, up through nodes inside a coarser leaf."""
    m = int(start)
    c = _cell(tree, m, fx >> (depth - m), fy >> (depth - m))
    while c <= 0:
        if c < 0:
            m = m + 1
        else:
            m = m - 1
        c = _cell(tree, m, fx >> (depth - m), fy >> (depth - m))
    return c - 1


@wp.kernel(enable_backward=False)
def _mark_kernel(offset: int, level: wp.array(dtype=wp.int32), x: wp.array(dtype=wp.int32),
                 y: wp.array(dtype=wp.int32), value: wp.array(dtype=wp.int32), nx: int, n_roots: int,
                 tree: wp.array(dtype=wp.int32)):
    i = wp.tid() + offset
    tree[_tree_cell(level[i], x[i], y[i], nx, n_roots)] = value[i]


@wp.func
def _edge_level(tree: TreeMap, level_of: wp.array(dtype=wp.int32), lv: int, nbx: int, nby: int,
                ax: int, ay: int, bx: int, by: int, depth: int, nz: int) -> int:
    """The larger ``level_of`` of the leaves containing finest cells a and b, both inside node (lv, nbx,
    nby), the neighbour across an edge (-1: beyond the root grid). Unless that node is split, one leaf
    holds both: one lookup."""
    if nbx < 0 or nby < 0 or nbx >= (tree.nx << lv) or nby >= (nz << lv):
        return -1
    c = _cell(tree, lv, nbx, nby)
    if c < 0:  # split: finer leaves, one walk down for each probe
        return wp.max(level_of[_leaf_at(tree, ax, ay, lv + 1, depth)],
                      level_of[_leaf_at(tree, bx, by, lv + 1, depth)])
    if c == 0:  # inside a coarser leaf
        return level_of[_leaf_at(tree, ax, ay, lv - 1, depth)]
    return level_of[c - 1]


@wp.func
def edge_levels(tree: TreeMap, level_of: wp.array(dtype=wp.int32), lv: int, xi: int, yi: int, depth: int,
                nz: int) -> wp.vec4i:
    """The largest ``level_of`` of the leaves across node (lv, xi, yi)'s west, north, east and south edges,
    probed just outside each edge at 1/4 and 3/4 of its length (-1 beyond the root grid)."""
    sh = depth - lv
    s = 1 << sh
    q1 = s / 4
    q3 = (3 * s) / 4
    x0 = xi << sh
    y0 = yi << sh
    return wp.vec4i(_edge_level(tree, level_of, lv, xi - 1, yi, x0 - 1, y0 + q1, x0 - 1, y0 + q3, depth, nz),
                    _edge_level(tree, level_of, lv, xi, yi - 1, x0 + q1, y0 - 1, x0 + q3, y0 - 1, depth, nz),
                    _edge_level(tree, level_of, lv, xi + 1, yi, x0 + s, y0 + q1, x0 + s, y0 + q3, depth, nz),
                    _edge_level(tree, level_of, lv, xi, yi + 1, x0 + q1, y0 + s, x0 + q3, y0 + s, depth, nz))


@wp.kernel(enable_backward=False)
def _neighbour_kernel(offset: int, level: wp.array(dtype=wp.int32), x: wp.array(dtype=wp.int32),
                      y: wp.array(dtype=wp.int32), level_of: wp.array(dtype=wp.int32),
                      tree: TreeMap, depth: int, nz: int,
                      out: wp.array2d(dtype=wp.int32)):
    i = wp.tid() + offset
    e = edge_levels(tree, level_of, level[i], x[i], y[i], depth, nz)
    for k in range(4):
        out[i, k] = e[k]


DENSE_MAX_CELLS = 1 << 26  # a deeper complete tree (256 MiB of int32 cells) gets the hash table


def tree_cells(roots: tuple[int, int], depth: int) -> int:
    """The nodes of the complete tree over ``roots`` = (nx, nz) root nodes, levels 0..depth: a dense tree map's
    cells (more than ``DENSE_MAX_CELLS``: the map is a hash table)."""
    return int(roots[0]) * int(roots[1]) * ((4 ** (int(depth) + 1) - 1) // 3)


def _slots(keys: np.ndarray, mask: int) -> np.ndarray:
    h = keys.astype(np.uint64) * np.uint64(11400714819323198485)  # wraps, as the kernel's uint64
    return (h >> np.uint64(24)).astype(np.int64) & np.int64(mask)


class TreeMapHost:
    """A tree map and its device view (:class:`TreeMap`): dense for a complete tree up to DENSE_MAX_CELLS
    cells, else a hash table of the marked nodes (kept at most half full; grown on the host)."""

    def __init__(self, roots: tuple[int, int], depth: int, device: str = "cpu"):
        self.roots, self.depth, self.device = (int(roots[0]), int(roots[1])), int(depth), device
        self.cells = tree_cells(roots, depth)
        self.sparse = self.cells > DENSE_MAX_CELLS
        if self.sparse:
            self.dense = wp.zeros(1, dtype=wp.int32, device=device)
            self._alloc(1 << 12)
        elif wp.get_device(device).is_cpu:  # calloc'd: only the pages a frame touches are ever zeroed
            self.dense = wp.array(np.zeros(self.cells, np.int32), dtype=wp.int32, device=device, copy=False)
        else:
            self.dense = wp.zeros(self.cells, dtype=wp.int32, device=device)

    def __len__(self) -> int:
        return self.cells if not self.sparse else int(self.n)

    def _alloc(self, cap: int) -> None:
        self.k = np.full(cap, -1, np.int64)
        self.v = np.zeros(cap, np.int32)
        self.n = 0

    def view(self) -> TreeMap:
        t = TreeMap()
        t.dense, t.sparse, t.nx, t.n_roots = self.dense, int(self.sparse), self.roots[0], self.roots[0] * self.roots[1]
        k = self.k if self.sparse else np.full(1, -1, np.int64)
        v = self.v if self.sparse else np.zeros(1, np.int32)
        t.keys = wp.array(k, dtype=wp.int64, device=self.device)
        t.vals = wp.array(v, dtype=wp.int32, device=self.device)
        t.mask = len(k) - 1
        return t

    def put(self, keys: np.ndarray, vals: np.ndarray) -> None:
        """Set the cells of ``keys`` (tile keys) to ``vals`` (the hash table; last write wins)."""
        if (self.n + len(keys)) * 2 > len(self.k):
            live = self.k >= 0
            old_k, old_v = self.k[live], self.v[live]
            cap = len(self.k)
            while (len(old_k) + len(keys)) * 2 > cap:
                cap *= 2
            self._alloc(cap)
            self._insert(old_k, old_v)
        self._insert(keys, vals)

    def _insert(self, keys: np.ndarray, vals: np.ndarray) -> None:
        keys = np.asarray(keys, np.int64)
        vals = np.asarray(vals, np.int32)
        _, last = np.unique(keys[::-1], return_index=True)  # one write per key: the last one
        pick = len(keys) - 1 - last
        keys, vals = keys[pick], vals[pick]
        mask = len(self.k) - 1
        pos = _slots(keys, mask)
        todo = np.arange(len(keys))
        while len(todo):
            cur = self.k[pos[todo]]
            hit = cur == keys[todo]
            self.v[pos[todo[hit]]] = vals[todo[hit]]
            free = cur == -1
            cand = todo[free]
            _, first = np.unique(pos[cand], return_index=True)  # one claim per empty slot per round
            won = cand[first]
            self.k[pos[won]] = keys[won]
            self.v[pos[won]] = vals[won]
            self.n += len(won)
            done = np.zeros(len(keys), bool)
            done[todo[hit]] = True
            done[won] = True
            rest = todo[~done[todo]]
            moved = rest[self.k[pos[rest]] != -1]  # blocked by another key: probe on
            pos[moved] = (pos[moved] + 1) & mask
            todo = rest


def tree_map(roots: tuple[int, int], depth: int, device: str = "cpu") -> TreeMapHost:
    """An empty tree map (every cell 0) for ``roots`` = (nx, nz) root nodes and levels 0..depth."""
    return TreeMapHost(roots, depth, device)


def tree_leaves(tree: TreeMapHost, roots: tuple[int, int], depth: int) -> np.ndarray:
    """The leaf indices of a dense map in key order (level by level, row-major (y, x) in a level): a scan of
    the whole map, for when it is not much larger than the number of leaves."""
    cells = tree.dense.numpy()
    parts, start = [], 0
    for lv in range(depth + 1):
        n = roots[0] * roots[1] << (2 * lv)  # the level's cells, as _tree_cell lays them out
        level_cells = cells[start:start + n]
        parts.append(level_cells[level_cells > 0] - 1)
        start += n
    return np.concatenate(parts)


def _i32(a: np.ndarray, device: str | wp.Device) -> wp.array:
    """An int32 Warp array of ``a`` (sharing its memory on the CPU when it is int32 already)."""
    return wp.array(np.ascontiguousarray(a, np.int32), dtype=wp.int32, device=device,
                    copy=not wp.get_device(device).is_cpu)


def mark_nodes(tree: TreeMapHost, roots: tuple[int, int], level: np.ndarray, x: np.ndarray, y: np.ndarray,
               value: np.ndarray | int) -> None:
    """Write ``value`` (leaf index + 1, or -1 for a split node) into the cells of nodes (level, x, y)."""
    n = len(level)
    if n == 0:
        return
    v = np.broadcast_to(np.asarray(value, np.int32), (n,))
    if tree.sparse:
        lv, xx, yy = (np.asarray(a, np.int64) for a in (level, x, y))
        tree.put((lv << 58) | (yy << 29) | xx, v)
        return
    dev = tree.dense.device
    launch(_mark_kernel, n, inputs=[_i32(level, dev), _i32(x, dev), _i32(y, dev), _i32(v, dev), int(roots[0]),
                                    int(roots[0] * roots[1])], outputs=[tree.dense], device=dev)


def neighbour_levels(tree: TreeMapHost, roots: tuple[int, int], depth: int, level: np.ndarray, x: np.ndarray,
                     y: np.ndarray, level_of: np.ndarray) -> np.ndarray:
    """(n, 4) int32: for each node (level, x, y), the largest ``level_of[leaf]`` of the leaves just across
    its west, north, east and south edges (probed at 1/4 and 3/4 of the edge, which finds any leaf finer
    than level + 1); -1 beyond the root grid."""
    n = len(level)
    dev = tree.dense.device
    out = wp.empty((n, 4), dtype=wp.int32, device=dev)
    launch(_neighbour_kernel, n, inputs=[_i32(level, dev), _i32(x, dev), _i32(y, dev), _i32(level_of, dev),
                                         tree.view(), int(depth), int(roots[1])], outputs=[out], device=dev)
    return out.numpy()


# ------------------------------------------------------------------------------------------------
# a quadtree walked by one thread in one launch (CDLOD, chunked LOD, the quadtree policies)
# ------------------------------------------------------------------------------------------------
@wp.func
def walk_roots(front: wp.array3d(dtype=wp.int32), roots: wp.vec2i) -> int:
    """The root nodes, row by row, into frontier 0; returns their count."""
    n = int(0)
    for ry in range(roots[1]):
        for rx in range(roots[0]):
            front[0, n, 0] = rx
            front[0, n, 1] = ry
            n += 1
    return n


@wp.func
def is_inside(cnt: wp.vec2i, x: int, y: int) -> wp.bool:
    """Node (x, y) of a level with ``cnt`` columns and rows of nodes inside the grid has its origin inside (the
    first root always), as the host's ``Terrain.inside``."""
    return (x < cnt[0] and y < cnt[1]) or (x == 0 and y == 0)


@wp.func
def keep_inside(front: wp.array3d(dtype=wp.int32), p: int, n: int, cnt: wp.vec2i) -> int:
    """Frontier ``p`` compacted to the nodes whose origin lies inside the grid (and the first root); returns
    their count."""
    m = int(0)
    for i in range(n):
        x = front[p, i, 0]
        y = front[p, i, 1]
        if is_inside(cnt, x, y):
            front[p, m, 0] = x
            front[p, m, 1] = y
            m += 1
    return m


@wp.func
def push_children(front: wp.array3d(dtype=wp.int32), p: int, n: int, code: wp.array(dtype=wp.int32),
                   split: int) -> int:
    """The children of the nodes of frontier ``p`` whose code is ``split`` into frontier ``1 - p``, quadrant by
    quadrant ((0, 0), (1, 0), (0, 1), (1, 1) blocks, as numpy concatenates them); returns their count."""
    m = int(0)
    for c in range(4):
        for i in range(n):
            if code[i] == split:
                front[1 - p, m, 0] = 2 * front[p, i, 0] + c % 2
                front[1 - p, m, 1] = 2 * front[p, i, 1] + c / 2
                m += 1
    return m


@wp.struct
class QuadTree:
    """A terrain's quadtree as the one-launch walks read it: every level's node minima, maxima and geometric errors,
    level after level (rows of ``roots[0] << level`` nodes from ``level_start[level]``), per level the columns and
    rows of nodes whose origin lies inside the grid, the root grid, the deepest level and the node size in metres
    (float32, the box test's)."""

    hmin: wp.array(dtype=wp.float32)
    hmax: wp.array(dtype=wp.float32)
    herr: wp.array(dtype=wp.float32)
    level_start: wp.array(dtype=wp.int32)
    inside: wp.array(dtype=wp.vec2i)
    roots: wp.vec2i
    depth: int
    size32: wp.array(dtype=wp.vec2)


@wp.func
def node_index(qt: QuadTree, lv: int, x: int, y: int) -> int:
    """Where node (lv, x, y) lies in the tree's per-level arrays."""
    return qt.level_start[lv] + y * (qt.roots[0] << lv) + x


class TreeWalk:
    """A quadtree walked by one thread in one launch (the quadtree policies', CDLOD's and chunked LOD's selections),
    as their references walk it in one recursion. Built once per terrain: the tree (:class:`QuadTree`) and the
    frame's buffers, with the launch recorded once (:func:`.parallel.record`) and replayed per frame, the frame's
    inputs written into its input arrays. One selection runs at a time (a lock)."""

    def __init__(self, stats: list, inside: np.ndarray, roots: tuple[int, int], sizes: list[tuple[float, float]],
                 device: str) -> None:
        """``stats``: per level (min, max, geometric error) arrays (nz << L, nx << L); ``inside``: (depth + 1, 2)
        int, per level the columns and rows of nodes whose origin lies inside the grid; ``sizes``: per level node
        size in metres (float64)."""
        self.levels = len(stats)
        ins = np.ascontiguousarray(inside, np.int32)
        self.capacity = 4 * (int(ins[-1, 0]) * int(ins[-1, 1]) + 1)  # 4 quadrants per finest node inside
        sz = np.asarray(sizes, np.float64)

        def pyramid(k: int) -> wp.array:
            return wp.array(np.concatenate([np.ascontiguousarray(a[k], np.float32).reshape(-1) for a in stats]),
                            dtype=wp.float32, device=device)

        t = QuadTree()
        t.hmin, t.hmax, t.herr = pyramid(0), pyramid(1), pyramid(2)
        t.level_start = wp.array(np.cumsum([0] + [a[0].size for a in stats[:-1]]).astype(np.int32), dtype=wp.int32,
                                 device=device)
        t.inside = wp.array(ins, dtype=wp.vec2i, device=device)
        t.roots, t.depth = wp.vec2i(int(roots[0]), int(roots[1])), self.levels - 1
        t.size32 = wp.array(sz.astype(np.float32), dtype=wp.vec2, device=device)
        self.tree = t
        self._lock = threading.Lock()
        self._cpu = wp.get_device(device).is_cpu
        self.device = device

    def _frontier(self, n: int) -> list[wp.array]:
        """The walk's scratch for frontiers of up to ``n`` nodes: two frontiers of (x, y) and a code per node."""
        return [wp.empty((2, n, 2), dtype=wp.int32, device=self.device),
                wp.empty(n, dtype=wp.int32, device=self.device)]

    def _record(self, kernel: wp.Kernel, inputs: list, outputs: list) -> None:
        """Record the walk's launch: the tree, then ``self._args`` (holding the per-frame ``inputs``, which
        :meth:`_run` writes)."""
        self._inputs, self._outputs = inputs, outputs
        self._kernel = kernel
        self._cmd = record(kernel, 1, [self.tree, *self._args], outputs, self.device)
        self._host_in = [a.numpy() for a in inputs] if self._cpu else None
        self._host_out = [a.numpy() for a in outputs] if self._cpu else None

    def launch_cost(self, repeat: int = 200) -> tuple[float, float]:
        """(µs per replay of the recorded launch, µs per ``wp.launch`` of the same launch, its arguments packed
        again), best of ``repeat`` each, on the last frame's inputs: what recording saves per frame."""
        args = [self.tree, *self._args]
        out = []
        with self._lock:
            for run in (lambda: self._cmd.launch(),
                        lambda: wp.launch(self._kernel, dim=1, inputs=args, outputs=self._outputs, device=self.device)):
                best = float("inf")
                for _ in range(repeat):
                    t0 = time.perf_counter()
                    run()
                    best = min(best, time.perf_counter() - t0)
                out.append(best * 1e6)
        return out[0], out[1]

    def _run(self, values: list) -> list[np.ndarray]:
        """Write ``values`` into the input arrays, replay the launch; the outputs as numpy (copy what is kept: the
        buffers are the next frame's). Call under the lock."""
        host = self._host_in if self._cpu else [a.numpy() for a in self._inputs]
        for h, v in zip(host, values, strict=True):
            h[...] = v
        if not self._cpu:
            for a, h in zip(self._inputs, host, strict=True):
                a.assign(h)
        replay(self._cmd)
        return self._host_out if self._cpu else [a.numpy() for a in self._outputs]


@wp.func
def _tile_key(lv: int, x: int, y: int) -> wp.int64:
    """As the host's ``tile_key``: level << 58 | y << 29 | x."""
    return (wp.int64(lv) << wp.int64(58)) | (wp.int64(y) << wp.int64(29)) | wp.int64(x)


@wp.func
def _add_node(nodes: wp.array2d(dtype=wp.int32), dm: wp.array2d(dtype=wp.float32), j: int, lv: int, x: int, y: int,
              flags: int, dist: float, metric: float):
    """Node j of the tiling: level, x, y, flags (1 culled, 2 outside the grid, 4 alive), distance, metric."""
    nodes[j, 0] = lv
    nodes[j, 1] = x
    nodes[j, 2] = y
    nodes[j, 3] = flags
    dm[j, 0] = dist
    dm[j, 1] = metric


@wp.func
def _evaluate_node(qt: QuadTree, lv: int, x: int, y: int, rel: wp.vec3, planes: wp.array(dtype=wp.vec4), code: int,
                   focal: float):
    """(culled, distance, metric) of node (lv, x, y), as :func:`_select_kernel` works them out."""
    k = node_index(qt, lv, x, y)
    lo, hi = node_box(rel, qt.size32[lv], x, y, qt.hmin[k], qt.hmax[k])
    dist = box_distance(lo, hi)
    metric = dist
    if code != 0:
        metric = screen_error(qt.herr[k], dist, focal)
    return box_outside(planes, lo, hi), dist, metric


@wp.func
def _cell_of(qt: QuadTree, lv: int, x: int, y: int) -> int:
    """Node (lv, x, y)'s cell in the dense tree map."""
    return _tree_cell(lv, x, y, qt.roots[0], qt.roots[0] * qt.roots[1])


@wp.func
def _descend(qt: QuadTree, rel: wp.vec3, planes: wp.array(dtype=wp.vec4), thresholds: wp.array(dtype=wp.float32),
             params: wp.array(dtype=wp.float32), ints: wp.array(dtype=wp.int32), prev: wp.array(dtype=wp.int64),
             front: wp.array3d(dtype=wp.int32), code: wp.array(dtype=wp.int32), tree: TreeMap,
             nodes: wp.array2d(dtype=wp.int32), dm: wp.array2d(dtype=wp.float32),
             out_split: wp.array2d(dtype=wp.int32)) -> wp.vec3i:
    """The descent from the roots, level by level: nodes outside the grid are leaves that only complete the tiling;
    the others split by the policy (:func:`splits`, ``ints[0]`` its code, against the previous frame's split keys
    in ``prev``, ``ints[2]`` of them), culled nodes and the deepest level do not, and with a fixed level
    (``ints[1]`` >= 0, the continuous policy) everything splits down to it. Split nodes go to ``out_split`` and are
    marked -1 in the tree map, the rest to the tiling ``nodes``. Returns (nodes of the tiling, split nodes, nodes
    visited)."""
    pcode = ints[0]
    fixed = ints[1]
    n = walk_roots(front, qt.roots)
    p = int(0)
    nn = int(0)
    ns = int(0)
    visited = int(0)
    for lvl in range(qt.depth + 1):
        cnt = qt.inside[lvl]
        m = int(0)
        for i in range(n):  # outside the grid: a leaf that only completes the tiling
            x = front[p, i, 0]
            y = front[p, i, 1]
            if is_inside(cnt, x, y):
                front[p, m, 0] = x
                front[p, m, 1] = y
                m += 1
            else:
                _add_node(nodes, dm, nn, lvl, x, y, 7, 0.0, 0.0)
                nn += 1
        n = m
        if n == 0:
            break
        visited += n
        can = lvl < qt.depth
        if fixed >= 0:
            can = lvl < fixed
        for i in range(n):
            x = front[p, i, 0]
            y = front[p, i, 1]
            culled, dist, metric = _evaluate_node(qt, lvl, x, y, rel, planes, pcode, params[0])
            was = False
            if ints[2] > 0:
                was = _was_split(prev, ints[2], _tile_key(lvl, x, y))
            split = int(0)
            if splits(pcode, metric, thresholds[lvl], params[1], was) and culled == 0 and can:
                split = 1
            if fixed >= 0 and lvl < fixed:
                split = 1  # a uniform grid: everything splits down to the level
            code[i] = split
            if split == 1:
                out_split[ns, 0] = lvl
                out_split[ns, 1] = x
                out_split[ns, 2] = y
                ns += 1
                tree.dense[_cell_of(qt, lvl, x, y)] = -1
            else:
                _add_node(nodes, dm, nn, lvl, x, y, 4 + culled, dist, metric)
                nn += 1
        n = push_children(front, p, n, code, 1)
        p = 1 - p
    return wp.vec3i(nn, ns, visited)


@wp.func
def _balance(qt: QuadTree, tree: TreeMap, nodes: wp.array2d(dtype=wp.int32), dm: wp.array2d(dtype=wp.float32),
             level_of: wp.array(dtype=wp.int32), bad: wp.array(dtype=wp.int32), out_split: wp.array2d(dtype=wp.int32),
             nn: int, ns: int) -> wp.vec3i:
    """The 2:1 balance: every pass splits at once the leaves with a neighbour more than one level finer, their
    four children joining the tiling and the tree map. Returns (nodes of the tiling, split nodes, forced
    splits)."""
    forced = int(0)
    for _ in range(4 * (qt.depth + 1) + 8):
        nb = int(0)
        for j in range(nn):
            if nodes[j, 3] == 4 or nodes[j, 3] == 5:  # alive, inside the grid
                e = edge_levels(tree, level_of, nodes[j, 0], nodes[j, 1], nodes[j, 2], qt.depth, qt.roots[1])
                if wp.max(wp.max(e[0], e[1]), wp.max(e[2], e[3])) > nodes[j, 0] + 1:
                    bad[nb] = j
                    nb += 1
        if nb == 0:
            break
        forced += nb
        for b in range(nb):
            j = bad[b]
            lv = nodes[j, 0]
            nodes[j, 3] = nodes[j, 3] & 3  # no longer alive
            out_split[ns, 0] = lv
            out_split[ns, 1] = nodes[j, 1]
            out_split[ns, 2] = nodes[j, 2]
            ns += 1
            tree.dense[_cell_of(qt, lv, nodes[j, 1], nodes[j, 2])] = -1
            cnt = qt.inside[lv + 1]
            for c in range(4):
                x = 2 * nodes[j, 1] + c % 2
                y = 2 * nodes[j, 2] + c / 2
                flags = int(4)
                if not is_inside(cnt, x, y):
                    flags = 6
                _add_node(nodes, dm, nn, lv + 1, x, y, flags, 0.0, 0.0)
                level_of[nn] = lv + 1
                tree.dense[_cell_of(qt, lv + 1, x, y)] = nn + 1
                nn += 1
    return wp.vec3i(nn, ns, forced)


@wp.func
def _children_stats(qt: QuadTree, rel: wp.vec3, planes: wp.array(dtype=wp.vec4), code: int, focal: float,
                    nodes: wp.array2d(dtype=wp.int32), dm: wp.array2d(dtype=wp.float32), first: int, nn: int):
    """The balance's children (tiling nodes ``first`` on) that stayed leaves: their own culling, distance and
    metric (the policy's ``code``)."""
    for j in range(first, nn):
        if nodes[j, 3] >= 4:
            culled, dist, metric = _evaluate_node(qt, nodes[j, 0], nodes[j, 1], nodes[j, 2], rel, planes, code, focal)
            nodes[j, 3] = nodes[j, 3] | culled
            dm[j, 0] = dist
            dm[j, 1] = metric


@wp.func
def _emit_leaves(qt: QuadTree, tree: TreeMap, nodes: wp.array2d(dtype=wp.int32), dm: wp.array2d(dtype=wp.float32),
                 level_of: wp.array(dtype=wp.int32), nn: int, out_patch: wp.array2d(dtype=wp.int32),
                 out_f: wp.array2d(dtype=wp.float32), out_key: wp.array(dtype=wp.int64)) -> wp.vec3i:
    """The drawn leaves (inside the grid, not culled) with their neighbours' levels (-1 outside the grid), distance,
    metric, geometric error and key, in tiling order (the host puts them in key order). Returns (leaves drawn,
    leaves, culled leaves)."""
    leaves = int(0)
    culled_leaves = int(0)
    for j in range(nn):  # level_of for the patches' neighbours: -1 outside the grid
        f = nodes[j, 3]
        if f >= 4 and (f & 2) == 0:
            leaves += 1
            culled_leaves += f & 1
        if (f & 2) != 0:
            level_of[j] = -1
    q = int(0)
    for j in range(nn):
        if nodes[j, 3] == 4:
            lv = nodes[j, 0]
            x = nodes[j, 1]
            y = nodes[j, 2]
            e = edge_levels(tree, level_of, lv, x, y, qt.depth, qt.roots[1])
            out_patch[q, 0] = lv
            out_patch[q, 1] = x
            out_patch[q, 2] = y
            for k in range(4):
                out_patch[q, 3 + k] = e[k]
            out_f[q, 0] = dm[j, 0]
            out_f[q, 1] = dm[j, 1]
            out_f[q, 2] = qt.herr[node_index(qt, lv, x, y)]
            out_key[q] = _tile_key(lv, x, y)
            q += 1
    return wp.vec3i(q, leaves, culled_leaves)


@wp.kernel(enable_backward=False)
def _quadtree_select_kernel(
    qt: QuadTree,
    eye: wp.array(dtype=wp.vec3),
    planes: wp.array(dtype=wp.vec4),
    thresholds: wp.array(dtype=wp.float32),
    params: wp.array(dtype=wp.float32),
    ints: wp.array(dtype=wp.int32),
    prev: wp.array(dtype=wp.int64),
    front: wp.array3d(dtype=wp.int32),
    code: wp.array(dtype=wp.int32),
    tree: TreeMap,
    nodes: wp.array2d(dtype=wp.int32),
    dm: wp.array2d(dtype=wp.float32),
    level_of: wp.array(dtype=wp.int32),
    bad: wp.array(dtype=wp.int32),
    # outputs
    out_patch: wp.array2d(dtype=wp.int32),
    out_f: wp.array2d(dtype=wp.float32),
    out_split: wp.array2d(dtype=wp.int32),
    out_key: wp.array(dtype=wp.int64),
    out_n: wp.array(dtype=wp.int64),
):
    """One thread: the descent (:func:`_descend`), the 2:1 balance (:func:`_balance`) and its children's stats, and
    the drawn leaves and their keys with their neighbours' levels (:func:`_emit_leaves`); see
    :meth:`QuadtreeWalk.select`. ``params``: focal px, hysteresis; ``ints``: policy code (0 distance, 1 screen
    error), the fixed level of the continuous policy (-1 none), the previous frame's split keys (in ``prev``,
    sorted). The tree map is all 0 on entry and is left all 0."""
    rel = eye[0]
    d = _descend(qt, rel, planes, thresholds, params, ints, prev, front, code, tree, nodes, dm, out_split)
    nn = d[0]
    for j in range(nn):
        tree.dense[_cell_of(qt, nodes[j, 0], nodes[j, 1], nodes[j, 2])] = j + 1
        level_of[j] = nodes[j, 0]
    b = _balance(qt, tree, nodes, dm, level_of, bad, out_split, nn, d[1])
    ccode = ints[0]
    if ints[1] >= 0:
        ccode = 0
    _children_stats(qt, rel, planes, ccode, params[0], nodes, dm, nn, b[0])
    nn = b[0]
    ns = b[1]
    e = _emit_leaves(qt, tree, nodes, dm, level_of, nn, out_patch, out_f, out_key)
    for j in range(nn):  # the map all 0 again
        tree.dense[_cell_of(qt, nodes[j, 0], nodes[j, 1], nodes[j, 2])] = 0
    for j in range(ns):
        tree.dense[_cell_of(qt, out_split[j, 0], out_split[j, 1], out_split[j, 2])] = 0
    out_n[0] = wp.int64(e[0])
    out_n[1] = wp.int64(d[2])
    out_n[2] = wp.int64(e[1])
    out_n[3] = wp.int64(e[2])
    out_n[4] = wp.int64(b[2])
    out_n[5] = wp.int64(ns)


class QuadtreeWalk(TreeWalk):
    """The quadtree policies' selection (:func:`terrainwarp.lod.select`) over one in-memory terrain with a dense
    tree map, in one launch (see :class:`TreeWalk`)."""

    def __init__(self, stats: list, inside: np.ndarray, roots: tuple[int, int], sizes: list[tuple[float, float]],
                 device: str = "cpu") -> None:
        super().__init__(stats, inside, roots, sizes, device)
        depth = self.levels - 1
        self.tree_map = TreeMapHost(roots, depth, device)
        if self.tree_map.sparse:
            raise ValueError("roots, depth: the complete tree is too deep for a dense tree map")
        cells = self.tree_map.cells
        inputs = [empty(1, wp.vec3, device), empty(6, wp.vec4, device), empty(self.levels, wp.float32, device),
                  empty(2, wp.float32, device), empty(3, wp.int32, device), empty(cells, wp.int64, device)]
        self._args = [*inputs, *self._frontier(cells), self.tree_map.view(),
                      wp.empty((cells, 4), dtype=wp.int32, device=device),
                      wp.empty((cells, 2), dtype=wp.float32, device=device),
                      wp.empty(cells, dtype=wp.int32, device=device), wp.empty(cells, dtype=wp.int32, device=device)]
        self._record(_quadtree_select_kernel, inputs, [
            empty((cells, 7), wp.int32, device), empty((cells, 3), wp.float32, device),
            empty((cells, 3), wp.int32, device), empty(cells, wp.int64, device), empty(6, wp.int64, device)])

    def select(self, rel_origin: tuple[float, float, float], planes: np.ndarray, thresholds: np.ndarray,
               focal_px: float, hysteresis: float, code: int, fixed_level: int,
               prev_split: np.ndarray) -> tuple[np.ndarray, ...]:
        """The selection for one camera, as :func:`terrainwarp.lod.select` makes it: the descent from the roots
        (per level: nodes outside the grid are leaves that only complete the tiling; the others split by the
        policy, ``code`` 0 distance below ``thresholds[level]`` or 1 screen error above it, with hysteresis
        against the keys of ``prev_split`` (sorted); culled nodes and the deepest level do not split;
        ``fixed_level`` >= 0: every node splits down to it, the continuous policy), then the 2:1 balance (pass
        after pass, every leaf with a neighbour more than one level finer split at once), then the stats of the
        balance's children.

        Returns:
            level, x, y (P,) int32 of the drawn leaves (inside the grid, not culled) in key order, their
            neighbours' levels (P, 4) int32 (-1 beyond the grid), distance, metric and geometric error (P,)
            float32, their keys (P,) int64 (level << 58 | y << 29 | x); the split nodes' (level, x, y) (S, 3)
            int32; and nodes visited, leaves, culled leaves, forced splits.
        """
        prev = np.asarray(prev_split, np.int64)
        with self._lock:
            n_prev = len(prev)
            host = self._host_in if self._cpu else None
            if host is not None:
                host[5][:n_prev] = prev
                vals = [rel_origin, planes, thresholds, (focal_px, hysteresis), (code, fixed_level, n_prev), host[5]]
            else:
                buf = np.zeros(self.tree_map.cells, np.int64)
                buf[:n_prev] = prev
                vals = [rel_origin, planes, thresholds, (focal_px, hysteresis), (code, fixed_level, n_prev), buf]
            patch, f, split, key, n = self._run(vals)
            q, ns = int(n[0]), int(n[5])
            order = np.argsort(key[:q])  # key order (the keys are distinct)
            # the columns in key order, each a contiguous row of one gathered copy: few numpy calls (each costs
            # microseconds right after a launch, whatever its size)
            cols, fc = np.take(patch.T, order, axis=1), np.take(f.T, order, axis=1)
            return (cols[0], cols[1], cols[2], patch[order, 3:7], fc[0], fc[1], fc[2], key[order], split[:ns].copy(),
                    int(n[1]), int(n[2]), int(n[3]), int(n[4]))

"""Quadtree LOD selection: terrain pyramids, policies, hysteresis, 2:1 balance, neighbours, edge factors
and frustum culling.

The quadtree has a grid of ``nx x nz`` root nodes (deaconu2021 tests 4, 16, 32 and 64 roots). Every
node is a square patch of ``S_L = S_0 / 2**L`` heightmap cells, tessellated with level ``T`` (its own
resolution: T segments per side). ``S_0 = T * 2**D`` is chosen so that the deepest level D draws one
vertex per heightmap sample and the roots cover the grid; parts of patches beyond the grid are
clamped to its border by the displacement stage.

Keys follow the zoom/x/y tile scheme of malafeev2014 (figures 6-7): ``zoom`` is the level, ``x`` the
column of the tile among the ``nx * 2**zoom`` of its level, ``y`` the row (along +z). They pack into one
int64 (``zoom << 58 | y << 29 | x``) and round-trip (:func:`tile_key`, :func:`tile_from_key`).

Selection runs level by level: one kernel launch evaluates every candidate node of a level (distance,
frustum, policy), children of split nodes become the next level's candidates. Then the tree is made
**restricted** (2:1 balanced): a leaf with a neighbour more than one level finer is split, repeated
until stable. We chose the restricted tree over the unrestricted O(log n) parent/child search of
deaconu2021 ("Finding edges at the border") because the edge-factor rule (double the factor toward a
finer neighbour) is only crack-free when neighbours differ by at most one level. Neighbour levels are
found in a tree map (:func:`terrainwarp.kernels.lod.tree_map`: one cell per node of every level, laid out
like the terrain's pyramids, holding leaf / split / not in the tree): the node just across an edge at the
leaf's own level is one lookup, and the leaf containing a probe cell is a short walk down or up from
there, so a balance pass and the neighbour levels are linear in the leaves (a kernel launch each).

Edge factors: with a constant tessellation level T, every edge gets T, and an edge whose neighbour is
finer gets 2T (deaconu2021, "Finding edges at the border", figure 7), so both sides place the same
vertices; hence T <= 32. Continuous factors (for fractional spacing) are computed per edge from the
edge's own endpoints only (length / distance of the edge midpoint), so the two patches that share an
edge compute the same value bit for bit; they are offered on a single-level patch grid
(:class:`ContinuousPolicy`), where no level change breaks the vertex match. The policies and the
continuous factor rule live in :mod:`.policies`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from ..camera import Camera, relative_origin
from ..heightmap import Heightmap, StreamedHeightmap
from ..io.files import write_text
from ..kernels.checks import check_device, check_int
from ..kernels.lod import (
    DENSE_MAX_CELLS,
    QuadtreeWalk,
    TreeMapHost,
    mark_nodes,
    neighbour_levels,
    select_level,
    tree_cells,
    tree_leaves,
    tree_map,
)
from ..kernels.pyramid import node_stats
from ..scene import check_roots, check_tess
from .policies import (
    MAX_TESS,
    ContinuousPolicy,
    DistancePolicy,
    Policy,
    ScreenErrorPolicy,
    check_policy,
    continuous_factors,
    edge_pixels,
)
from .streaming import StreamedPyramid

__all__ = ["Terrain", "DistancePolicy", "ScreenErrorPolicy", "ContinuousPolicy", "PatchList", "LodState",
           "NodeMetrics", "node_metrics",
           "select", "uniform_patches", "tile_key", "tile_from_key", "tile_name", "MAX_TESS"]

_ZOOM_SHIFT = 58
_Y_SHIFT = 29
_MASK29 = (1 << 29) - 1


# ------------------------------------------------------------------------------------------------
# keys
# ------------------------------------------------------------------------------------------------
def tile_key(zoom, x, y):
    """Pack zoom/x/y tile coordinates (scalars or arrays) into int64 keys."""
    z = np.asarray(zoom, dtype=np.int64)
    xx = np.asarray(x, dtype=np.int64)
    yy = np.asarray(y, dtype=np.int64)
    if np.any(z < 0) or np.any(z > 31) or np.any(xx < 0) or np.any(yy < 0) or np.any(xx > _MASK29) \
            or np.any(yy > _MASK29):
        raise ValueError("tile_key: expected 0 <= zoom <= 31 and 0 <= x, y < 2**29")
    k = (z << _ZOOM_SHIFT) | (yy << _Y_SHIFT) | xx
    return k if k.ndim else int(k)


def tile_from_key(key):
    """Inverse of :func:`tile_key`: (zoom, x, y)."""
    k = np.asarray(key, dtype=np.int64)
    z, x, y = k >> _ZOOM_SHIFT, k & _MASK29, (k >> _Y_SHIFT) & _MASK29
    if k.ndim == 0:
        return int(z), int(x), int(y)
    return z, x, y


def tile_name(key: int) -> str:
    """The ``zoom/x/y`` name of a key (as in an OSM tile URL)."""
    z, x, y = tile_from_key(int(key))
    return f"{z}/{x}/{y}"


# ------------------------------------------------------------------------------------------------
# terrain (precomputed once per heightmap)
# ------------------------------------------------------------------------------------------------
def _roots_shape(roots: int | tuple[int, int], shape: tuple[int, int]) -> tuple[int, int]:
    check_roots(roots)  # the one rule (terrainwarp.scene): >= 1, or (nx, nz) each >= 1
    if isinstance(roots, tuple | list):
        return int(roots[0]), int(roots[1])
    n = int(roots)
    # the factorisation nx * nz = n closest to the grid's aspect ratio (wider along the longer axis)
    aspect = (shape[1] - 1) / max(shape[0] - 1, 1)
    best = min(((a, n // a) for a in range(1, n + 1) if n % a == 0),
               key=lambda p: abs(math.log(p[0] / p[1]) - math.log(max(aspect, 1e-9))))
    return best


def layout(shape: tuple[int, int], roots: int | tuple[int, int], tess: int,
           depth: int | None) -> tuple[tuple[int, int], int, float]:
    """((nx, nz) roots, depth D, root side S_0 in cells) of a quadtree over a (rows, cols) grid (see
    :meth:`Terrain.prepare`)."""
    check_tess(tess)  # the one rule (terrainwarp.scene); a quadtree's doubled edges are checked in select
    hh, ww = shape
    nx, nz = _roots_shape(roots, (hh, ww))
    need = max((ww - 1) / nx, (hh - 1) / nz, 1e-9)
    if depth is None:
        depth = max(0, math.ceil(math.log2(max(need / tess, 1.0)) - 1e-12))
    depth = check_int("depth", depth, 0, 20)
    root_cells = float(tess) * 2.0 ** depth
    if root_cells < need:  # an explicit, too-small depth: grow the patches to cover the grid
        root_cells = need
    return (nx, nz), depth, root_cells


@dataclass(frozen=True, eq=False)
class Terrain:
    """A heightmap prepared for LOD selection: the quadtree layout and per-node pyramids.

    Attributes:
        heightmap: the source.
        roots: (nx, nz) root nodes.
        tess: tessellation level T of every patch (its own resolution).
        depth: deepest level D.
        root_cells: S_0, the side of a root node in cells.
        stats: per level (min, max, geometric error) arrays of shape (nz * 2**L, nx * 2**L) float32.
        time_ms: time spent building the pyramids.
    """

    heightmap: Heightmap
    roots: tuple[int, int]
    tess: int
    depth: int
    root_cells: float
    stats: list = field(repr=False)
    time_ms: float = 0.0
    _dev: dict = field(default_factory=dict, repr=False)
    provider: Any = field(default=None, repr=False)

    @classmethod
    def prepare(cls, heightmap: Heightmap, roots: int | tuple[int, int] = 16, tess: int = 32,
                depth: int | None = None, device: str = "cpu") -> Terrain:
        """Build the quadtree layout and its min/max/geometric-error pyramids (Warp kernels).

        Args:
            roots: number of root nodes (factorised to the grid's aspect) or (nx, nz).
            tess: tessellation level T of every patch, 1..64.
            depth: deepest level; default: the smallest D with roots * T * 2**D cells covering the grid
                (one vertex per sample at level D).
        """
        check_device("device", device)
        if isinstance(heightmap, StreamedHeightmap):
            return cls.prepare_streamed(heightmap, roots=roots, tess=tess, depth=depth, device=device)
        if not isinstance(heightmap, Heightmap):
            raise TypeError(f"heightmap: expected a Heightmap, got {type(heightmap).__name__}")
        (nx, nz), depth, root_cells = layout(heightmap.shape, roots, tess, depth)
        t0 = time.perf_counter()
        stats = node_stats(heightmap.heights, (nx, nz), root_cells, depth, int(tess), device=device)
        return cls(heightmap, (nx, nz), int(tess), depth, root_cells, stats, (time.perf_counter() - t0) * 1e3)

    @classmethod
    def prepare_streamed(cls, heightmap: StreamedHeightmap, roots: int | tuple[int, int] = 16, tess: int = 32,
                         depth: int | None = None, device: str = "cpu", *, exact: bool | None = None,
                         progress: Callable[[int], None] | None = None, map: Callable | None = None) -> Terrain:
        """A streamed heightmap's quadtree: its pyramids come from a :class:`.streaming.StreamedPyramid`
        (exact and cached beside a file, or worked out on demand for the nodes a selection visits).

        Args:
            exact: force (True) or refuse (False) the exact pyramid built root by root; default: exact
                when the source cannot bound its overviews (files), on demand otherwise (procedural).
            progress: called with 1 per root while an exact pyramid is built.
            map: build the exact pyramid's roots on workers, e.g. ``Runner(workers=4).map`` (the sweeps' Dask
                runner); the values are the same as in this process.
        """
        if not isinstance(heightmap, StreamedHeightmap):
            raise TypeError(f"heightmap: expected a StreamedHeightmap, got {type(heightmap).__name__}")
        (nx, nz), depth, root_cells = layout(heightmap.shape, roots, tess, depth)
        t0 = time.perf_counter()
        pyr = StreamedPyramid(heightmap, (nx, nz), root_cells, depth, int(tess), exact=exact, device=device,
                              progress=progress, map=map)
        return cls(heightmap, (nx, nz), int(tess), depth, root_cells, [], (time.perf_counter() - t0) * 1e3,
                   provider=pyr)

    @property
    def n_leaves_full(self) -> int:
        """Leaves of the complete tree (every node split to depth D)."""
        return self.roots[0] * self.roots[1] * 4 ** self.depth

    def node_size_world(self, level: int) -> tuple[float, float]:
        s = self.root_cells / 2.0 ** level
        return (s * self.heightmap.dx, s * self.heightmap.dz)

    def cached(self, key: object, make: Callable[[], object]) -> object:
        """The value kept under ``key`` (a normal map, device arrays), made by ``make()`` on first use.

        What persists between frames lives here, in the object the caller holds, never in module state."""
        if key not in self._dev:
            self._dev[key] = make()
        return self._dev[key]

    def is_cached(self, key: object) -> bool:
        return key in self._dev

    def stats_at(self, level: int, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(min, max, geometric error) of nodes (level, x, y), each (N,) float32: gathered from the pyramids,
        or, for a streamed heightmap, worked out for just these nodes by its provider (:mod:`.streaming`)."""
        if self.provider is not None:
            return self.provider.stats_at(int(level), np.asarray(x), np.asarray(y))
        mn, mx, er = self.stats[int(level)]
        return mn[y, x], mx[y, x], er[y, x]

    def inside(self, level: int, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """True for nodes whose origin lies inside the sample grid (others are never drawn)."""
        return _inside_many(self, int(level), x, y)

    def inside_counts(self) -> np.ndarray:
        """(depth + 1, 2) int64: per level, the columns and rows of nodes whose origin lies inside the grid
        (:meth:`inside` is ``x < columns and y < rows``, or the first root)."""
        return self.cached("inside_counts", lambda: _inside_counts(self))


# ------------------------------------------------------------------------------------------------
# selection result
# ------------------------------------------------------------------------------------------------
class PatchList(NamedTuple):
    """The selected, visible patches of a frame as a structure of arrays (P patches).

    Attributes:
        level: (P,) int32 quadtree level.
        key: (P,) int64 zoom/x/y key.
        origin: (P, 2) float64 world (x, z) of the patch's corner (u = v = 0).
        size: (P, 2) float64 world extent (x, z).
        origin_cells: (P, 2) float32 (column, row) of the corner in heightmap samples.
        size_cells: (P,) float32 side in cells.
        outer: (P, 4) float32 outer tessellation levels, OpenGL order (u=0, v=0, u=1, v=1 edges:
            west, north, east, south).
        inner: (P, 2) float32 inner levels (along u = x, along v = z).
        neighbour_level: (P, 4) int32 level of the leaf across each edge (-1: terrain border).
        distance: (P,) float32 eye-to-box distance, metres.
        metric: (P,) float32 what the policy compared: distance (m) or screen error (px).
        geometric_error: (P,) float32 metres.
        stats: counters (nodes visited, leaves, culled, forced splits, ...).
    """

    level: np.ndarray
    key: np.ndarray
    origin: np.ndarray
    size: np.ndarray
    origin_cells: np.ndarray
    size_cells: np.ndarray
    outer: np.ndarray
    inner: np.ndarray
    neighbour_level: np.ndarray
    distance: np.ndarray
    metric: np.ndarray
    geometric_error: np.ndarray
    stats: dict

    def __len__(self) -> int:  # type: ignore[override]
        return int(self.level.shape[0])

    def to_csv(self, path: str | Path) -> None:
        head = ("key,zoom_x_y,level,origin_x,origin_z,size_x,size_z,outer0,outer1,outer2,outer3,inner0,inner1,"
                "nbr0,nbr1,nbr2,nbr3,distance,metric,geometric_error")
        lines = [head]
        for i in range(len(self)):
            lines.append(",".join([str(int(self.key[i])), tile_name(int(self.key[i])), str(int(self.level[i])),
                                   *(f"{v:.6f}" for v in self.origin[i]), *(f"{v:.6f}" for v in self.size[i]),
                                   *(f"{v:g}" for v in self.outer[i]), *(f"{v:g}" for v in self.inner[i]),
                                   *(str(int(v)) for v in self.neighbour_level[i]),
                                   f"{self.distance[i]:.6g}", f"{self.metric[i]:.6g}",
                                   f"{self.geometric_error[i]:.6g}"]))
        write_text(path, "\n".join(lines) + "\n")


@dataclass
class LodState:
    """What persists between frames for hysteresis: the sorted keys of the previous frame's split
    nodes. The caller holds it and passes it to :func:`select` frame after frame."""

    split_keys: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    frames: int = 0


# ------------------------------------------------------------------------------------------------
# selection
# ------------------------------------------------------------------------------------------------
class _View(NamedTuple):
    """A camera as the selection kernel takes it: the heightmap origin relative to the eye, the frustum."""

    rel_origin: tuple[float, float, float]
    planes: np.ndarray
    focal_px: float


def _view(terrain: Terrain, camera: Camera) -> _View:
    rel = relative_origin(terrain.heightmap.origin, camera.position)
    return _View(rel, camera.frustum_planes(), camera.focal_px)


class _Nodes(NamedTuple):
    """Leaves of the tiling being built (structure of arrays): level, x, y, eye distance, policy metric,
    frustum-culled, outside the sample grid (never drawn; they only complete the tiling), and alive (a
    leaf the balance split stays in place, not alive, so that indices into the arrays never move)."""

    level: np.ndarray
    x: np.ndarray
    y: np.ndarray
    dist: np.ndarray
    metric: np.ndarray
    culled: np.ndarray
    outside: np.ndarray
    alive: np.ndarray

    def split(self, split: np.ndarray, children: _Nodes) -> _Nodes:
        """These nodes with the ``split`` ones no longer alive, followed by ``children``."""
        kept = self._replace(alive=self.alive & ~split)
        return _Nodes(*(np.concatenate([a, b]) for a, b in zip(kept, children)))


class _Tree(NamedTuple):
    """The leaves and the tree map (:func:`terrainwarp.kernels.lod.tree_map`) that locates them."""

    nodes: _Nodes
    map: TreeMapHost
    roots: tuple[int, int]
    depth: int

    def neighbour_levels(self, level_of: np.ndarray, idx: np.ndarray | None = None) -> np.ndarray:
        """(n, 4) largest ``level_of`` of the leaves across each edge of every node, or of nodes ``idx``
        (-1: beyond the roots)."""
        n = self.nodes
        lv, x, y = (n.level, n.x, n.y) if idx is None else (n.level[idx], n.x[idx], n.y[idx])
        return neighbour_levels(self.map, self.roots, self.depth, lv, x, y, level_of)

    def key_order(self, mask: np.ndarray) -> np.ndarray:
        """Indices of the nodes in ``mask`` (leaves) sorted by key: read off the map when it is small
        beside the leaves (level by level, row-major), else sorted."""
        n = self.nodes
        if not self.map.sparse and len(self.map) <= 8 * len(n.level):
            order = tree_leaves(self.map, self.roots, self.depth)
            return order[mask[order]]
        idx = np.flatnonzero(mask)
        return idx[np.argsort(tile_key(n.level[idx], n.x[idx], n.y[idx]), kind="stable")]

    def split(self, split: np.ndarray, children: _Nodes) -> _Tree:
        """Split leaves ``split`` into ``children`` (appended), in the arrays and in the map."""
        n = self.nodes
        mark_nodes(self.map, self.roots, n.level[split], n.x[split], n.y[split], -1)
        first = len(n.level) + 1
        mark_nodes(self.map, self.roots, children.level, children.x, children.y,
                   np.arange(first, first + len(children.level), dtype=np.int32))
        return self._replace(nodes=n.split(split, children))


def _children(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The four children of each node (x, y), quadrant by quadrant."""
    return (np.concatenate([2 * x, 2 * x + 1, 2 * x, 2 * x + 1]),
            np.concatenate([2 * y, 2 * y, 2 * y + 1, 2 * y + 1]))


def _root_grid(terrain: Terrain) -> tuple[np.ndarray, np.ndarray]:
    nx, nz = terrain.roots
    x, y = np.meshgrid(np.arange(nx, dtype=np.int32), np.arange(nz, dtype=np.int32))
    return x.reshape(-1), y.reshape(-1)


def select(terrain: Terrain, camera: Camera, policy: Policy | None = None, state: LodState | None = None,
           device: str = "cpu") -> PatchList:
    """Select the visible patches of a frame: the descent from the roots, the 2:1 balance, the neighbours' levels
    and the edge factors; in one launch for an in-memory terrain whose complete tree fits a dense tree map
    (:class:`terrainwarp.kernels.lod.QuadtreeWalk`), else level by level (a streamed terrain); the same patches
    either way.

    Args:
        terrain: the prepared terrain (:meth:`Terrain.prepare`).
        camera: the frame's camera.
        policy: :class:`DistancePolicy`, :class:`ScreenErrorPolicy` (default, 1 px) or
            :class:`ContinuousPolicy` (``make_policy(scene.lod)`` for a scene's).
        state: hysteresis state from the previous frame (updated in place), or None.

    Returns:
        A :class:`PatchList` of the visible leaves, with edge factors that never crack.
    """
    if not isinstance(terrain, Terrain):
        raise TypeError(f"terrain: expected a Terrain (Terrain.prepare(heightmap)), got {type(terrain).__name__}")
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a Camera, got {type(camera).__name__}")
    policy = ScreenErrorPolicy() if policy is None else policy
    check_policy(policy)
    view = _view(terrain, camera)
    prev = state.split_keys if (state is not None and policy.hysteresis > 0) else np.zeros(0, np.int64)
    if terrain.provider is None and tree_cells(terrain.roots, terrain.depth) <= DENSE_MAX_CELLS:
        return _select_in_one_launch(terrain, camera, view, policy, prev, state, device)
    tree, split_keys, visited = _descend(terrain, view, policy, prev, device)
    tree, forced = _balance(terrain, view, policy, tree, split_keys, device)
    if state is not None:
        sk = np.concatenate(split_keys) if split_keys else np.zeros(0, np.int64)
        state.split_keys = np.unique(sk)
        state.frames += 1
    return _patch_list(terrain, camera, policy, tree, {"nodes_visited": visited, "forced_splits": forced})


def _select_in_one_launch(terrain: Terrain, camera: Camera, view: _View, policy: Policy, prev: np.ndarray,
                          state: LodState | None, device: str) -> PatchList:
    """:func:`select` for an in-memory terrain whose complete tree fits a dense tree map: the descent, the
    balance and the drawn leaves in key order in one launch (:class:`terrainwarp.kernels.lod.QuadtreeWalk`),
    the same patches as :func:`_descend`, :func:`_balance` and :func:`_patch_list` make."""
    depth = terrain.depth
    walk = terrain.cached(("quadtree_walk", device), lambda: QuadtreeWalk(
        terrain.stats, terrain.inside_counts(), terrain.roots, [terrain.node_size_world(lv) for lv in range(depth + 1)],
        device=device))
    continuous = isinstance(policy, ContinuousPolicy)
    thresholds = np.array([0.0 if continuous else policy.threshold(lv, max(terrain.node_size_world(lv)))
                           for lv in range(depth + 1)], np.float32)
    level, lx, ly, nbr, dist, metric, err, keys, split, visited, leaves, culled, forced = walk.select(
        view.rel_origin, view.planes, thresholds, view.focal_px, float(policy.hysteresis),
        0 if continuous else policy.code, min(policy.level, depth) if continuous else -1, prev)
    if state is not None:
        state.split_keys = np.unique(tile_key(split[:, 0], split[:, 1], split[:, 2]))
        state.frames += 1
    return _assemble(terrain, camera, policy, level, lx, ly, dist, metric, nbr, err,
                     {"nodes_visited": visited, "leaves": leaves, "culled": culled, "forced_splits": forced}, keys)


def _descend(terrain: Terrain, view: _View, policy: Policy, prev: np.ndarray,
             device: str) -> tuple[_Tree, list[np.ndarray], int]:
    """Level by level from the roots: one launch evaluates every candidate node of a level (distance,
    frustum, policy); children of split nodes are the next level's candidates. Candidates outside the
    grid are leaves too (never drawn, deciding nothing): with them the leaves tile the root grid, so
    that point location works everywhere.

    Returns the tree (leaves and map), the keys of the split nodes (one array per level) and the number
    of (inside) nodes visited."""
    depth = terrain.depth
    fixed_level = min(policy.level, depth) if isinstance(policy, ContinuousPolicy) else None
    parts, outside, inner, split_keys, visited = [], [], [], [], 0
    x, y = _root_grid(terrain)
    for lvl in range(depth + 1):
        keep = terrain.inside(lvl, x, y)
        outside.append((lvl, x[~keep], y[~keep]))
        x, y = x[keep], y[keep]
        if len(x) == 0:
            break
        visited += len(x)
        size = terrain.node_size_world(lvl)
        if fixed_level is not None:
            can, thr, code = lvl < fixed_level, 0.0, 0
        else:
            can, thr, code = lvl < depth, policy.threshold(lvl, max(size)), policy.code
        keys = tile_key(np.full(len(x), lvl), x, y) if len(prev) else None
        sp, cu, di, me = _evaluate(terrain, lvl, x, y, keys, view, code, thr, policy.hysteresis, can, prev, device)
        if fixed_level is not None and lvl < fixed_level:
            sp = np.ones_like(sp)  # a uniform grid: everything splits down to the level
        split = sp.astype(bool)
        split_keys.append(tile_key(np.full(int(split.sum()), lvl), x[split], y[split]))
        inner.append((lvl, x[split], y[split]))
        leaf = ~split
        n = int(leaf.sum())
        parts.append((np.full(n, lvl, np.int32), x[leaf], y[leaf], di[leaf], me[leaf], cu[leaf].astype(bool),
                      np.zeros(n, bool)))
        x, y = _children(x[split], y[split])
    for lvl, ox, oy in outside:
        parts.append((np.full(len(ox), lvl, np.int32), ox, oy, np.zeros(len(ox), np.float32),
                      np.zeros(len(ox), np.float32), np.ones(len(ox), bool), np.ones(len(ox), bool)))
    nodes = _Nodes(*(np.concatenate(a) for a in zip(*parts)), np.ones(sum(len(p[0]) for p in parts), bool))
    # one launch marks every node: the leaves with their index + 1, the split nodes with -1
    sl = [np.full(len(sx), lv, np.int32) for lv, sx, _ in inner]
    tmap = tree_map(terrain.roots, depth, device)
    mark_nodes(tmap, terrain.roots, np.concatenate([nodes.level, *sl]),
               np.concatenate([nodes.x, *(sx for _, sx, _ in inner)]),
               np.concatenate([nodes.y, *(sy for _, _, sy in inner)]),
               np.concatenate([np.arange(1, len(nodes.level) + 1, dtype=np.int32),
                               np.full(sum(len(a) for a in sl), -1, np.int32)]))
    return _Tree(nodes, tmap, terrain.roots, depth), split_keys, visited


def _balance(terrain: Terrain, view: _View, policy: Policy, tree: _Tree, split_keys: list[np.ndarray],
             device: str) -> tuple[_Tree, int]:
    """2:1 balance: split leaves that have a neighbour more than one level finer, until stable (appends
    the keys of the nodes it splits to ``split_keys``). Returns the balanced tree and the number of
    forced splits."""
    forced = 0
    first_child = len(tree.nodes.level)
    for _ in range(4 * (terrain.depth + 1) + 8):  # terminates: each pass only splits, and depth is bounded
        nodes = tree.nodes
        nbr = tree.neighbour_levels(nodes.level)
        bad = (nbr.max(axis=1) > nodes.level + 1) & ~nodes.outside & nodes.alive
        if not bad.any():
            break
        forced += int(bad.sum())
        bl, bx, by = nodes.level[bad], nodes.x[bad], nodes.y[bad]
        nl = np.concatenate([bl + 1] * 4)
        nxs, nys = _children(bx, by)
        split_keys.append(tile_key(bl, bx, by))
        zero = np.zeros(len(nl), np.float32)  # distance, metric and culling: worked out once, below
        tree = tree.split(bad, _Nodes(nl, nxs, nys, zero, zero, np.zeros(len(nl), bool),
                                      ~_inside_many(terrain, nl, nxs, nys), np.ones(len(nl), bool)))
    # The passes read only levels, the grid's extent and which leaves are alive, so the children's stats are
    # worked out once for the children that stayed leaves (one launch per level, not per pass and level, and
    # none for a child a later pass split again): each node's stats are its own, whatever the batch.
    nodes = tree.nodes
    new = first_child + np.flatnonzero(nodes.alive[first_child:])
    if len(new):
        nd, nm, nc = _child_stats(terrain, view, nodes.level[new], nodes.x[new], nodes.y[new], policy, device)
        nodes.dist[new], nodes.metric[new], nodes.culled[new] = nd, nm, nc
    return tree, forced


def _patch_list(terrain: Terrain, camera: Camera, policy: Policy, tree: _Tree, counts: dict) -> PatchList:
    """The drawn leaves (inside the grid, not culled) in key order, with their neighbours' levels, world
    extents and edge factors; ``counts``: the descent's ``nodes_visited`` and the balance's ``forced_splits``."""
    nodes = tree.nodes
    leaf = nodes.alive & ~nodes.outside
    drawn = leaf & ~nodes.culled
    n_culled = int((leaf & nodes.culled).sum())
    draw = tree.key_order(drawn)  # deterministic order: by key
    level, lx, ly, dist, metric = (a[draw] for a in (nodes.level, nodes.x, nodes.y, nodes.dist, nodes.metric))
    nbr = tree.neighbour_levels(np.where(nodes.outside, -1, nodes.level), draw)
    return _assemble(terrain, camera, policy, level, lx, ly, dist, metric, nbr, _gather_err(terrain, level, lx, ly),
                     {**counts, "leaves": int(leaf.sum()), "culled": n_culled})


def _assemble(terrain: Terrain, camera: Camera, policy: Policy, level: np.ndarray, lx: np.ndarray, ly: np.ndarray,
              dist: np.ndarray, metric: np.ndarray, nbr: np.ndarray, err: np.ndarray, counts: dict,
              keys: np.ndarray | None = None) -> PatchList:
    """The PatchList of the drawn leaves (key order): world extents and edge factors; ``counts``: nodes_visited,
    leaves, culled, forced_splits; ``keys``: their tile keys when known."""
    hm = terrain.heightmap
    nx, nz = terrain.roots
    if keys is None:
        keys = tile_key(level, lx, ly) if len(level) else np.zeros(0, np.int64)
    # a node's side in cells per level (root_cells / 2^level), the spacing and origin as columns: kept per terrain
    side, spacing, org = terrain.cached(("patch_extents",), lambda: (
        terrain.root_cells / np.exp2(np.arange(terrain.depth + 1, dtype=np.float64)), np.array([[hm.dx], [hm.dz]]),
        np.array([[hm.origin[0]], [hm.origin[1]]], np.float64)))
    s_cells = side[level]
    # as (2, P) rows (x, z), laid out (P, 2) at the end: few numpy calls (each costs microseconds right after a
    # launch), and no broadcast over a 2-item inner axis
    cells = np.array([lx, ly]) * s_cells
    origin, size = (cells * spacing + org).T.copy(), (spacing * s_cells).T.copy()
    origin_cells = cells.T.astype(np.float32, order="C")
    outer, inner = _edge_factors(terrain, camera, policy, level, nbr, origin, size)
    stats = {"nodes_visited": counts["nodes_visited"], "leaves": counts["leaves"], "culled": counts["culled"],
             "patches": int(len(level)), "forced_splits": counts["forced_splits"],
             "max_level": int(level.max()) if len(level) else -1, "roots": nx * nz, "depth": terrain.depth,
             "tess": terrain.tess}
    f32, i32 = {"dtype": np.float32, "copy": False}, {"dtype": np.int32, "copy": False}
    return PatchList(level.astype(**i32), keys.astype(np.int64, copy=False), origin, size,
                     origin_cells, s_cells.astype(**f32), outer.astype(**f32), inner.astype(**f32),
                     nbr.astype(**i32), dist.astype(**f32), metric.astype(**f32), err, stats)


def uniform_patches(terrain: Terrain, level: int, factor: float | None = None) -> PatchList:
    """Every node of one ``level`` inside the grid as a patch, none culled, each tessellated with ``factor`` on
    every edge and inside (default: the terrain's T): the surface a quadtree draws where that level is the leaf
    level (the fit's models measure it once per level, :mod:`terrainwarp.fit.probe`). Key order; ``distance``
    and ``metric`` 0; neighbour levels ``level`` (-1 at the grid's border)."""
    level = check_int("level", level, 0, terrain.depth)
    hm = terrain.heightmap
    f = np.float32(terrain.tess if factor is None else factor)
    cx, cy = terrain.inside_counts()[level]
    yy, xx = np.meshgrid(np.arange(cy, dtype=np.int64), np.arange(cx, dtype=np.int64), indexing="ij")
    lx, ly = xx.reshape(-1), yy.reshape(-1)
    lv = np.full(len(lx), level, np.int32)
    keys = tile_key(lv, lx, ly)
    order = np.argsort(keys, kind="stable")
    lx, ly, keys = lx[order], ly[order], keys[order]
    s = terrain.root_cells / 2.0 ** level
    origin_cells = np.stack([lx * s, ly * s], axis=1)
    origin = np.stack([hm.origin[0] + origin_cells[:, 0] * hm.dx, hm.origin[1] + origin_cells[:, 1] * hm.dz], 1)
    size = np.tile(np.array([[s * hm.dx, s * hm.dz]]), (len(lx), 1))
    # OpenGL edge order: u=0 (west), v=0 (north), u=1 (east), v=1 (south); -1 beyond the grid
    nbr = np.stack([np.where(lx > 0, level, -1), np.where(ly > 0, level, -1), np.where(lx < cx - 1, level, -1),
                    np.where(ly < cy - 1, level, -1)], 1).astype(np.int32)
    zero = np.zeros(len(lx), np.float32)
    return PatchList(lv, keys, origin, size, origin_cells.astype(np.float32), np.full(len(lx), s, np.float32),
                     np.full((len(lx), 4), f, np.float32), np.full((len(lx), 2), f, np.float32), nbr, zero, zero,
                     _gather_err(terrain, lv, lx, ly),
                     {"patches": len(lx), "leaves": len(lx), "depth": terrain.depth, "tess": terrain.tess})


def _edge_factors(terrain: Terrain, camera: Camera, policy: Policy, level: np.ndarray, nbr: np.ndarray,
                  origin: np.ndarray, size: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(outer (P, 4), inner (P, 2)) float32: the continuous rule of :mod:`.policies`, or the quadtree's
    constant level T with 2T on edges toward a finer neighbour (deaconu2021)."""
    if isinstance(policy, ContinuousPolicy):
        px = edge_pixels(terrain.heightmap, camera.position, camera.focal_px, origin, size)
        outer, inner = continuous_factors(px, policy.target_px)
        return outer.astype(np.float32), inner.astype(np.float32)
    t = float(terrain.tess)
    if t * 2 > MAX_TESS and (nbr > level[:, None]).any():
        raise ValueError(f"tess: {terrain.tess} doubled toward a finer neighbour exceeds the hardware maximum "
                         f"{MAX_TESS}: use tess <= {MAX_TESS // 2} with a quadtree (deaconu2021)")
    return (np.where(nbr > level[:, None], np.float32(2.0 * t), np.float32(t)),
            np.full((len(level), 2), t, np.float32))


def _inside_counts(terrain: Terrain) -> np.ndarray:
    """(depth + 1, 2): per level, how many columns and rows of nodes have their origin inside the grid,
    ``x * s < w - 1`` with ``s`` the node side in cells (float64, monotone in x: the first x that fails)."""
    hh, ww = terrain.heightmap.shape
    out = np.zeros((terrain.depth + 1, 2), np.int64)
    for lv in range(terrain.depth + 1):
        s = terrain.root_cells / 2.0 ** lv
        for k, lim in enumerate((ww - 1, hh - 1)):
            c = max(0, math.ceil(lim / s))
            while c > 0 and (c - 1) * s >= lim:
                c -= 1
            while c * s < lim:
                c += 1
            out[lv, k] = c
    return out


def _inside_many(terrain: Terrain, lv: int | np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """True for nodes (lv, x, y) whose origin lies inside the sample grid (and the first root always)."""
    c = terrain.inside_counts()[lv]
    return (x < c[..., 0]) & (y < c[..., 1]) | ((x == 0) & (y == 0))


def _evaluate(terrain: Terrain, lvl: int, x: np.ndarray, y: np.ndarray, keys: np.ndarray | None, view: _View,
              code: int, thr: float, hysteresis: float, can: bool, prev: np.ndarray,
              device: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(split, culled, dist, metric) of candidates (lvl, x, y): one :func:`select_level` launch on the pyramid.

    A streamed pyramid worked out on demand knows each node's stats only within bounds at an overview step
    (measured values, and those widened by what the step can miss). The decision is monotone in the error
    and the box, so a node is decided when the measured and the widened stats decide alike (the exact stats
    lie between them: the same decision); the others are measured again at a finer step, down to step 1
    (exact). The decisions are the exact pyramid's; distance and metric are the widened stats'."""
    size = terrain.node_size_world(lvl)
    prov = terrain.provider

    def run(idx: np.ndarray, stats: tuple) -> tuple[np.ndarray, ...]:
        k = keys[idx] if keys is not None else None
        return select_level(x[idx], y[idx], k, stats, view.rel_origin, size, view.planes, code, thr, view.focal_px,
                            hysteresis, can, prev, device=device)

    if prov is None or prov.exact:
        return run(np.arange(len(x)), terrain.stats_at(lvl, x, y))
    out = [np.zeros(len(x), np.int32), np.zeros(len(x), np.int32), np.zeros(len(x), np.float32),
           np.zeros(len(x), np.float32)]
    todo = np.arange(len(x))
    for step in prov.steps(lvl):
        mn, mx, er, pad = prov.measured(lvl, x[todo], y[todo], step)
        done = np.ones(len(todo), bool)
        if pad > 0 and step > 1:  # the widened and the measured stats in one launch
            both = run(np.concatenate([todo, todo]), (np.concatenate([mn - pad, mn]), np.concatenate([mx + pad, mx]),
                                                      np.concatenate([er + pad, er])))
            up, lo = tuple(a[:len(todo)] for a in both), tuple(a[len(todo):] for a in both)
            done = (up[0] == lo[0]) & (up[1] == lo[1])
        else:
            up = run(todo, (mn - pad, mx + pad, er + pad))
        for o, u in zip(out, up, strict=True):
            o[todo[done]] = u[done]
        todo = todo[~done]
        if not len(todo):
            break
    return tuple(out)


def _gather_err(terrain: Terrain, level, lx, ly) -> np.ndarray:
    """The geometric error of nodes (level, x, y), ``level`` ascending (as in key order)."""
    out = np.empty(len(level), np.float32)
    ends = np.searchsorted(level, np.arange(terrain.depth + 2))
    for lv in range(terrain.depth + 1):
        a, b = ends[lv], ends[lv + 1]
        if a < b:
            out[a:b] = terrain.stats_at(lv, lx[a:b], ly[a:b])[2]
    return out


def _child_stats(terrain: Terrain, view: _View, nl: np.ndarray, nxs: np.ndarray, nys: np.ndarray, policy: Policy,
                 device: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distance, metric and culling of children created by the balance pass (one launch per level)."""
    nd = np.zeros(len(nl), np.float32)
    nm = np.zeros(len(nl), np.float32)
    nc = np.zeros(len(nl), bool)
    code = policy.code if not isinstance(policy, ContinuousPolicy) else 0
    for lv in np.unique(nl):
        m = nl == lv
        lvl = int(lv)
        keys = tile_key(np.full(int(m.sum()), lvl), nxs[m], nys[m])
        size = terrain.node_size_world(lvl)
        _, cu, di, me = _evaluate(terrain, lvl, nxs[m], nys[m], keys, view, code, policy.threshold(lvl, max(size)),
                                  0.0, False, np.zeros(0, np.int64), device)
        nd[m], nm[m], nc[m] = di, me, cu.astype(bool)
    return nd, nm, nc


# ------------------------------------------------------------------------------------------------
# per-node metrics of the complete tree (for relaxed, differentiable selection in terrainwarp.fit)
# ------------------------------------------------------------------------------------------------
class NodeMetrics(NamedTuple):
    """Every inside node of every level, for one camera (the complete tree, whatever a policy decides).

    Attributes (lists over levels 0..D of (N_L,) arrays, in row-major (y, x) order of the level):
        x, y: node coordinates; inside: origin inside the grid; culled: outside the frustum;
        dist: eye-to-box distance (m); sse: projected geometric error (px, inf at distance 0 with error);
        size: node side in metres (max of x and z).
    """

    x: list
    y: list
    inside: list
    culled: list
    dist: list
    sse: list
    size: list


def node_metrics(terrain: Terrain, camera: Camera, device: str = "cpu") -> NodeMetrics:
    """Distance, screen-space error and culling of every node of the complete tree, one launch per level."""
    nx, nz = terrain.roots
    view = _view(terrain, camera)
    out = NodeMetrics([], [], [], [], [], [], [])
    for lvl in range(terrain.depth + 1):
        yy, xx = np.meshgrid(np.arange(nz << lvl, dtype=np.int64), np.arange(nx << lvl, dtype=np.int64),
                             indexing="ij")
        x, y = xx.reshape(-1), yy.reshape(-1)
        keys = tile_key(np.full(len(x), lvl), x, y)
        _, cu, di, me = select_level(x, y, keys, terrain.stats_at(lvl, x, y), view.rel_origin,
                                     terrain.node_size_world(lvl), view.planes, 1, 1.0, view.focal_px, 0.0, False,
                                     np.zeros(0, np.int64), device=device)
        out.x.append(x)
        out.y.append(y)
        out.inside.append(_inside_many(terrain, lvl, x, y))
        out.culled.append(cu.astype(bool))
        out.dist.append(di.astype(np.float64))
        out.sse.append(me.astype(np.float64))
        out.size.append(np.full(len(x), max(terrain.node_size_world(lvl))))
    return out

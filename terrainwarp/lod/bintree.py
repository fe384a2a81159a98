"""The multiresolution BSP (right-triangle bisection) tree and its apparent-size LOD rule
(mrbsp-lod-visibility.txt, sections 2 and 3).

The root is a square bounding the heightmap (side = the larger of its x and z extents, anchored at
its origin; heights beyond the grid are clamped to its border). Level 1 splits it along the diagonal
(0, 0)-(side, side) into two right triangles; every further level splits each triangle from its
right angle to the middle of its hypotenuse, so level L holds 2**L triangles and a complete
representation of the terrain (tested). Vertices lie on a grid of ``G = 2**floor(M/2)`` cells per
side; at level L the triangles' legs are ``side * 2**(-(L-1)/2)``, so ``S = side * 2**(-(M-1)/2)``. For a 256 x 256-cell
heightmap, M = 16 gives the paper's 65,536-triangle landscape (each triangle covers one cell; the
vertices use every other sample), M = 17 uses every sample (131,072 triangles).

LOD (section 3): a triangle is displayed at depth ``ceil(M - log2(D / S))`` (clamped to [1, M]), D the
distance from the eye to its furthest vertex. With per-vertex thresholds ``t(v) = ceil(M - log2(D_v /
S))`` that is the smallest threshold of its vertices; descending from the root, a node is displayed at
the first level ``L >= min t``. Hole fixing (the paper): a displayed triangle whose right-angle vertex
alone has the lowest threshold is rendered one level finer. That fix does not close every crack (a
counter-example is in tests/lod/test_bintree.py), so ``propagate=True`` adds ROAM's forced split
propagation: every split node's base neighbour (the node of the same level across its hypotenuse) is
split too, repeated until stable, which makes the mesh conforming (no T-junctions).

float32: vertex positions are camera-relative (root corner minus eye in float64 on the host, then
``+ g * step`` in float32), so precision is ~1e-7 of the terrain's size.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field
from typing import NamedTuple, Protocol

import numpy as np

from ..camera import Camera, relative_origin
from ..heightmap import Heightmap
from ..kernels import bintree as _k
from ..kernels.checks import check_choice, check_int
from ..mesh import Mesh

__all__ = ["Bintree", "BintreeFrame", "select_bintree", "lod_threshold", "HEIGHT_METHODS"]

HEIGHT_METHODS = tuple(_k.HEIGHT_METHODS)
MAX_DEPTH = 22  # 2**23 heap nodes, ~200 MB of device arrays


def lod_threshold(distance: object, depth: int, short_side: float) -> np.ndarray:
    """The paper's LOD threshold ``ceil(M - log2(D / S))`` clamped to [1, M] (float64 host reference of
    the kernel's float32 rule): the level at which a triangle whose furthest vertex is ``distance`` away
    is displayed."""
    d = np.asarray(distance, dtype=np.float64)
    with np.errstate(divide="ignore"):
        t = np.where(d > short_side, np.ceil(depth - np.log2(np.maximum(d, 1e-300) / short_side)), depth)
    return np.clip(t, 1, depth).astype(np.int32)


@dataclass(frozen=True, eq=False)
class Bintree:
    """A built MRBSP tree (device arrays in :attr:`arrays`, heap-indexed; see kernels/bintree.py).

    Attributes:
        heightmap: the source heightmap.
        depth: M, the deepest level (2**M triangles there).
        method: vertex heights, ``"nearest3"`` (the paper: plane through the three closest samples) or
            ``"bilinear"``.
        origin: (x0, z0) world corner of the root square; side: its side in metres.
        grid: G, vertex grid cells per side; step: side / G metres.
        build_s: wall time of the build in seconds.
    """

    heightmap: Heightmap
    depth: int
    method: str
    origin: tuple[float, float]
    side: float
    grid: int
    step: float
    arrays: dict
    build_s: float
    device: str = "cpu"
    _walks: threading.local = field(default_factory=threading.local, init=False, repr=False)

    def _walk(self) -> _k.Walk:
        """This thread's selection walk of the tree (its buffers and recorded launch, made on first use and
        reused every frame; one per thread, so threads may select on one tree at once)."""
        w = getattr(self._walks, "walk", None)
        if w is None:
            w = self._walks.walk = _k.Walk(self.arrays, self.depth, self.device)
        return w

    @classmethod
    def build(cls, heightmap: Heightmap, depth: int | None = None, method: str = "nearest3",
              device: str = "cpu") -> Bintree:
        """Build the tree level by level on the device.

        Args:
            heightmap: a :class:`Heightmap` (NaN-free).
            depth: M in [1, 24]; default: the smallest M whose vertex grid is at least as fine as the
                heightmap's samples (M = 2 * ceil(log2(max(rows, cols) - 1)) + 1).
            method: ``"nearest3"`` or ``"bilinear"``.
        """
        if not isinstance(heightmap, Heightmap):
            raise TypeError(f"heightmap: expected a Heightmap, got {type(heightmap).__name__}")
        if not np.all(np.isfinite(heightmap.heights)):
            raise ValueError("heightmap: expected finite heights (fill no-data first)")
        check_choice("method", method, HEIGHT_METHODS)
        rows, cols = heightmap.shape
        if depth is None:
            depth = 2 * max(1, math.ceil(math.log2(max(rows, cols, 2) - 1))) + 1
        depth = check_int("depth", depth, 1, MAX_DEPTH)
        (x0, z0), (x1, z1) = heightmap.bounds_xz
        side = max(x1 - x0, z1 - z0)
        if not side > 0:
            raise ValueError("heightmap: expected at least 2 samples along x or z")
        t0 = time.perf_counter()
        arr = _k.build_tree(heightmap.heights, heightmap.origin, (heightmap.dx, heightmap.dz), x0, z0, side,
                            int(depth), method, device)
        build_s = time.perf_counter() - t0
        grid = int(arr["grid"])
        return cls(heightmap, int(depth), method, (float(x0), float(z0)), float(side), grid, side / grid, arr,
                   build_s, device)

    # -- geometry -----------------------------------------------------------------------------------
    @property
    def n_nodes(self) -> int:
        """Heap size 2**(M+1) - 1 (root square included)."""
        return (1 << (self.depth + 1)) - 1

    @property
    def short_side(self) -> float:
        """S: the short side (leg) of a level-M triangle, metres."""
        return self.side * 2.0 ** (-(self.depth - 1) / 2.0)

    def level_slice(self, level: int) -> slice:
        """Heap indices of the nodes of ``level``."""
        if not 0 <= level <= self.depth:
            raise ValueError(f"level: expected 0..{self.depth}, got {level}")
        return slice((1 << level) - 1, (1 << (level + 1)) - 1)

    def node_vertices(self, nodes: object | None = None) -> np.ndarray:
        """(k, 3) int32 grid vertex ids (apex, b0, b1) of heap ``nodes`` (all when None)."""
        a = np.stack([self.arrays[k].numpy() for k in ("apex", "b0", "b1")], axis=1)
        return a if nodes is None else a[np.asarray(nodes, dtype=np.int64)]

    def vertex_grid_xz(self, ids: object) -> np.ndarray:
        """(k, 2) int64 integer grid coordinates (gx, gz) of vertex ids."""
        i = np.asarray(ids, dtype=np.int64)
        g1 = self.grid + 1
        return np.stack([i % g1, i // g1], axis=-1)

    def vertex_world(self, ids: object) -> np.ndarray:
        """(k, 3) float64 world positions of vertex ids."""
        g = self.vertex_grid_xz(ids)
        h = self.arrays["vertex_height"].numpy()[np.asarray(ids, dtype=np.int64)]
        return np.stack([self.origin[0] + g[..., 0] * self.step, h.astype(np.float64),
                         self.origin[1] + g[..., 1] * self.step], axis=-1)

    def surface_height(self, x: object, z: object) -> np.ndarray:
        """Height of the level-M surface (linear on its triangles) at world (x, z), float64; points
        outside the root square are clamped to it."""
        shape = np.broadcast_shapes(np.shape(x), np.shape(z))
        xs = np.clip((np.broadcast_to(np.asarray(x, np.float64), shape).reshape(-1) - self.origin[0]) / self.side,
                     0.0, 1.0)
        zs = np.clip((np.broadcast_to(np.asarray(z, np.float64), shape).reshape(-1) - self.origin[1]) / self.side,
                     0.0, 1.0)
        node = self.locate(xs * self.grid, zs * self.grid, self.depth)
        v = self.node_vertices(node)
        g = self.vertex_grid_xz(v).astype(np.float64)  # (k, 3, 2)
        h = self.arrays["vertex_height"].numpy()[v].astype(np.float64)
        p = np.stack([xs * self.grid, zs * self.grid], axis=-1)
        a, b, c = g[:, 0], g[:, 1], g[:, 2]
        det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
        wb = ((p[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (p[:, 1] - a[:, 1])) / det
        wc = ((b[:, 0] - a[:, 0]) * (p[:, 1] - a[:, 1]) - (p[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])) / det
        return (h[:, 0] * (1 - wb - wc) + h[:, 1] * wb + h[:, 2] * wc).reshape(shape)

    def locate(self, gx: object, gz: object, level: int) -> np.ndarray:
        """Heap index of the level-``level`` node containing grid point(s) (gx, gz) (vectorised descent;
        points on a split line go to the first child)."""
        px = np.atleast_1d(np.asarray(gx, np.float64)).reshape(-1)
        pz = np.atleast_1d(np.asarray(gz, np.float64)).reshape(-1)
        verts = self.node_vertices()
        g1 = self.grid + 1
        node = np.where(pz <= px, 1, 2).astype(np.int64)  # level 1: below / above the diagonal x = z
        for _ in range(1, level):
            a, p = verts[node, 0], verts[node, 1]
            ax, az = a % g1, a // g1
            qx, qz = p % g1, p // g1
            # child 0 = (c, a, b0) lies on b0's side of the line apex -> midpoint; the midpoint c is the
            # new apex (children's apex array), which is where the first child starts.
            c = verts[2 * node + 1, 0]
            cx, cz = c % g1, c // g1
            side_p = (cx - ax) * (qz - az) - (cz - az) * (qx - ax)
            side_x = (cx - ax) * (pz - az) - (cz - az) * (px - ax)
            node = np.where(side_x * side_p >= 0, 2 * node + 1, 2 * node + 2)
        return node


class BintreeFrame(NamedTuple):
    """One frame's selection.

    Attributes:
        mesh: :class:`Mesh` (camera-relative float32 positions, int32 ccw triangles, uv over the
            heightmap's bounds (beyond [0, 1] where the root square overhangs it); ``level`` and
            ``patch_id`` per vertex are 0: per-triangle levels are in :attr:`level`).
        node: (m,) int32 heap index of the tree node drawn as each triangle.
        level: (m,) int32 tree level of each triangle.
        grid_id: (n,) int32 grid vertex id of each mesh vertex (exact positions: merge by these).
        stats: ``triangles``, ``forced_splits``, ``propagation_iterations``, ``select_ms``.
    """

    mesh: Mesh
    node: np.ndarray
    level: np.ndarray
    grid_id: np.ndarray
    stats: dict


class NodeFlags(Protocol):
    """Per-node visibility, as :class:`terrainwarp.lod.visibility.VisibilityState` gives it (that module
    builds on this one, so the type is named by what it does)."""

    def node_flags(self) -> np.ndarray: ...  # (n_nodes,) uint8, 0 = hidden subtree


def select_bintree(tree: Bintree, camera: Camera, *, lod: bool = True, hole_fix: bool = True,
                   propagate: bool = True, frustum: bool = True,
                   visibility: NodeFlags | np.ndarray | None = None) -> BintreeFrame:
    """Select the triangles to draw for ``camera``.

    Args:
        tree: a :class:`Bintree`.
        camera: the observer (its position is the LOD eye; its matrices give the frustum).
        lod: the paper's apparent-size rule; False draws every level-M triangle (brute force).
        hole_fix: the paper's hole fixing (only with ``lod``).
        propagate: ROAM's forced split propagation (conforming mesh; only with ``lod``).
        frustum: drop subtrees outside the view frustum (their bounds: triangle footprint x subtree
            height range).
        visibility: a :class:`terrainwarp.lod.visibility.VisibilityState` (or a per-node (n_nodes,) uint8
            array): hidden subtrees are dropped.

    Returns:
        :class:`BintreeFrame`.
    """
    if not isinstance(tree, Bintree):
        raise TypeError(f"tree: expected a Bintree, got {type(tree).__name__}")
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a Camera, got {type(camera).__name__}")
    vis = None
    if visibility is not None:
        vis = visibility.node_flags() if hasattr(visibility, "node_flags") else np.asarray(visibility)
        if vis.shape != (tree.n_nodes,):
            raise ValueError(f"visibility: expected {tree.n_nodes} node flags, got shape {vis.shape}")
        vis = np.ascontiguousarray(vis, dtype=np.uint8)
    t0 = time.perf_counter()
    eye = np.asarray(camera.position, dtype=np.float64)
    planes = None
    if frustum:
        planes = camera.frustum_planes()
    r = _k.select_nodes(tree.arrays, tree.depth, relative_origin(tree.origin, eye)[::2], tree.step,
                        float(eye[1]), tree.short_side, mode=int(bool(lod)), hole_fix=bool(hole_fix and lod),
                        propagate=bool(propagate and lod), planes=planes, vis=vis, device=tree.device,
                        walk=tree._walk())
    dt = time.perf_counter() - t0
    node = r["node"].astype(np.int32, copy=False)
    level = (np.floor(np.log2(node.astype(np.float64) + 1.0))).astype(np.int32)
    pos = r["positions"].astype(np.float32, copy=False)
    gid = r["grid_id"].astype(np.int32, copy=False)
    g = tree.vertex_grid_xz(gid).astype(np.float64)
    (hx0, hz0), (hx1, hz1) = tree.heightmap.bounds_xz
    ex, ez = hx1 - hx0, hz1 - hz0  # one of them is 0 for a single row or column: u or v is then 0
    uv = np.stack([(tree.origin[0] + g[:, 0] * tree.step - hx0) / ex if ex > 0 else 0.0 * g[:, 0],
                   (tree.origin[1] + g[:, 1] * tree.step - hz0) / ez if ez > 0 else 0.0 * g[:, 1]], axis=1)
    mesh = Mesh(positions=pos, eye=tuple(float(v) for v in eye), triangles=r["triangles"].astype(np.int32, copy=False),
                uv=uv.astype(np.float32).reshape(-1, 2), level=np.zeros(len(pos), np.int32),
                patch_id=np.zeros(len(pos), np.int32))
    stats = {"triangles": int(len(node)), "forced_splits": int(r["forced"]),
             "propagation_iterations": int(r["iterations"]), "select_ms": dt * 1e3}
    return BintreeFrame(mesh, node, level, gid, stats)

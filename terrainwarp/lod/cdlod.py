"""CDLOD: Continuous Distance-Dependent Level of Detail (Strugar 2010), and the NVIDIA DX11 terrain sample's
per-edge factor compared with the ``continuous`` policy.

**What the publication prescribes** (the paper, and its reference implementation ``fstrugar/CDLOD``,
``CDLODQuadTree.cpp`` and ``CDLODTerrain.vsh``, read for this):

* A quadtree over the heightmap with per-node min/max heights (the node's box). LOD level 0 is the finest.
* Selection by distance ranges: a node of LOD ``i`` is drawn where its box intersects the sphere of radius
  ``range[i]`` around the eye; it is split where its box also intersects ``range[i-1]``, and a child whose
  box does not intersect ``range[i-1]`` is drawn as that quadrant of the parent (the parent's grid, a
  quarter of it). Nodes outside the frustum are dropped. The ranges are built from a "LOD distance ratio"
  (the demo's ``detailBalance`` = 2): the band of each level is ``ratio`` times the band of the level
  below it, ``range[i] = first_range * (1 + ratio + ... + ratio**i)``.
* Every node is drawn with the same grid mesh (``grid`` x ``grid`` quads); no stitching, no seams.
* Morph in the vertex shader: ``k = clamp((d - morph_start[i]) / (morph_end[i] - morph_start[i]), 0, 1)``
  with ``d`` the eye distance of the unmorphed vertex (height sampled there), and the vertices at odd grid
  indices slide by ``k`` grid steps toward their even neighbour, so that at ``k = 1`` the node is exactly
  its parent's grid; the height is sampled again at the morphed position. ``morph_end[i] = range[i]``,
  ``morph_start[i] = prev + (range[i] - prev) * morph_start_ratio``, ``prev`` the previous level's morph
  start (0 for level 0), and morph_end is pulled 1% toward morph_start (the reference's ``errorFudge``) so
  that float rounding of the distance cannot leave a vertex unmorphed at a range border. The paper morphs
  over the last 15-30% of a range.
* The reference flags frames whose ranges are too small for the node sizes ("visibility distance too
  small": a selected node's farthest point lies past the next coarser level's morph start, where the
  coarser neighbour would already morph and a seam could open). We count those nodes in the selection's
  ``too_small`` and give a first range that never triggers it (:attr:`Cdlod.min_first_range`).

**Where we had to choose.**

* The quadtree is :class:`terrainwarp.lod.Terrain` (its min/max pyramids, its node boxes and frustum test), walked
  in one launch (:class:`terrainwarp.kernels.schemes.CdlodTree`), with ``tess = grid`` so the finest level draws one
  vertex per sample. ``levels`` fixes the tree depth (roots are added to cover the grid).
* The coarsest level has an infinite range (the reference stops at a visibility distance): the whole
  terrain is drawn, as every other scheme here draws it, so coverage can be compared.
* The fittable threshold is ``first_range`` (metres): larger is finer. Below :attr:`Cdlod.min_first_range`
  seams may open (counted, not refused).
* Heights are sampled bilinearly from the full-resolution heightmap at every level (the reference's
  "precise" sampling, no mip maps), so a vertex on a sample takes the sample's height exactly.
* Each drawn node is emitted as its four quadrants (``grid / 2`` quads each), so the parent's quadrants and
  whole nodes are one item type and the vertex stage is one launch over the frame; ``grid`` must be even.

**The NVIDIA DX11 terrain sample** (issue item 4) is not the same rule as our ``continuous`` policy; see
:func:`terrainwarp.lod.policies.dx11_edge_pixels` (beside ``edge_pixels``) for the mapping.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..camera import Camera, relative_origin
from ..heightmap import Heightmap
from ..kernels.checks import check_int, check_number
from ..kernels.schemes import CdlodTree, cdlod_mesh
from ..mesh import Draws, Mesh
from .quadtree import Terrain
from .scheme import SelectThenMesh, view_of

__all__ = ["Cdlod", "CdlodSelection", "cdlod_ranges"]

MORPH_FUDGE = 0.01  # the reference's errorFudge: morph_end pulled 1% toward morph_start
# how the reference draws a node (pipeline statistics): one grid of (grid + 1)^2 vertices per draw, each a 2D grid
# position (8 bytes) whose height is sampled bilinearly twice (unmorphed and morphed: 8 texels)
VERTEX_BYTES = 8
TEXELS_PER_VERTEX = 8


def cdlod_ranges(first_range: float, ratio: float, morph_start_ratio: float,
                 levels: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(range, morph_start, morph_end) float64 (levels,) of the LOD levels 0 (finest) .. levels-1, as the
    reference builds them; the coarsest level's range is infinite and it never morphs."""
    rng = first_range * np.cumsum(ratio ** np.arange(levels, dtype=np.float64))
    rng[-1] = math.inf
    start = np.empty(levels)
    end = rng.copy()
    prev = 0.0
    for i in range(levels):
        start[i] = prev + (rng[i] - prev) * morph_start_ratio if math.isfinite(rng[i]) else math.inf
        prev = start[i]
        if math.isfinite(end[i]):
            end[i] = end[i] + (start[i] - end[i]) * MORPH_FUDGE
    return rng, start, end


@dataclass(frozen=True)
class CdlodSelection:
    """The drawn quadrants of one frame (structure of arrays, Q quadrants).

    Attributes:
        origin: (Q, 2) float32 corner in heightmap cells (column, row); size: (Q,) float32 side in cells.
        step: (Q,) float32 vertex spacing in cells; lod: (Q,) int32 CDLOD level (0 finest).
        stats: nodes visited, quadrants, culled, too_small (nodes whose farthest point lies past the next
            coarser level's morph start), levels, whole_nodes and quadrant_draws.
        draws: (D, 2) int32 ranges [first, stop) of ``order`` drawn by each of the reference's draw calls: a
            whole node's four quadrants, or a parent's quadrant alone; order: (Q,) int32 the quadrants in the
            order of those draws.
    """

    origin: np.ndarray
    size: np.ndarray
    step: np.ndarray
    lod: np.ndarray
    stats: dict = field(default_factory=dict)
    draws: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int32))
    order: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))


@dataclass(eq=False)
class Cdlod(SelectThenMesh):
    """CDLOD over a heightmap (see the module docstring).

    Args:
        heightmap: the terrain (no NaN).
        first_range: metres, the range of LOD 0 (the fittable threshold; larger is finer).
        ratio: LOD distance ratio (> 1): each level's band is ``ratio`` times the previous one.
        morph_start_ratio: in (0, 1): where in its band a level starts morphing (0.7: over the last 30%).
        grid: grid resolution of a node (quads per side; even, 2..64).
        levels: number of LOD levels (default: one root covers the longer side, fewer roots for more levels).
        device: Warp device.
    """

    heightmap: Heightmap
    first_range: float
    ratio: float = 2.0
    morph_start_ratio: float = 0.7
    grid: int = 32
    levels: int | None = None
    device: str = "cpu"
    terrain: Terrain = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.heightmap, Heightmap):
            raise TypeError(f"heightmap: expected a Heightmap, got {type(self.heightmap).__name__}")
        if np.isnan(self.heightmap.heights).any():
            raise ValueError("heightmap: CDLOD here expects no NaN (no-data) heights")
        self.first_range = check_number("first_range", self.first_range, 0.0, lo_open=True)
        self.ratio = check_number("ratio", self.ratio, 1.0, lo_open=True)
        self.morph_start_ratio = check_number("morph_start_ratio", self.morph_start_ratio, 0.0, 1.0, lo_open=True,
                                              hi_open=True)
        self.grid = check_int("grid", self.grid, 2, 64)
        if self.grid % 2:
            raise ValueError(f"grid: expected an even integer in 2..64, got {self.grid!r}")
        hh, ww = self.heightmap.shape
        longest = max(ww - 1, hh - 1, 1)
        if self.levels is None:
            self.levels = max(1, math.ceil(math.log2(max(longest / self.grid, 1.0)) - 1e-12) + 1)
        self.levels = check_int("levels", self.levels, 1, 20)
        root = self.grid * 2 ** (self.levels - 1)
        roots = (max(1, math.ceil((ww - 1) / root)), max(1, math.ceil((hh - 1) / root)))
        self.terrain = Terrain.prepare(self.heightmap, roots=roots, tess=self.grid, depth=self.levels - 1,
                                       device=self.device)
        self._h = None
        self._ranges = None

    # -- ranges ---------------------------------------------------------------------------------------
    def ranges(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(range, morph_start, morph_end) of LOD 0 .. levels-1 (:func:`cdlod_ranges`)."""
        key = (self.first_range, self.ratio, self.morph_start_ratio, self.levels)
        if self._ranges is None or self._ranges[0] != key:  # the knobs are fields a fit may set between frames
            self._ranges = (key, cdlod_ranges(*key))
        return tuple(a.copy() for a in self._ranges[1])

    @property
    def min_first_range(self) -> float:
        """The smallest ``first_range`` for which no selected node can reach past the next coarser level's
        morph start (so no seam can open, and neighbours differ by at most one level), from the largest
        node box of each level: a node of LOD i is drawn only when its box is within ``range[i]``, so its
        points lie within ``range[i] + diagonal_i``, which must not pass ``morph_start[i+1]``."""
        t = self.terrain
        rng, start, _ = cdlod_ranges(1.0, self.ratio, self.morph_start_ratio, self.levels)
        need = 0.0
        for lod in range(self.levels - 1):
            lvl = t.depth - lod
            mn, mx, _ = t.stats[lvl]
            sx, sz = t.node_size_world(lvl)
            diag = math.sqrt(sx * sx + sz * sz + float((mx - mn).max()) ** 2)
            if math.isfinite(start[lod + 1]):
                need = max(need, diag / (start[lod + 1] - rng[lod]))
        return need

    # -- selection ------------------------------------------------------------------------------------
    def select(self, camera: Camera) -> CdlodSelection:
        """The quadrants to draw from ``camera``: the tree walked in one launch
        (:class:`terrainwarp.kernels.schemes.CdlodTree`)."""
        t = self.terrain
        rng, start, _ = self.ranges()
        rel, planes = view_of(self.heightmap, camera)
        tree = t.cached(("cdlod_tree", self.grid, self.device), lambda: CdlodTree(
            t.stats, t.inside_counts(), t.roots, t.root_cells, [t.node_size_world(lv) for lv in range(t.depth + 1)],
            self.grid, device=self.device))
        origin, size, step, lod, draws, order, n = tree.select(rel, planes, rng, start)
        stats = {"nodes_visited": int(n[2]), "culled": int(n[3]), "too_small": int(n[4]), "levels": self.levels,
                 "whole_nodes": int(n[5]), "quadrant_draws": int(n[6]), "quadrants": int(n[0])}
        return CdlodSelection(origin, size, step, lod, stats, draws, order)

    def _quadrants(self, parts: list, stats: dict) -> CdlodSelection:
        """Each drawn node as its four quadrants, each parent quadrant as itself (cells, float32). ``stats``:
        ``whole_nodes`` and ``quadrant_draws``; ``draws``: the reference's draw calls, a whole node's four
        quadrants together, a parent's quadrant alone (the reference draws a partly selected node quadrant by
        quadrant)."""
        t = self.terrain
        org, size, step, lods, calls = [], [], [], [], []
        whole = single = 0
        base = 0
        for x, y, lvl, lod in parts:
            s = t.root_cells / 2.0 ** lvl
            st = t.root_cells / 2.0 ** (t.depth - lod) / self.grid  # the drawn level's vertex spacing
            k = len(x)
            if lod == t.depth - lvl:  # a whole node: its four quadrants
                q = s / 2
                for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
                    org.append(np.stack([x * s + dx * q, y * s + dy * q], 1))
                    size.append(np.full(k, q))
                    step.append(np.full(k, st))
                    lods.append(np.full(k, lod))
                calls.append(base + np.arange(k)[:, None] + k * np.arange(4)[None, :])  # node by node
                whole += k
                base += 4 * k
            else:  # a quadrant of the parent, drawn with the parent's grid
                org.append(np.stack([x * s, y * s], 1))
                size.append(np.full(k, s))
                step.append(np.full(k, st))
                lods.append(np.full(k, lod))
                calls.append(base + np.arange(k)[:, None])
                single += k
                base += k
        stats.update(whole_nodes=whole, quadrant_draws=single)
        if not org:
            z = np.zeros(0, np.float32)
            return CdlodSelection(np.zeros((0, 2), np.float32), z, z, np.zeros(0, np.int32), {**stats, "quadrants": 0})
        stats["quadrants"] = int(sum(len(a) for a in size))
        order = np.concatenate([c.reshape(-1) for c in calls]).astype(np.int32)
        per = np.concatenate([np.full(len(c), c.shape[1]) for c in calls])
        ends = np.cumsum(per)
        return CdlodSelection(np.concatenate(org).astype(np.float32), np.concatenate(size).astype(np.float32),
                              np.concatenate(step).astype(np.float32), np.concatenate(lods).astype(np.int32), stats,
                              np.stack([ends - per, ends], 1).astype(np.int32), order)

    def uniform(self, lod: int) -> CdlodSelection:
        """Every node of one LOD inside the grid, as its four quadrants: the grid that LOD draws where it is drawn
        whole (with :meth:`mesh` and ``morph=False``, the unmorphed surface the fit's probes measure)."""
        t = self.terrain
        lod = check_int("lod", lod, 0, self.levels - 1)
        lvl = t.depth - lod
        nx, nz = t.roots[0] << lvl, t.roots[1] << lvl
        yy, xx = np.meshgrid(np.arange(nz, dtype=np.int64), np.arange(nx, dtype=np.int64), indexing="ij")
        x, y = xx.reshape(-1), yy.reshape(-1)
        keep = t.inside(lvl, x, y)
        return self._quadrants([(x[keep], y[keep], lvl, lod)], {})

    # -- mesh -----------------------------------------------------------------------------------------
    def mesh(self, camera: Camera, selection: CdlodSelection, *, morph: bool = True) -> Mesh:
        """The selected quadrants' grids, morphed per vertex by the eye distance (one launch), as a Mesh
        (``morph=False``: unmorphed)."""
        _, start, end = self.ranges()
        if not morph:
            start = np.full_like(start, math.inf)
        with np.errstate(invalid="ignore", divide="ignore"):
            inv = np.where(np.isfinite(start), 1.0 / (end - start), 0.0)
        ms = np.where(np.isfinite(start), start, 3e38)
        hm = self.heightmap
        if self._h is None:
            self._h = np.ascontiguousarray(hm.heights, np.float32)
        pos, uv, lev, item, tri = cdlod_mesh(self._h, selection.origin, selection.step, selection.lod, self.grid // 2,
                                             ms, inv, relative_origin(hm.origin, camera.position), hm.dx, hm.dz,
                                             device=self.device)
        n = self.grid // 2
        st = selection.stats
        per = 2 * n * n  # triangles per quadrant
        order = (selection.order[:, None] * per + np.arange(per)[None, :]).reshape(-1).astype(np.int32)
        draws = Draws(ranges=(selection.draws * per).astype(np.int32), order=order,
                      vertex_invocations=st.get("whole_nodes", 0) * (self.grid + 1) ** 2
                      + st.get("quadrant_draws", 0) * (n + 1) ** 2, vertex_bytes=VERTEX_BYTES,
                      texels_per_vertex=TEXELS_PER_VERTEX)
        return Mesh(positions=pos, eye=camera.position, triangles=tri, uv=uv, level=lev, patch_id=item, draws=draws)


"""Continuous-resolution polygonalisation of taylor-barrett-continuous-resolution.txt: bottom-up merging
of homogeneous rectangles in a quadtree, at many tolerances at once, triangulated without gaps and
morphed continuously between tolerances.

::

    hm = Heightmap.fbm(257, seed=3)
    pt = build_polytree(hm, default_tolerances(hm, 100))   # the multiresolution polygon array (figure 4)
    pt.polygons.level(10)                                   # (P, 4) int32 rectangles (i0, i1, j0, j1)
    mesh = pt.mesh(10, eye=camera.position)                 # watertight Mesh for the rasterizer
    mesh = pt.morph_mesh(10.4, eye=camera.position)         # TIN morph 40% of the way to level 11

The merge itself runs in :mod:`terrainwarp.kernels.polytree` (each node in the paper's order A, B, C; one
launch a tolerance, which merges again only the nodes whose result that tolerance changes); here are the
host side, the polygon array and the meshes.

Conventions: a rectangle ``(i0, i1, j0, j1)`` covers cells ``i0 <= i < i1``, ``j0 <= j < j1`` of the
(H-1) x (W-1) cells; its corners are heightmap samples, sample (i, j) at world
``(x0 + j*dx, h[i, j], z0 + i*dz)``. Gradients are the paper's unnormalised ``Xgr`` (along j / x) and
``Ygr`` (along i / z) in metres, and tolerances are metres of ``|dXgr| + |dYgr|``.

Precision: heights are float32 and the gradients are sums of four float32 differences, so two
coplanar rectangles can differ by a few ulps of the heights in ``Xgr``; a plane merges to one polygon at
tolerance 0 only when its heights are exact in float32 (dyadic slopes), and at any tolerance above
``8 * ulp(max |h|)`` otherwise. The unnormalised gradient of a plane grows with the rectangle size, so
on grids whose cell counts are not powers of two the clipped border nodes of a tilted plane need a
tolerance of the order of the slope times the size difference to merge.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..camera import relative_origin
from ..heightmap import Heightmap
from ..kernels import polytree as _k
from ..kernels.checks import check_int, check_number, is_int, is_number
from ..mesh import Mesh

__all__ = ["PolygonArray", "Polytree", "TinMorph", "build_polytree", "default_tolerances", "merge_rectangles",
           "gradients"]


def gradients(heights: np.ndarray, rects: np.ndarray) -> np.ndarray:
    """(P, 2) float64 (Xgr, Ygr) of rectangles (P, 4) (i0, i1, j0, j1): equations 1 and 2 (reference)."""
    h = np.asarray(heights, np.float64)
    r = np.asarray(rects, np.int64).reshape(-1, 4)
    z1, z2 = h[r[:, 0], r[:, 2]], h[r[:, 0], r[:, 3]]
    z3, z4 = h[r[:, 1], r[:, 3]], h[r[:, 1], r[:, 2]]
    return np.stack([(z2 - z1) + (z3 - z4), (z4 - z1) + (z3 - z2)], 1)


@dataclass(frozen=True, eq=False)
class PolygonArray:
    """The multiresolution polygon array of figure 4: an index array into a polygon array.

    Attributes:
        tolerances: (T,) float32 metres, ascending; the last one is the first whose root holds one polygon
            (or the last one asked for).
        start: (T+1,) int64; level t's polygons are rows ``start[t]:start[t+1]`` of the polygon arrays.
        rects: (P, 4) int32 (i0, i1, j0, j1) rectangles, each level in the root's order.
        grads: (P, 2) float32 (Xgr, Ygr) metres.
        flags: (P,) int32 failure flags (``terrainwarp.kernels.polytree.FLAG_*``: a merge across that side
            was tried and failed).
    """

    tolerances: np.ndarray
    start: np.ndarray
    rects: np.ndarray
    grads: np.ndarray
    flags: np.ndarray

    @property
    def n_levels(self) -> int:
        return int(len(self.tolerances))

    def _check(self, t: int) -> int:
        if not is_int(t):
            raise TypeError(f"t: expected an integer level index, got {t!r}")
        if not 0 <= int(t) < self.n_levels:
            raise ValueError(f"t: expected a level in [0, {self.n_levels}), got {t}")
        return int(t)

    def level(self, t: int) -> np.ndarray:
        """(P_t, 4) int32 rectangles of level t."""
        t = self._check(t)
        return self.rects[self.start[t]:self.start[t + 1]]

    def n_polygons(self, t: int) -> int:
        t = self._check(t)
        return int(self.start[t + 1] - self.start[t])

    def level_for(self, tolerance: float) -> int:
        """The level of the largest computed tolerance <= ``tolerance`` (level 0 below the first)."""
        return int(max(0, np.searchsorted(self.tolerances, np.float32(tolerance), side="right") - 1))


@dataclass
class TinMorph:
    """Section 2.5 between levels ``t`` (fine) and ``t + 1`` (coarse).

    Level t's polygons are split where they cover several level t+1 polygons (the common refinement of
    the two tilings; carried down from the top, :meth:`Polytree.split_level`, so that the morph of
    t -> t+1 ends on the vertices the morph of t+1 -> t+2 starts from), the split tiling is triangulated
    watertight, and every vertex gets a target vertex of split level t+1 inside the closure of every
    polygon of it that the vertex touches (coarse vertices stay, vertices on a coarse edge slide to its
    nearer end, interior vertices go to the nearest corner). At parameter s, x and z are interpolated
    linearly and the height is sampled from the heightmap (bilinear; exact samples at s = 0 and 1).

    At s = 1 the vertices coincide with split level t+1's, but the collapsed fine triangles may pick the
    other diagonal of a coarse rectangle than split level t+1's own triangulation: the one jump left
    at integer levels (benchmarks/results/polytree.md measures it).

    Attributes:
        t: the fine level.
        rects: (R, 4) int32 split level t; split_added: R minus level t's polygon count.
        src, dst: (n, 2) int32 grid (i, j) of each vertex at s = 0 and at s = 1.
        triangles: (m, 3) int32 counter-clockwise from +y at s = 0.
    """

    t: int
    rects: np.ndarray
    split_added: int
    src: np.ndarray
    dst: np.ndarray
    triangles: np.ndarray


@dataclass
class Polytree:
    """The result of :func:`build_polytree`.

    Attributes:
        heightmap: the input.
        polygons: the multiresolution :class:`PolygonArray`.
        depth: quadtree depth (2^depth cells a side).
        pass_ms: (T,) wall time of each tolerance's merge pass (ms).
        pass_stats: (T, 6) int64 per pass: pair tests, bounds failures, similarity failures, merges,
            neighbour-search pointer steps (two searches per test), the most steps of one search; the
            paper's algorithm's counts, over every node not frozen by step j (also the nodes a pass did not
            need to merge again, with the counts of their last merge).
    """

    heightmap: Heightmap
    polygons: PolygonArray
    depth: int
    pass_ms: np.ndarray
    pass_stats: np.ndarray
    device: str = "cpu"
    _labels: dict = field(default_factory=dict, repr=False)
    _grids: dict = field(default_factory=dict, repr=False)
    _morphs: dict = field(default_factory=dict, repr=False)
    _splits: dict = field(default_factory=dict, repr=False)

    @property
    def n_levels(self) -> int:
        return self.polygons.n_levels

    def label_map(self, t: int) -> np.ndarray:
        """(H-1, W-1) int32: the index (within level t) of the polygon covering each cell."""
        t = self.polygons._check(t)
        if t not in self._labels:
            hh, ww = self.heightmap.shape
            lab, hits = _k.paint(self.polygons.level(t), (hh - 1, ww - 1), device=self.device)
            if hits.size and (hits.min() != 1 or hits.max() != 1):
                raise RuntimeError(f"level {t} does not cover the grid exactly once")  # an internal error
            self._labels[t] = lab
        return self._labels[t]

    def grid_triangulation(self, t: int) -> tuple[np.ndarray, np.ndarray]:
        """Section 2.4: (vertices (n, 2) int32 grid (i, j), triangles (m, 3) int32) of level t."""
        t = self.polygons._check(t)
        if t not in self._grids:
            hm = self.heightmap
            self._grids[t] = _k.triangulate_tiling(hm.heights, self.polygons.level(t), self.label_map(t), hm.dx,
                                                   hm.dz, device=self.device)
        return self._grids[t]

    def n_triangles(self, t: int) -> int:
        return int(len(self.grid_triangulation(t)[1]))

    def _rel(self, eye) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        hm = self.heightmap
        e = (hm.origin[0], 0.0, hm.origin[1]) if eye is None else tuple(float(v) for v in np.asarray(eye).reshape(3))
        if not np.all(np.isfinite(e)):
            raise ValueError(f"eye: expected 3 finite numbers, got {eye!r}")
        return e, relative_origin(hm.origin, e)

    def _mesh(self, ij: np.ndarray, pos: np.ndarray, tri: np.ndarray, eye, level: int) -> Mesh:
        hh, ww = self.heightmap.shape
        n = len(pos)
        uv = np.stack([ij[:, 1] / max(ww - 1, 1), ij[:, 0] / max(hh - 1, 1)], 1).astype(np.float32)
        return Mesh(positions=pos, eye=eye, triangles=np.ascontiguousarray(tri, np.int32), uv=uv,
                    level=np.full(n, level, np.int32), patch_id=np.zeros(n, np.int32))

    def mesh(self, t: int, eye=None, *, split: bool = False) -> Mesh:
        """Level t as a watertight :class:`Mesh` (positions relative to ``eye``, default the heightmap
        origin at height 0); ``level`` holds t. ``split``: the split level t of :meth:`split_level` (what
        :meth:`morph_mesh` shows at integer levels)."""
        if split:
            hm = self.heightmap
            rects, lab = self.split_level(t)
            verts, tri = _k.triangulate_tiling(hm.heights, rects, lab, hm.dx, hm.dz, device=self.device)
        else:
            verts, tri = self.grid_triangulation(t)
        eye3, rel = self._rel(eye)
        pos = _k.morph_positions(self.heightmap.heights, verts, verts, 0.0, self.heightmap.dx, self.heightmap.dz,
                                 rel, device=self.device)
        return self._mesh(verts, pos, tri, eye3, int(t))

    def split_level(self, t: int) -> tuple[np.ndarray, np.ndarray]:
        """Level t with its polygons split along the borders of every coarser level (section 2.5's split,
        carried down from the top so the split levels nest: each rectangle of split level t lies inside one
        of split level t+1). Returns (rects (R, 4) int32, label (H-1, W-1) int32); the last level is
        unsplit."""
        t = self.polygons._check(t)
        u = self.n_levels - 1
        if u not in self._splits:
            self._splits[u] = (self.polygons.level(u), self.label_map(u))
        while t not in self._splits:
            u = min(k for k in self._splits if k > t) - 1
            rb, lb = self._splits[u + 1]
            ra, la = self.polygons.level(u), self.label_map(u)
            key = la.astype(np.int64) * len(rb) + lb  # link each level-u polygon to the coarser ones it meets
            uniq, inv = np.unique(key.reshape(-1), return_inverse=True)
            a, b = ra[uniq // len(rb)], rb[uniq % len(rb)]
            rects = np.stack([np.maximum(a[:, 0], b[:, 0]), np.minimum(a[:, 1], b[:, 1]),
                              np.maximum(a[:, 2], b[:, 2]), np.minimum(a[:, 3], b[:, 3])], 1).astype(np.int32)
            self._splits[u] = (rects, inv.reshape(la.shape).astype(np.int32))
        return self._splits[t]

    def morph(self, t: int) -> TinMorph:
        """The :class:`TinMorph` from (split) level t to (split) level t+1 (cached)."""
        t = self.polygons._check(t)
        if t + 1 >= self.n_levels:
            raise ValueError(f"t: expected a level below the last ({self.n_levels - 1}), got {t}")
        if t not in self._morphs:
            hm = self.heightmap
            rects, lab = self.split_level(t)
            rb, lb = self.split_level(t + 1)
            src, tri = _k.triangulate_tiling(hm.heights, rects, lab, hm.dx, hm.dz, device=self.device)
            dst = _k.morph_targets(src, rb, lb, device=self.device)
            self._morphs[t] = TinMorph(t, rects, int(len(rects) - self.polygons.n_polygons(t)), src, dst, tri)
        return self._morphs[t]

    def level_for_distance(self, distance: float, fine_distance: float, coarse_distance: float,
                           levels: tuple[float, float] | None = None) -> float:
        """A continuous level for :meth:`morph_mesh` chosen from a camera distance (metres): ``levels[0]``
        (default 0) at ``fine_distance`` or nearer, ``levels[1]`` (default the last level) at
        ``coarse_distance`` or farther, linear in between."""
        lo, hi = (0.0, float(self.n_levels - 1)) if levels is None else (float(levels[0]), float(levels[1]))
        if not (0.0 <= lo <= self.n_levels - 1 and 0.0 <= hi <= self.n_levels - 1):
            raise ValueError(f"levels: expected two levels in [0, {self.n_levels - 1}], got {levels!r}")
        if not (np.isfinite(fine_distance) and np.isfinite(coarse_distance) and 0 <= fine_distance < coarse_distance):
            raise ValueError(f"fine_distance, coarse_distance: expected 0 <= fine < coarse, got {fine_distance}, "
                             f"{coarse_distance}")
        a = float(np.clip((float(distance) - fine_distance) / (coarse_distance - fine_distance), 0.0, 1.0))
        return lo + a * (hi - lo)

    def morph_mesh(self, x: float, eye=None) -> Mesh:
        """The mesh at continuous level ``x`` in [0, T-1]: level floor(x) morphed by s = x - floor(x)
        towards the next level; at an integer x < T-1, the split level floor(x) (see :class:`TinMorph`)."""
        x = check_number("x", x)
        if not 0.0 <= x <= self.n_levels - 1:
            raise ValueError(f"x: expected a continuous level in [0, {self.n_levels - 1}], got {x}")
        t = min(int(np.floor(x)), self.n_levels - 2)
        if t < 0:  # a single level
            return self.mesh(0, eye)
        return self.morph_at(t, x - t, eye)

    def morph_at(self, t: int, s: float, eye=None) -> Mesh:
        """The morph from level t to t+1 at parameter ``s`` in [0, 1] (same vertices and triangles for
        every s; at s = 1 every vertex sits on a level t+1 vertex)."""
        s = check_number("s", s, 0.0, 1.0)
        mo = self.morph(t)
        eye3, rel = self._rel(eye)
        hm = self.heightmap
        pos = _k.morph_positions(hm.heights, mo.src, mo.dst, s, hm.dx, hm.dz, rel, device=self.device)
        return self._mesh(mo.src, pos, mo.triangles, eye3, t)


def _check_heightmap(heightmap: object) -> Heightmap:
    if not isinstance(heightmap, Heightmap):
        raise TypeError(f"heightmap: expected a Heightmap, got {type(heightmap).__name__}")
    hh, ww = heightmap.shape
    if hh < 2 or ww < 2:
        raise ValueError(f"heightmap: expected at least 2 x 2 samples, got {hh} x {ww}")
    if not np.all(np.isfinite(heightmap.heights)):
        raise ValueError("heightmap: expected finite heights (no NaN holes)")
    return heightmap


def default_tolerances(heightmap: Heightmap, n: int = 100) -> np.ndarray:
    """(n,) float32 tolerances from 0 to 8x the height range (the largest possible ``|dXgr| + |dYgr|``),
    spaced quadratically so most of them fall where the merging changes."""
    hm = _check_heightmap(heightmap)
    n = check_int("n", n, 1)
    lo, hi = hm.height_range
    span = max(8.0 * (hi - lo), 1e-6)
    k = np.arange(int(n), dtype=np.float64) / max(int(n) - 1, 1)
    return (span * k * k).astype(np.float32)


def build_polytree(heightmap: Heightmap, tolerances: object, *, stop_at_one: bool = True,
                   device: str = "cpu") -> Polytree:
    """Merge at every tolerance (ascending), reusing the quadtree nodes that hold one polygon (step j) and
    the merges a tolerance does not change, and stop after the first tolerance whose root holds one polygon
    (``stop_at_one``).

    Args:
        heightmap: finite heights, at least 2 x 2 samples.
        tolerances: 1-D ascending non-negative metres of ``|dXgr| + |dYgr|``.

    Returns:
        :class:`Polytree`. Deterministic: identical polygons on every run.
    """
    hm = _check_heightmap(heightmap)
    tol = np.asarray(tolerances, dtype=np.float64).reshape(-1) if not np.isscalar(tolerances) else \
        np.asarray([tolerances], np.float64)
    if tol.size == 0:
        raise ValueError("tolerances: expected at least one tolerance")
    if not np.all(np.isfinite(tol)) or tol.min() < 0:
        raise ValueError(f"tolerances: expected finite non-negative numbers, got {tol.tolist()[:8]}")
    if np.any(np.diff(tol) < 0):
        raise ValueError("tolerances: expected ascending values")
    st = _k.MergeState(hm.heights, device=device)
    rects, grads, flags, counts, stats, ms = st.run_passes(tol, stop_at_one=stop_at_one)
    pa = PolygonArray(tolerances=tol[:len(counts)].astype(np.float32),
                      start=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
                      rects=rects.astype(np.int32, copy=False), grads=grads.astype(np.float32, copy=False),
                      flags=flags.astype(np.int32, copy=False))
    return Polytree(hm, pa, st.depth, ms, stats, device)


def merge_rectangles(heightmap: Heightmap, tolerance: float, device: str = "cpu") -> np.ndarray:
    """The single-resolution polygonalisation at one tolerance: (P, 4) int32 rectangles (i0, i1, j0, j1)."""
    if not is_number(tolerance):
        raise TypeError(f"tolerance: expected a number of metres, got {tolerance!r}")
    return build_polytree(heightmap, [float(tolerance)], device=device).polygons.level(0)

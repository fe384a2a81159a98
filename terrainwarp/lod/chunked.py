"""Chunked LOD with skirts (Ulrich 2002, "Rendering Massive Terrains using Chunked Level of Detail Control";
the way Cesium's quantized-mesh terrain hides cracks).

**What the publication prescribes.**

* A quadtree of chunks, built offline; each chunk is a mesh of its area with its own maximum geometric error
  (metres): the largest vertical distance between the chunk's surface and the full-resolution terrain.
  Errors are monotone (a parent's is at least each child's).
* Selection by screen-space error: ``sse = geometric_error * focal_px / distance`` (Cesium:
  ``geometricError * viewportHeight / (distance * 2 tan(fovy / 2))``), refine (draw the four children
  instead) while ``sse > maximumScreenSpaceError`` (Cesium's default 2 px); chunks outside the frustum are
  dropped.
* No stitching between neighbours at different levels: every chunk carries vertical skirts hanging from its
  edges, deep enough to hide the gap to any neighbour. Skirts add triangles (2 per edge segment) and hidden
  geometry.
* Ulrich also morphs each chunk's vertices over time after a level switch; **we leave that out**: a switch
  pops here, and the popping column shows it.

**Where we had to choose.**

* The chunk quadtree is :class:`terrainwarp.lod.Terrain` (``tess = tile``): a chunk of tree level L is a
  regular ``tile x tile`` grid of the heightmap's samples at spacing ``S_L / tile`` cells (triangulated like
  the grid mesh), and its geometric error is the Terrain pyramid's (its bilinear vertex grid against every
  sample, made monotone). Ulrich and Cesium simplify each chunk adaptively (fewer triangles for the same
  error); a regular grid is what Cesium's heightmap terrain and most engines' chunked terrains draw.
* Skirt depth: along an edge, the gap between two chunks is at most the sum of their geometric errors (both
  edges are linear between samples, each within its error of the samples). ``skirt_depth=None`` (default)
  gives each chunk, per frame, ``own error + the largest error of the chunks across its edges`` (plus
  1e-6 of the terrain's relief for rounding): the least depth that hides every gap. A number gives every
  chunk that depth in metres (Cesium's own rule is five times the level's maximum error).
* Skirts hang only from edges that have a neighbour inside the terrain: the terrain's outer border gets
  none, so nothing is drawn where the full grid shows background.
* The fittable threshold is ``max_sse_px`` (pixels, Cesium's maximumScreenSpaceError): smaller is finer, 0
  draws every chunk at full detail.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..camera import Camera, relative_origin
from ..heightmap import Heightmap
from ..kernels.checks import check_number
from ..kernels.schemes import ChunkTree, chunk_mesh
from ..mesh import Draws, Mesh
from .quadtree import Terrain
from .scheme import SelectThenMesh, view_of

__all__ = ["ChunkedLod", "ChunkSelection", "DEFAULT_MAX_SSE_PX"]

DEFAULT_MAX_SSE_PX = 2.0  # Cesium's maximumScreenSpaceError default


@dataclass(frozen=True)
class ChunkSelection:
    """The drawn chunks of one frame (structure of arrays, C chunks), sorted by key.

    Attributes:
        level, x, y: (C,) int64 tree level and position (Terrain keys); origin: (C, 2) float32 corner in cells;
        step: (C,) float32 vertex spacing in cells; error: (C,) float32 geometric error (m);
        neighbour_level: (C, 4) int32 level of the chunk across each edge (OpenGL order; -1: none, the
            terrain's border); neighbour_error: (C, 4) float32 its error (0 for none);
        skirt: (C,) float32 skirt depth (m); skirt_mask: (C,) int32 bit e set when edge e has a skirt.
        stats: nodes visited, chunks, culled.
    """

    level: np.ndarray
    x: np.ndarray
    y: np.ndarray
    origin: np.ndarray
    step: np.ndarray
    error: np.ndarray
    neighbour_level: np.ndarray
    neighbour_error: np.ndarray
    skirt: np.ndarray
    skirt_mask: np.ndarray
    stats: dict = field(default_factory=dict)


@dataclass(eq=False)
class ChunkedLod(SelectThenMesh):
    """Chunked LOD with skirts over a heightmap (see the module docstring).

    Args:
        heightmap: the terrain (no NaN).
        max_sse_px: refine while a chunk's projected error exceeds this (pixels; >= 0; Cesium default 2).
        tile: quads per chunk side (1..64).
        roots: root chunks (as :meth:`Terrain.prepare`).
        skirt_depth: metres for every chunk, or None for the per-frame least safe depth.
        device: Warp device.
    """

    heightmap: Heightmap
    max_sse_px: float = DEFAULT_MAX_SSE_PX
    tile: int = 32
    roots: int | tuple[int, int] = 1
    skirt_depth: float | None = None
    device: str = "cpu"
    terrain: Terrain = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.heightmap, Heightmap):
            raise TypeError(f"heightmap: expected a Heightmap, got {type(self.heightmap).__name__}")
        if np.isnan(self.heightmap.heights).any():
            raise ValueError("heightmap: chunked LOD here expects no NaN (no-data) heights")
        self.max_sse_px = check_number("max_sse_px", self.max_sse_px, 0.0)
        if self.skirt_depth is not None:
            self.skirt_depth = check_number("skirt_depth", self.skirt_depth, 0.0)
        self.terrain = Terrain.prepare(self.heightmap, roots=self.roots, tess=self.tile, device=self.device)
        lo, hi = self.heightmap.height_range
        self._slack = 1e-6 * max(hi - lo, 1.0)
        self._h = np.ascontiguousarray(self.heightmap.heights, np.float32)

    # -- selection ------------------------------------------------------------------------------------
    def split_above(self) -> float:
        """The walk splits a chunk whose screen-space error (float32) is above this: ``max_sse_px``."""
        return float(self.max_sse_px)

    def select(self, camera: Camera) -> ChunkSelection:
        """Screen-space-error selection (the tree walked in one launch, :class:`terrainwarp.kernels.schemes.
        ChunkTree`), neighbours and skirts."""
        t = self.terrain
        rel, planes = view_of(self.heightmap, camera)
        tree = t.cached(("chunk_tree", self.device), lambda: ChunkTree(
            t.stats, t.inside_counts(), t.roots, [t.node_size_world(lv) for lv in range(t.depth + 1)],
            device=self.device))
        level, x, y, nbr_level, nbr_err, err, leaves, visited = tree.select(rel, planes, self.split_above(),
                                                                            camera.focal_px)
        s = t.root_cells / np.exp2(level.astype(np.float64))
        mask = ((nbr_level >= 0) << np.arange(4)).sum(axis=1).astype(np.int32)
        if self.skirt_depth is None:
            skirt = err + nbr_err.max(axis=1, initial=0.0) + self._slack
        else:
            skirt = np.full(len(level), self.skirt_depth)
        stats = {"nodes_visited": visited, "culled": leaves - len(level), "chunks": int(len(level))}
        return ChunkSelection(level, x, y, np.stack([x * s, y * s], 1).astype(np.float32),
                              (s / t.tess).astype(np.float32), err, nbr_level, nbr_err, skirt.astype(np.float32),
                              mask, stats)

    # -- mesh -----------------------------------------------------------------------------------------
    def mesh(self, camera: Camera, selection: ChunkSelection) -> Mesh:
        """The chunks' grids and skirts (one launch each for vertices and triangles), as a Mesh; drawn as a GPU
        draws Chunked LOD: one draw per chunk (its grid and skirts, from its own vertex buffer of positions)."""
        hm = self.heightmap
        pos, uv, lev, item, tri = chunk_mesh(self._h, selection.origin, selection.step, selection.level,
                                             selection.skirt, selection.skirt_mask, self.tile,
                                             relative_origin(hm.origin, camera.position), hm.dx, hm.dz,
                                             device=self.device)
        n = self.tile
        edges = np.array([bin(int(m)).count("1") for m in selection.skirt_mask], np.int64)
        ends = np.cumsum(2 * n * n + 2 * n * edges)
        draws = Draws(ranges=np.stack([ends - (2 * n * n + 2 * n * edges), ends], 1).astype(np.int32),
                      vertex_invocations=int(((n + 1) ** 2 + (n + 1) * edges).sum()))
        return Mesh(positions=pos, eye=camera.position, triangles=tri, uv=uv, level=lev, patch_id=item, draws=draws)


    def skirt_triangles(self, selection: ChunkSelection) -> int:
        """Skirt triangles of a selection: 2 per edge segment (``tile`` per edge) of every skirted edge."""
        return 2 * self.tile * int(sum(bin(int(m)).count("1") for m in selection.skirt_mask))

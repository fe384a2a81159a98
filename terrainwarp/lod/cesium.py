"""Cesium's heightmap terrain on a planar heightmap: the tiles CesiumJS would draw for a
``maximumScreenSpaceError``, so that a fitted value can be taken to ``viewer.scene.globe.maximumScreenSpaceError``.

**What Cesium does** (CesiumJS ``QuadtreePrimitive``, ``GlobeSurfaceTileProvider``, ``TerrainProvider``,
``HeightmapTerrainData``, read for this):

* Terrain is a quadtree of tiles, each a regular grid of 65 x 65 height samples (64 x 64 quads), the root
  tiles at level 0; a tile of level L+1 has half its parent's sample spacing.
* A tile's geometric error is not measured: ``getLevelMaximumGeometricError(L)`` is the level-0 estimate
  ``ellipsoid.maximumRadius * 2 pi * heightmapTerrainQuality (0.25) / (65 * tiles across at level 0)`` halved per
  level (:func:`terrainwarp.lod.policies.cesium_level_error`).
* ``screenSpaceError = geometricError * drawingBufferHeight / (distance * 2 tan(fovy / 2))`` with ``distance``
  from the camera to the tile's bounding volume (:func:`terrainwarp.lod.policies.cesium_sse`); a tile is drawn
  when its error is strictly below ``maximumScreenSpaceError`` (default 2), else its children are visited
  (:func:`terrainwarp.lod.policies.cesium_refines`); tiles outside the frustum are culled; the deepest tiles are
  drawn whatever their error.
* Tiles hide the cracks between levels with skirts ``min(4 * geometricError, 1000)`` metres deep.

**How it maps onto a planar heightmap** (where we had to choose):

* The level-0 tiles are square, as few as cover the grid with tiles whose deepest descendants sample every
  heightmap sample (:func:`cesium_roots`: 1 x 1 for a square grid, 2 x 1 for a 2:1 one, as Cesium's geographic
  tiling starts); the level-0 tile's width is its extent along x, in metres (the equator's length over Cesium's
  level-0 tiles). A tile past the grid's edge samples the edge (clamped), as every scheme here.
* The bounding volume is the axis-aligned box of the tile's x, z extent and the lowest and highest of its own
  65 x 65 samples (Cesium's bounding region of the tile's mesh, with no curvature); the distance is 0 inside
  it, where the error is infinite and the tile refines.
* The selection is :class:`terrainwarp.lod.chunked.ChunkedLod`'s walk (one launch) with these errors and boxes,
  refining at ``sse >= maximumScreenSpaceError`` (the float32 threshold one step below the value). The error
  is computed in float32: a tile within a float32 rounding of the threshold may go either way.
* No fog (Cesium's default fog lowers the error of far tiles: set ``scene.fog.enabled = false`` for the same
  selection, or expect coarser far terrain), ``pixelRatio`` 1 (``resolutionScale`` 1 on a display scale of 1),
  no loading (every tile is available at once: Cesium draws a coarser ancestor while children load).
* Skirts hang from the edges that have a neighbour inside the terrain (none at the terrain's border, as the
  ``chunked`` scheme).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..camera import Camera
from ..heightmap import Heightmap
from .chunked import ChunkedLod, ChunkSelection
from .policies import CESIUM_DEFAULT_SSE, CESIUM_TILE_SAMPLES, cesium_level_error

__all__ = ["CesiumTerrain", "cesium_roots", "tile_sample_range", "CESIUM_SKIRT_FACTOR", "CESIUM_MAX_SKIRT_M"]

CESIUM_SKIRT_FACTOR = 4.0  # HeightmapTerrainData: skirtHeight = min(4 * levelMaximumGeometricError, 1000)
CESIUM_MAX_SKIRT_M = 1000.0
QUADS = CESIUM_TILE_SAMPLES - 1


def cesium_roots(shape: tuple[int, int]) -> tuple[int, int]:
    """(nx, nz) level-0 tiles over a (rows, cols) grid: square tiles of ``64 * 2**D`` cells, D the levels below
    them that reach one sample per vertex along the shorter side, as few as cover the grid."""
    hh, ww = shape
    short = max(min(ww - 1, hh - 1), 1)
    depth = max(0, math.ceil(math.log2(max(short / QUADS, 1.0)) - 1e-12))
    side = QUADS * 2 ** depth
    return max(1, math.ceil((ww - 1) / side)), max(1, math.ceil((hh - 1) / side))


def tile_sample_range(heights: np.ndarray, roots: tuple[int, int], root_cells: float, level: int
                      ) -> tuple[np.ndarray, np.ndarray]:
    """(min, max) float32 (nz * 2**L, nx * 2**L) of each level-``level`` tile's own 65 x 65 samples (positions
    clamped to the grid): the heights of its bounding volume."""
    hh, ww = heights.shape
    nx, nz = roots[0] << level, roots[1] << level
    size = root_cells / 2.0 ** level
    k = np.arange(CESIUM_TILE_SAMPLES) * (size / QUADS)
    cols = np.clip(np.round(np.arange(nx)[:, None] * size + k[None, :]), 0, ww - 1).astype(np.int64)
    rows = np.clip(np.round(np.arange(nz)[:, None] * size + k[None, :]), 0, hh - 1).astype(np.int64)
    sub = heights[rows.reshape(-1)][:, cols.reshape(-1)].reshape(nz, CESIUM_TILE_SAMPLES, nx, CESIUM_TILE_SAMPLES)
    return sub.min(axis=(1, 3)).astype(np.float32), sub.max(axis=(1, 3)).astype(np.float32)


@dataclass(eq=False)
class CesiumTerrain(ChunkedLod):
    """Cesium's heightmap-terrain selection over a heightmap (see the module docstring).

    Args:
        heightmap: the terrain (no NaN).
        max_sse_px: Cesium's ``maximumScreenSpaceError`` (pixels, >= 0; default 2): a tile is drawn when its
            screen-space error is below it, refined otherwise.
        device: Warp device.

    ``tile`` (64 quads) and ``roots`` (:func:`cesium_roots`) are Cesium's; the skirts are Cesium's rule.
    """

    max_sse_px: float = CESIUM_DEFAULT_SSE
    tile: int = QUADS

    def __post_init__(self) -> None:
        if self.tile != QUADS:
            raise ValueError(f"tile: Cesium's heightmap tiles have {CESIUM_TILE_SAMPLES} samples a side "
                             f"({QUADS} quads), got {self.tile}")
        if not isinstance(self.heightmap, Heightmap):
            raise TypeError(f"heightmap: expected a Heightmap, got {type(self.heightmap).__name__}")
        self.roots = cesium_roots(self.heightmap.shape)
        super().__post_init__()
        t = self.terrain
        self.level0_width_m = t.root_cells * self.heightmap.dx
        stats = []
        for lvl in range(t.depth + 1):
            mn, mx = tile_sample_range(self.heightmap.heights, t.roots, t.root_cells, lvl)
            stats.append((mn, mx, np.full_like(mn, cesium_level_error(lvl, self.level0_width_m))))
        self.terrain = replace(t, stats=stats, _dev={})  # the walk is built from these stats on first use

    def level_error(self, level: int | np.ndarray) -> float | np.ndarray:
        """Cesium's geometric error (m) of the tiles of ``level`` (0: the root tiles)."""
        return cesium_level_error(level, self.level0_width_m)

    def split_above(self) -> float:
        """The float32 just below ``max_sse_px``: the walk splits at ``sse > that``, i.e. at Cesium's
        ``sse >= maximumScreenSpaceError``."""
        return float(np.nextafter(np.float32(self.max_sse_px), np.float32(-np.inf)))

    def select(self, camera: Camera) -> ChunkSelection:
        """The tiles Cesium draws from ``camera``, with Cesium's skirt depths."""
        sel = super().select(camera)
        skirt = np.minimum(CESIUM_SKIRT_FACTOR * self.level_error(sel.level), CESIUM_MAX_SKIRT_M)
        return replace(sel, skirt=np.asarray(skirt, np.float32))

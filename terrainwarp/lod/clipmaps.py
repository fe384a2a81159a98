"""Geometry clipmaps (Losasso & Hoppe 2004, "Geometry Clipmaps: Terrain Rendering Using Nested Regular Grids";
Asirvatham & Hoppe, GPU Gems 2 ch. 2, "Terrain Rendering Using GPU-Based Geometry Clipmaps").

**What the publications prescribe.**

* L nested square grids ("levels") of n x n vertices centred on the viewer; level l has grid spacing
  ``2**l`` times the finest. Each level is drawn as a ring around the finer level inside it (the finest as a
  full square). As the viewer moves, each level's square moves in steps of twice its spacing (so that it
  stays on the coarser level's grid): its position is the viewer's, snapped.
* ``n = 2**k - 1`` (GPU Gems uses 255), so that a ring splits into 12 m x m blocks (m = (n+1)/4), fix-up
  strips and an L-shaped interior trim, drawn from a few vertex buffers; blocks are frustum-culled.
* Transition regions: within ``w = n/10`` grid units of a level's outer border, its heights blend toward the
  coarser level's surface, ``z = (1 - alpha) z_fine + alpha z_coarse`` with
  ``alpha = max over x, z of clamp((|p - viewer| / spacing - ((n-1)/2 - w - 1)) / w, 0, 1)`` (GPU Gems' vertex
  shader), so the two levels meet with no gap and no pop as levels move. Zero-area triangles along each
  level's outer border cover the T-junctions' rounding cracks.
* Losasso & Hoppe deactivate the finer levels when the viewer is high above the terrain: level l is drawn
  only while the viewer's height above the terrain is at most ``0.4 n g_l`` (``g_l`` its spacing in metres).

**Where we had to choose.**

* We draw each level's ring directly (every quad of the level's lattice that the finer level does not cover),
  culled in square blocks of ``(n+1)/4`` quads per side (the publication's block size) against the frustum
  with the block's own vertex bounds; we need no vertex-buffer reuse, so any odd ``n >= 15`` works (it is the
  fittable threshold: larger is finer). The snap rule ``origin = 2 s * round((viewer - (n-1)/2 s) / 2 s)``
  keeps the viewer within one spacing of the centre, so the GPU Gems alpha reaches 1 on the whole outer
  border; there we set alpha to exactly 1 (not 1 minus float rounding), so the border is the coarse surface.
* Coarse heights are the full-resolution samples at the coarse lattice points (Losasso & Hoppe prefilter the
  pyramid; point sampling keeps the finest level exact, so its error is 0 where it reaches) and the coarse
  surface inside a coarse quad is its two triangles, split along the same diagonal as every grid here.
* Lattice points past the heightmap are clamped to its border (quads wholly outside are not drawn), the coarse
  surface is evaluated in its clamped quads, and the outer border still meets it exactly.
* ``levels=None`` takes enough levels for the coarsest to cover the terrain from any viewer above it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..camera import Camera, relative_origin
from ..heightmap import Heightmap
from ..kernels.checks import check_int, check_number
from ..kernels.schemes import clipmap_mesh
from ..mesh import Draws, Mesh
from .scheme import SelectThenMesh

__all__ = ["Clipmap", "ClipmapLevels", "ACTIVE_HEIGHT_RATIO"]

ACTIVE_HEIGHT_RATIO = 0.4  # Losasso & Hoppe: level l is active while the viewer height <= 0.4 n g_l
# how GPU Gems 2 ch. 2 draws a block (pipeline statistics): one draw per block (and per level's stitches) from a
# vertex buffer of 2D grid positions (8 bytes), the vertex shader fetching the fine and coarse heights from the
# level's elevation texture (one 2-float texel: 2 x 4 bytes)
VERTEX_BYTES = 8
TEXELS_PER_VERTEX = 2


@dataclass(frozen=True)
class ClipmapLevels:
    """The drawn levels of one frame (finest first; structure of arrays over the K drawn levels).

    Attributes:
        level: (K,) int32 clipmap level (spacing ``2**level`` cells); origin: (K, 2) float32 lattice corner in
            cells; spacing: (K,) float32 cells; coarser: (K,) int32 1 when a coarser level surrounds it;
        hole: (K, 4) int32 quads ``[a0, a1) x [b0, b1)`` covered by the finer level (zeros for the finest).
        viewer: the viewer's (x, z) in cells.
        stats: levels drawn, first (finest active) level.
    """

    level: np.ndarray
    origin: np.ndarray
    spacing: np.ndarray
    coarser: np.ndarray
    hole: np.ndarray
    viewer: tuple[float, float]
    stats: dict = field(default_factory=dict)


@dataclass(eq=False)
class Clipmap(SelectThenMesh):
    """Geometry clipmaps over a heightmap (see the module docstring).

    Args:
        heightmap: the terrain (no NaN).
        n: vertices per level side (odd, >= 15; GPU Gems 255). Larger is finer.
        levels: number of levels L (default: the coarsest covers the terrain from anywhere above it).
        transition: transition width w in grid units (default n / 10), in (0, ((n-1)/2 - 1) / 2].
        active_height_ratio: Losasso & Hoppe's 0.4 (None: every level always drawn).
        device: Warp device.
    """

    heightmap: Heightmap
    n: int = 255
    levels: int | None = None
    transition: float | None = None
    active_height_ratio: float | None = ACTIVE_HEIGHT_RATIO
    device: str = "cpu"
    _h: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.heightmap, Heightmap):
            raise TypeError(f"heightmap: expected a Heightmap, got {type(self.heightmap).__name__}")
        if np.isnan(self.heightmap.heights).any():
            raise ValueError("heightmap: clipmaps here expect no NaN (no-data) heights")
        self.n = check_int("n", self.n, 15)
        if self.n % 2 == 0:
            raise ValueError(f"n: expected an odd integer >= 15, got {self.n!r}")
        m = (self.n - 1) // 2
        if self.transition is None:
            self.transition = self.n / 10.0
        self.transition = check_number("transition", self.transition, 0.0, (m - 1) / 2, lo_open=True)
        hh, ww = self.heightmap.shape
        if self.levels is None:
            self.levels = max(1, math.ceil(math.log2(max(max(ww - 1, hh - 1) / (m - 1), 1.0)) - 1e-12) + 1)
        self.levels = check_int("levels", self.levels, 1, 24)
        if self.active_height_ratio is not None:
            self.active_height_ratio = check_number("active_height_ratio", self.active_height_ratio, 0.0, lo_open=True)
        self._h = np.ascontiguousarray(self.heightmap.heights, np.float32)

    @property
    def block(self) -> int:
        """Quads per culling block side: GPU Gems' block of m = (n+1)/4 vertices."""
        return max(1, (self.n + 1) // 4)

    # -- the levels of a frame ------------------------------------------------------------------------
    def finest_active(self, camera: Camera) -> int:
        """The finest level drawn: Losasso & Hoppe's height rule (0 without it)."""
        if self.active_height_ratio is None:
            return 0
        hm = self.heightmap
        (x0, z0), (x1, z1) = hm.bounds_xz
        ex, ey, ez = camera.position
        ground = float(hm.sample(min(max(ex, x0), x1), min(max(ez, z0), z1)))
        above = max(ey - ground, 0.0)
        g = min(hm.dx, hm.dz)
        for lv in range(self.levels):
            if above <= self.active_height_ratio * self.n * g * 2 ** lv:
                return lv
        return self.levels - 1

    def select(self, camera: Camera) -> ClipmapLevels:
        """Each drawn level's snapped lattice and the hole its finer level leaves."""
        hm = self.heightmap
        n, m = self.n, (self.n - 1) // 2
        v = ((camera.position[0] - hm.origin[0]) / hm.dx, (camera.position[2] - hm.origin[1]) / hm.dz)
        first = self.finest_active(camera)
        lv = np.arange(first, self.levels)
        s = np.exp2(lv.astype(np.float64))
        origin = np.stack([2 * s * np.floor((v[k] - m * s) / (2 * s) + 0.5) for k in (0, 1)], 1)
        hole = np.zeros((len(lv), 4), np.int64)
        if len(lv) > 1:
            a0 = (origin[:-1] - origin[1:]) / s[1:, None]  # the finer level's corner in this level's quads
            hole[1:, 0], hole[1:, 2] = a0[:, 0], a0[:, 1]
            hole[1:, 1], hole[1:, 3] = a0[:, 0] + m, a0[:, 1] + m
            if (hole[1:, [0, 2]] < 1).any() or (hole[1:, [1, 3]] > n - 2).any():
                raise AssertionError("clipmap nesting: a finer level reaches its coarser level's border")
        coarser = (lv < self.levels - 1).astype(np.int32)
        return ClipmapLevels(lv.astype(np.int32), origin.astype(np.float32), s.astype(np.float32), coarser,
                             hole.astype(np.int32), (float(v[0]), float(v[1])),
                             {"levels_drawn": int(len(lv)), "finest_level": int(first)})

    # -- mesh -----------------------------------------------------------------------------------------
    def mesh(self, camera: Camera, sel: ClipmapLevels) -> Mesh:
        """Every drawn level's vertices (transition-blended by ``camera``'s viewer position, as the vertex shader
        does each frame), culled blocks of quads and stitches, as a Mesh. ``sel`` may be another frame's
        levels (held): the blend still follows this camera."""
        hm = self.heightmap
        m = (self.n - 1) // 2
        planes = camera.frustum_planes()
        viewer = ((camera.position[0] - hm.origin[0]) / hm.dx, (camera.position[2] - hm.origin[1]) / hm.dz)
        pos, uv, lev, item, tri, draws, groups = clipmap_mesh(
            self._h, sel.origin, sel.spacing, sel.coarser, sel.level, sel.hole, self.n, viewer,
            m - self.transition - 1.0, self.transition, planes, relative_origin(hm.origin, camera.position), hm.dx,
            hm.dz, self.block, device=self.device)
        return Mesh(positions=pos, eye=camera.position, triangles=tri, uv=uv, level=lev, patch_id=item,
                    draws=Draws(ranges=draws, groups=groups, vertex_bytes=VERTEX_BYTES,
                                texels_per_vertex=TEXELS_PER_VERTEX))


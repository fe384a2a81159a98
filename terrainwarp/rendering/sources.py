"""Prebuilt meshes as :class:`terrainwarp.rendering.pipeline.MeshSource` s, so ``render`` draws them too.

* :class:`StreamedSource`: a streamed heightmap's quadtree frames (``render`` makes one for a scene whose
  heightmap is a :class:`terrainwarp.StreamedHeightmap`): selection on its pyramids, then the patches
  tessellated and displaced from the overview windows they need (:mod:`terrainwarp.lod.streaming`).
* :class:`PeerSource`: a Martini/Delatin mesh (:mod:`terrainwarp.lod.peers`) made camera-relative; no
  selection (0 ms).
* :class:`PolytreeSource`: level ``level`` of a taylor-barrett polytree; no selection (0 ms).
* :class:`BintreeSource`: the mrbsp apparent-size selection of a bintree; the whole call is selection.
* :class:`CdlodSource`, :class:`ClipmapSource`, :class:`ChunkedSource`: the schemes engines ship (CDLOD,
  geometry clipmaps, Chunked LOD with skirts; :mod:`terrainwarp.lod.cdlod`, ``.clipmaps``, ``.chunked``),
  selected per frame (select_ms: their selection) and meshed by their vertex stage. :data:`SCHEMES` names
  each one's fittable parameter, its range and which way is finer; :func:`scheme_source` makes one.

Each holds what it was built from, the time that took (``build_ms``, kept apart from frame cost), and a
cache (the heightmap's normal map) that sources of the same heightmap may share::

    cache = {}
    src = PeerSource(delatin_mesh(hm, 2.0), hm, cache=cache)
    frame = render(scene, source=src)   # select_ms = 0, mesh_ms = to_mesh
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import Any, NamedTuple

import numpy as np
import warp as wp

from ..camera import Camera
from ..heightmap import Heightmap, StreamedHeightmap
from ..kernels.displacement import drop_nonfinite_triangles, sample_normal_map
from ..kernels.normals import sobel_normals
from ..kernels.stack import stack_displace
from ..kernels.tessellator import tessellate_patches
from ..lod.bintree import Bintree, select_bintree
from ..lod.cdlod import Cdlod
from ..lod.chunked import ChunkedLod
from ..lod.clipmaps import Clipmap
from ..lod.peers import PeerMesh
from ..lod.policies import make_policy
from ..lod.polytree import Polytree
from ..lod.quadtree import LodState, PatchList, Terrain, select
from ..lod.streaming import overview_windows
from ..mesh import Mesh
from ..scene import LodConfig

__all__ = ["SourceBase", "StreamedSource", "PeerSource", "PolytreeSource", "BintreeSource", "CdlodSource",
           "ClipmapSource", "ChunkedSource", "SchemeSpec", "SCHEMES", "scheme_source", "scheme_range"]


@dataclass(eq=False)
class SourceBase:
    """What every source carries: a cache (a dict the caller may share between sources of one heightmap).
    Subclass it and add ``mesh_for(camera)`` for a new kind of source."""

    cache: dict = field(default_factory=dict, kw_only=True, repr=False)

    def cached(self, key: object, make: Callable[[], Any]) -> Any:
        if key not in self.cache:
            self.cache[key] = make()
        return self.cache[key]

    def is_cached(self, key: object) -> bool:
        return key in self.cache


@dataclass(eq=False)
class StreamedSource(SourceBase):
    """Quadtree frames of a :class:`StreamedHeightmap`, reading only the tiles under the drawn patches.

    Selection is :func:`terrainwarp.lod.select` on the streamed pyramids; the patches are tessellated as in
    memory (one launch, the same edge factors), then displaced from one overview window per step the
    patches need (:func:`terrainwarp.lod.streaming.overview_windows`, :func:`terrainwarp.kernels.stack.
    stack_displace`), with vertex normals by central differences in the window each vertex read. With
    ``full_resolution`` (a heightmap that fits in memory) the one window is the whole grid, read tile by
    tile, and the normals are its Sobel map's, as in memory: the frame is bit for bit the in-memory one.

    ``last`` holds the latest frame's counters: tiles read, bytes read and cache hits (for that frame),
    the windows and their samples, the tile cache's resident bytes, the pyramid blocks built.
    """

    heightmap: StreamedHeightmap
    lod: LodConfig = field(default_factory=LodConfig)
    device: str = "cpu"
    full_resolution: bool = False
    terrain: Terrain | None = None
    state: LodState | None = None
    build_ms: float = 0.0
    last: dict = field(default_factory=dict)
    provides_normals: bool = True  # the mesh carries vertex normals: no heightmap normal map is made

    def __post_init__(self) -> None:
        if not isinstance(self.heightmap, StreamedHeightmap):
            raise TypeError(f"heightmap: expected a StreamedHeightmap, got {type(self.heightmap).__name__}")
        if self.lod.filter != "bilinear":
            raise ValueError(f"lod.filter: a streamed heightmap is displaced 'bilinear', got {self.lod.filter!r}")
        if self.terrain is None:
            t0 = time.perf_counter()
            self.terrain = Terrain.prepare(self.heightmap, roots=self.lod.roots, tess=self.lod.tess,
                                           device=self.device)
            self.build_ms = (time.perf_counter() - t0) * 1e3
        self._zero = wp.zeros(1, dtype=wp.float32, device=self.device)

    def mesh_for(self, camera: Camera) -> tuple[Mesh, float]:
        hm = self.heightmap
        before = hm.counters()
        blocks = dict(self.terrain.provider.counters)
        t0 = time.perf_counter()
        patches = select(self.terrain, camera, make_policy(self.lod), self.state, device=self.device)
        select_ms = (time.perf_counter() - t0) * 1e3
        mesh, windows = self.mesh_of(patches, camera)
        after = hm.counters()
        self.last = {k: after[k] - before[k] for k in ("tiles_read", "bytes_read", "hits")}
        self.last.update(windows=len(windows), window_samples=int(sum(w[3] * w[4] for w in windows)),
                         finest_step=1 << windows[0][0] if windows else 0,
                         coarsest_step=1 << windows[-1][0] if windows else 0, patches=len(patches),
                         cache_resident_bytes=after["resident_bytes"],
                         pyramid_blocks_built=self.terrain.provider.counters["blocks_built"] - blocks["blocks_built"])
        self.patches = patches
        return mesh, select_ms

    def mesh_of(self, patches: PatchList, camera: Camera) -> tuple[Mesh, list[tuple[int, int, int, int, int]]]:
        """The patches tessellated for ``camera`` and displaced from their overview windows."""
        hm = self.heightmap
        factor = np.maximum(patches.outer.max(axis=1, initial=1.0), patches.inner.max(axis=1, initial=1.0))
        windows = [(0, 0, 0, *hm.shape)] if self.full_resolution and len(patches) else \
            overview_windows(hm, patches.origin_cells, patches.size_cells, factor)
        if self.full_resolution and windows:  # the whole grid, read from the tiles once and kept
            stack = [(0, 0, 0, self.cached(("grid",), lambda: hm.window(1, 0, 0, *hm.shape)))]
        else:
            stack = [(sh, r0, c0, hm.window(1 << sh, r0, c0, rows, cols)) for sh, r0, c0, rows, cols in windows]
        stand_in = wp.array(ptr=self._zero.ptr, dtype=wp.float32, shape=hm.shape, strides=(0, 0),
                            device=self.device, copy=False)  # the grid's shape, no heights: displaced below
        t = tessellate_patches({"origin_xz": patches.origin, "size": patches.size, "outer": patches.outer,
                                "inner": patches.inner, "level": patches.level}, stand_in, hm.dx, hm.dz,
                               camera.position, spacing=self.lod.spacing, origin=hm.origin, device=self.device,
                               need=("uv", "level", "patch_id"), uv_cells=True)
        if not stack:
            return Mesh(positions=t.positions, eye=camera.position, triangles=t.triangles, uv=t.uv, level=t.level,
                        patch_id=t.patch_id, normals=np.zeros_like(t.positions)), windows
        pos, nrm, _ = stack_displace(t.uv, t.positions, stack, [hm.source.level_shape(1 << w[0]) for w in stack],
                                     float(camera.position[1]), hm.dx, hm.dz, device=self.device)
        tri = t.triangles
        if any(np.isnan(w[3]).any() for w in stack):  # no-data holes: drop triangles touching them
            pos, tri = drop_nonfinite_triangles(pos, tri, device=self.device)
            nrm[~np.isfinite(nrm).all(axis=1)] = (0.0, 1.0, 0.0)
        w1, h1 = np.float32(max(hm.shape[1] - 1, 1)), np.float32(max(hm.shape[0] - 1, 1))
        uv = np.stack([t.uv[:, 0] / w1, t.uv[:, 1] / h1], axis=1).astype(np.float32)
        if self.full_resolution:  # the in-memory frame's normals: the grid's Sobel map, fetched at uv
            grid = stack[0][3]
            nmap = self.cached(("normal_map", self.device),
                               lambda: sobel_normals(grid, hm.dx, hm.dz, border="clamp", device=self.device))
            nrm = sample_normal_map(nmap, uv, device=self.device)
        return Mesh(positions=pos, eye=camera.position, triangles=tri, uv=uv, level=t.level, patch_id=t.patch_id,
                    normals=nrm), windows


@dataclass(eq=False)
class PeerSource(SourceBase):
    """A peer mesher's static mesh; ``error_m`` its measured vertical error (metres, NaN when not measured)."""

    peer: PeerMesh
    heightmap: Heightmap
    error_m: float = math.nan

    @property
    def build_ms(self) -> float:
        return self.peer.mesh_ms

    def mesh_for(self, camera: Camera) -> tuple[Mesh, float]:
        return self.peer.to_mesh(self.heightmap, camera), 0.0


@dataclass(eq=False)
class PolytreeSource(SourceBase):
    """One level of a polytree (view-independent: the finest level is used when ``level`` is past it)."""

    tree: Polytree
    level: int
    build_ms: float = 0.0
    error_m: float = math.nan

    def mesh_for(self, camera: Camera) -> tuple[Mesh, float]:
        return self.tree.mesh(min(int(self.level), self.tree.n_levels - 1), eye=camera.position), 0.0


@dataclass(eq=False)
class BintreeSource(SourceBase):
    """A bintree selected per frame with the paper's apparent-size rule; the whole call is selection."""

    tree: Bintree
    build_ms: float = 0.0
    error_m: float = math.nan

    def mesh_for(self, camera: Camera) -> tuple[Mesh, float]:
        t0 = time.perf_counter()
        mesh = select_bintree(self.tree, camera).mesh
        return mesh, (time.perf_counter() - t0) * 1e3


@dataclass(eq=False)
class _SchemeSource(SourceBase):
    """A scheme selected per frame (``scheme.select(camera)``) and meshed by its vertex stage
    (``scheme.mesh(camera, selection)``); ``scheme.frame(camera)`` times the selection."""

    scheme: Cdlod | Clipmap | ChunkedLod

    def mesh_for(self, camera: Camera) -> tuple[Mesh, float]:
        mesh, select_ms, _ = self.scheme.frame(camera)
        return mesh, select_ms

    def held_mesh_for(self, previous: Camera, camera: Camera) -> Mesh:
        """The selection made for ``previous`` drawn for ``camera`` (its vertex stage runs with ``camera``): the
        held LOD that popping compares with ``mesh_for(camera)``."""
        return self.scheme.mesh(camera, self.scheme.select(previous))


@dataclass(eq=False)
class CdlodSource(_SchemeSource):
    """CDLOD (:class:`terrainwarp.lod.cdlod.Cdlod`): distance-range quadtree selection, then one morphing vertex
    launch; ``build_ms`` the pyramids' time."""

    scheme: Cdlod

    @property
    def build_ms(self) -> float:
        return self.scheme.terrain.time_ms


@dataclass(eq=False)
class ClipmapSource(_SchemeSource):
    """Geometry clipmaps (:class:`terrainwarp.lod.clipmaps.Clipmap`): the levels snapped to the viewer, then
    the blended vertices and the culled ring quads; nothing is built ahead (``build_ms`` 0)."""

    scheme: Clipmap
    build_ms: float = 0.0


@dataclass(eq=False)
class ChunkedSource(_SchemeSource):
    """Chunked LOD with skirts (:class:`terrainwarp.lod.chunked.ChunkedLod`): screen-space-error selection of
    chunks, then their grids and skirts; ``build_ms`` the pyramids' time."""

    scheme: ChunkedLod

    @property
    def build_ms(self) -> float:
        return self.scheme.terrain.time_ms


class SchemeSpec(NamedTuple):
    """A scheme's fittable parameter: the keyword of its class, the range a fit searches, whether a larger value
    is finer, and whether it is an integer (``n`` is odd besides)."""

    scheme: type
    source: type
    parameter: str
    lo: float
    hi: float
    larger_is_finer: bool
    integer: bool


SCHEMES: dict[str, SchemeSpec] = {
    # first_range in metres; its lower end is the scheme's own min_first_range (seams below it), its upper end
    # any distance past the farthest visible point (everything at full detail)
    "cdlod": SchemeSpec(Cdlod, CdlodSource, "first_range", 0.0, math.inf, True, False),
    "clipmaps": SchemeSpec(Clipmap, ClipmapSource, "n", 15, 4095, True, True),
    "chunked": SchemeSpec(ChunkedLod, ChunkedSource, "max_sse_px", 0.0, 64.0, False, False),
}


def _spec(name: str) -> SchemeSpec:
    if name not in SCHEMES:
        raise ValueError(f"name: expected one of {sorted(SCHEMES)}, got {name!r}")
    return SCHEMES[name]


def _base_scheme(name: str, heightmap: Heightmap, cache: dict, params: dict) -> Cdlod | ChunkedLod:
    """The scheme ``name`` with ``params`` whose pyramids every value shares (kept in ``cache``)."""
    spec = SCHEMES[name]
    key = ("scheme", name, tuple(sorted(params.items())))
    if key not in cache:
        start = spec.hi if math.isfinite(spec.hi) else 1.0  # any valid value: it is replaced per source
        cache[key] = spec.scheme(heightmap, **{spec.parameter: start}, **params)
    return cache[key]


def scheme_source(name: str, heightmap: Heightmap, value: float, *, cache: dict | None = None,
                  **params: Any) -> CdlodSource | ClipmapSource | ChunkedSource:
    """The source of scheme ``name`` (a :data:`SCHEMES` key) with its fittable parameter set to ``value``
    (rounded to the next odd integer for clipmaps' ``n``) and the scheme's other keyword ``params``.

    With a ``cache``, the schemes with pyramids (CDLOD and chunked: a :class:`terrainwarp.lod.Terrain`, which
    does not depend on the parameter) are prepared once per (name, params) and kept there; each source holds
    a copy of that scheme with its own ``value``, the pyramids shared. The clipmaps build nothing ahead."""
    spec = _spec(name)
    if spec.integer:
        value = int(math.ceil(value)) | 1
    if cache is None or "terrain" not in {f.name for f in fields(spec.scheme)}:
        scheme = spec.scheme(heightmap, **{spec.parameter: value}, **params)
        return spec.source(scheme=scheme, cache={} if cache is None else cache)
    zero_ok = not spec.larger_is_finer  # a zero threshold is full detail; a zero range is no range
    if not (math.isfinite(value) and spec.lo <= value <= spec.hi and (value > spec.lo or zero_ok)):
        raise ValueError(f"value: expected a finite {spec.parameter} in the range of {name!r} "
                         f"({spec.lo:g}..{spec.hi:g}), got {value}")
    scheme = copy.copy(_base_scheme(name, heightmap, cache, params))
    setattr(scheme, spec.parameter, value)
    return spec.source(scheme=scheme, cache=cache)


def scheme_range(name: str, heightmap: Heightmap, *, cache: dict | None = None,
                 **params: Any) -> tuple[float, float]:
    """The finite range a sweep or a fit searches for scheme ``name``'s parameter on ``heightmap``: the
    :data:`SCHEMES` range, with CDLOD's ends made concrete: from its seam-free
    :attr:`terrainwarp.lod.cdlod.Cdlod.min_first_range` (at least one sample spacing) to twice the diagonal of
    the terrain's box (every point within the first range from any eye over the terrain: full detail), and a
    zero lower end (chunked's 0 px: full detail) raised to ``hi / 4096``, so the range can be searched in log
    space."""
    spec = _spec(name)
    if name != "cdlod":
        return (float(spec.lo) if spec.lo > 0 else spec.hi / 4096.0), float(spec.hi)
    base = _base_scheme(name, heightmap, {} if cache is None else cache, params)
    (x0, z0), (x1, z1) = heightmap.bounds_xz
    lo_h, hi_h = heightmap.height_range
    lo = max(base.min_first_range, min(heightmap.dx, heightmap.dz))
    return lo, max(2.0 * math.sqrt((x1 - x0) ** 2 + (z1 - z0) ** 2 + (hi_h - lo_h) ** 2), 2.0 * lo)

"""Mesh sources: what ``render(scene, source=...)`` draws in place of the scene's quadtree policy.

:class:`MeshSource` is the protocol: every member the pipeline reads. :class:`SourceBase` gives each one but
``mesh_for`` a default; subclass it (a dataclass) and write ``mesh_for(camera)`` for a new LOD scheme, then
register it by name (:func:`terrainwarp.schemes.register_scheme`) to have the report and the fit take it.
``examples/custom_scheme.py`` does both in under 80 lines. The sources here:

* :class:`StreamedSource`: a streamed heightmap's quadtree frames (``render`` makes one for a scene whose
  heightmap is a :class:`terrainwarp.heightmap.StreamedHeightmap`): selection on its pyramids, then the
  patches tessellated and displaced from the overview windows they need (:mod:`terrainwarp.lod.streaming`).
* :class:`PeerSource`: a Martini/Delatin mesh (:mod:`terrainwarp.lod.peers`) made camera-relative; no
  selection (0 ms).
* :class:`PolytreeSource`: level ``level`` of a taylor-barrett polytree; no selection (0 ms).
* :class:`BintreeSource`: the mrbsp apparent-size selection of a bintree; the whole call is selection.
* :class:`CdlodSource`, :class:`ClipmapSource`, :class:`ChunkedSource`: the schemes engines ship (CDLOD,
  geometry clipmaps, Chunked LOD with skirts; :mod:`terrainwarp.lod.cdlod`, ``.clipmaps``, ``.chunked``),
  selected per frame (select_ms: their selection) and meshed by their vertex stage; registered as the
  schemes ``cdlod``, ``clipmaps`` and ``chunked`` (:data:`terrainwarp.schemes.SCHEMES`: each one's fittable
  parameter, its range and which way is finer); :func:`terrainwarp.schemes.scheme_source` makes one.

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
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Protocol, runtime_checkable

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
from ..lod.cesium import CesiumTerrain
from ..lod.chunked import ChunkedLod
from ..lod.clipmaps import Clipmap
from ..lod.peers import PeerMesh
from ..lod.policies import make_policy
from ..lod.polytree import Polytree
from ..lod.quadtree import LodState, PatchList, Terrain, select
from ..lod.streaming import overview_windows
from ..mesh import Mesh
from ..scene import POLICY_TABLE, LodConfig, Scene
from ..schemes import (  # noqa: F401 - SCHEMES, SchemeSpec, scheme_range: importable here as before
    SCHEMES,
    SchemeKnob,
    SchemeSpec,
    register_scheme,
    scheme_default,
    scheme_range,
    scheme_source,
)

# SCHEMES, SchemeSpec, scheme_source and scheme_range are terrainwarp.schemes', importable here as before
__all__ = ["MeshSource", "SourceBase", "missing_members", "StreamedSource", "PeerSource", "PolytreeSource",
           "BintreeSource", "CdlodSource", "ClipmapSource", "ChunkedSource", "CesiumSource", "scene_source"]


# ------------------------------------------------------------------------------------------------
# the protocol and its defaults
# ------------------------------------------------------------------------------------------------
@runtime_checkable
class MeshSource(Protocol):
    """A mesh made outside the quadtree LOD path (a LOD scheme, a peer mesher's static mesh, a polytree level, a
    bintree selection, a streamed terrain's frames), drawn by ``render(scene, source=...)`` in place of the
    scene's ``mesh`` policy. The source is an object the caller holds across frames, like a Terrain: what
    persists between frames (the built mesh or tree, the heightmap's normal map) lives in it.

    What the pipeline reads of it, per frame: ``mesh_for`` in the ``select`` stage (its selection time is the
    stage's, the rest of the call is the ``mesh`` stage's), then ``last``, ``patches`` and ``report_info()``;
    ``provides_normals`` when it plans the stages, ``cached``/``is_cached`` for the normal map;
    :func:`terrainwarp.rendering.pop_stats` calls ``held_mesh_for``; the report sweep reads ``build_ms`` and
    ``error_m``. :class:`SourceBase` has a default for every member but ``mesh_for``.

    Attributes:
        provides_normals: the meshes carry vertex normals (``Mesh.normals``), so no heightmap normal map is
            made; False: shading fetches the heightmap's normal map where each vertex lies.
        build_ms: what building the source took (ms), reported apart from frame cost (``peer_mesh_ms``).
        error_m: the mesh's measured vertical error (metres), NaN when not measured (``peer_error_m``).
        patches: the :class:`terrainwarp.lod.PatchList` the latest ``mesh_for`` drew (``Frame.patches``), or
            None for a mesh that is not made of quadtree patches.
        last: counters of the latest ``mesh_for`` (added to the ``select`` stage's counters in the report).
    """

    provides_normals: bool
    build_ms: float
    error_m: float
    patches: PatchList | None
    last: Mapping[str, Any]

    def mesh_for(self, camera: Camera) -> tuple[Mesh, float]:
        """The mesh to draw from ``camera`` (positions relative to ``camera.position``, float32 (n, 3);
        triangles int32 (m, 3), counter-clockwise seen from above) and the ms of the call spent selecting (0.0
        for a static mesh: the whole call is meshing)."""
        ...

    def held_mesh_for(self, previous: Camera, camera: Camera) -> Mesh:
        """The selection made for ``previous`` drawn for ``camera``: the held LOD that popping compares with
        ``mesh_for(camera)`` (a scheme's per-frame morph or snapping is then not counted as a pop)."""
        ...

    def cached(self, key: object, make: Callable[[], Any]) -> Any:
        """The value kept under ``key``, made by ``make()`` on first use (as :meth:`Terrain.cached`)."""
        ...

    def is_cached(self, key: object) -> bool:
        """Whether ``key`` is kept (the report says a normal map was cached rather than made)."""
        ...

    def report_info(self) -> dict[str, Any]:
        """Entries for the frame's ``Report.info`` after each ``mesh_for`` (a streamed terrain's tiles read)."""
        ...


def missing_members(source: object) -> list[str]:
    """The :class:`MeshSource` members ``source`` lacks (empty for a complete source)."""
    names = ["mesh_for", "held_mesh_for", "cached", "is_cached", "report_info", "provides_normals", "build_ms",
             "error_m", "patches", "last"]
    return [n for n in names if not hasattr(source, n)]


@dataclass(eq=False)
class SourceBase:
    """The defaults of every :class:`MeshSource` member but ``mesh_for``: a cache (a dict the caller may share
    between sources of one heightmap), no vertex normals, nothing built (0 ms), the error not measured, no
    patches, no counters, the held mesh re-made for the previous camera. Subclass it (a dataclass) and write
    ``mesh_for(camera)``; a subclass may declare any of the attributes as its own fields or properties."""

    cache: dict = field(default_factory=dict, kw_only=True, repr=False)
    provides_normals = False
    build_ms = 0.0
    error_m = math.nan
    patches = None
    last = MappingProxyType({})  # class attributes, not fields: a subclass may declare them as its own

    def mesh_for(self, camera: Camera) -> tuple[Mesh, float]:  # pragma: no cover - every source defines it
        raise NotImplementedError(f"{type(self).__name__}.mesh_for(camera): a MeshSource makes the frame's mesh")

    def held_mesh_for(self, previous: Camera, camera: Camera) -> Mesh:
        """The mesh made for ``previous`` (right for a static mesh, and for a scheme whose vertices do not
        depend on the camera once selected; a scheme that morphs or snaps per frame overrides it)."""
        return self.mesh_for(previous)[0]

    def cached(self, key: object, make: Callable[[], Any]) -> Any:
        if key not in self.cache:
            self.cache[key] = make()
        return self.cache[key]

    def is_cached(self, key: object) -> bool:
        return key in self.cache

    def report_info(self) -> dict[str, Any]:
        return {}


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
    the windows and their samples, the tile cache's resident bytes, the pyramid blocks built. ``attributes``:
    the meshes carry level and patch id (uv they always carry); ``render`` sets it for the source a heightmap
    holds to what the scene reads (the mesh or patches outputs, the level and patch shadings).
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
    attributes: bool = True

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

    def report_info(self) -> dict[str, Any]:
        """``{"tiles": {"tiles_read", "bytes_read", "hits"}}``: what the latest frame read."""
        return {"tiles": {k: self.last[k] for k in ("tiles_read", "bytes_read", "hits")}}

    def mesh_of(self, patches: PatchList, camera: Camera) -> tuple[Mesh, list[tuple[int, int, int, int, int]]]:
        """The patches tessellated for ``camera`` and displaced from their overview windows."""
        hm = self.heightmap
        factor = np.maximum(patches.outer.max(axis=1, initial=1.0), patches.inner.max(axis=1, initial=1.0))
        windows = [(0, 0, 0, *hm.shape)] if self.full_resolution and len(patches) else \
            overview_windows(hm, patches.origin_cells, patches.size_cells, factor)
        if self.full_resolution and windows:  # the whole grid, read from the tiles once and kept
            stack = [(0, 0, 0, self.cached(("grid",), lambda: hm.window(1, 0, 0, *hm.shape)))]
            data = stack[0][3].reshape(-1)
        else:  # every window assembled from the tiles straight into one flat buffer, the kernel's
            data = np.empty(sum(w[3] * w[4] for w in windows), np.float32)
            stack, at = [], 0
            for sh, r0, c0, rows, cols in windows:
                part = data[at:at + rows * cols].reshape(rows, cols)
                stack.append((sh, r0, c0, hm.window(1 << sh, r0, c0, rows, cols, out=part)))
                at += rows * cols
        stand_in = wp.array(ptr=self._zero.ptr, dtype=wp.float32, shape=hm.shape, strides=(0, 0),
                            device=self.device, copy=False)  # the grid's shape, no heights: displaced below
        t = tessellate_patches({"origin_xz": patches.origin, "size": patches.size, "outer": patches.outer,
                                "inner": patches.inner, "level": patches.level}, stand_in, hm.dx, hm.dz,
                               camera.position, spacing=self.lod.spacing, origin=hm.origin, device=self.device,
                               need=("uv", "level", "patch_id") if self.attributes else ("uv",), uv_cells=True)
        if not stack:
            return Mesh(positions=t.positions, eye=camera.position, triangles=t.triangles, uv=t.uv, level=t.level,
                        patch_id=t.patch_id, normals=np.zeros_like(t.positions), counters=t.counters), windows
        pos, nrm, _ = stack_displace(t.uv, t.positions, stack, [hm.source.level_shape(1 << w[0]) for w in stack],
                                     hm.shape, float(camera.position[1]), hm.dx, hm.dz, device=self.device, data=data,
                                     shifts=False)
        tri = t.triangles
        if np.isnan(data.min()):  # no-data holes (min is NaN when any is): drop triangles touching them
            pos, tri = drop_nonfinite_triangles(pos, tri, device=self.device)
            nrm[~np.isfinite(nrm).all(axis=1)] = (0.0, 1.0, 0.0)
        uv = t.uv  # in cells, for the windows; the mesh's in [0, 1], divided in place (no frame-sized copies)
        uv[:, 0] /= np.float32(max(hm.shape[1] - 1, 1))
        uv[:, 1] /= np.float32(max(hm.shape[0] - 1, 1))
        if self.full_resolution:  # the in-memory frame's normals: the grid's Sobel map, fetched at uv
            grid = stack[0][3]
            nmap = self.cached(("normal_map", self.device),
                               lambda: sobel_normals(grid, hm.dx, hm.dz, border="clamp", device=self.device))
            nrm = sample_normal_map(nmap, uv, device=self.device)
        return Mesh(positions=pos, eye=camera.position, triangles=tri, uv=uv, level=t.level, patch_id=t.patch_id,
                    normals=nrm, counters=t.counters), windows


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


@dataclass(eq=False)
class CesiumSource(_SchemeSource):
    """Cesium's heightmap terrain (:class:`terrainwarp.lod.cesium.CesiumTerrain`): 65 x 65-sample tiles selected by
    Cesium's screen-space-error rule, then their grids and skirts; ``build_ms`` the pyramids' time."""

    scheme: CesiumTerrain

    @property
    def build_ms(self) -> float:
        return self.scheme.terrain.time_ms


def scene_source(scene: Scene, device: str = "cpu") -> MeshSource:
    """The mesh source that draws a LOD scene whose ``LodConfig.policy`` is a scheme (``render`` makes it):
    :func:`terrainwarp.schemes.scheme_source` with the configuration's ``params`` (a main parameter left out
    takes :func:`terrainwarp.schemes.scheme_default`), what the scheme prepares kept in the heightmap's
    ``held`` cache per device, so every frame and every setting of one heightmap share its pyramids."""
    hm, lod = scene.heightmap, scene.lod
    if not lod.is_scheme:
        raise ValueError(f"lod.policy: expected a registered scheme, got the quadtree policy {lod.policy!r}")
    if not isinstance(hm, Heightmap) or isinstance(hm, StreamedHeightmap):
        raise ValueError(f"lod.policy: the scheme {lod.policy!r} draws an in-memory Heightmap; a streamed heightmap "
                         f"is drawn by the quadtree policies ({', '.join(POLICY_TABLE)})")
    cache = hm.held.schemes.setdefault(str(device), {})
    params = dict(lod.params)
    value = params.pop(SCHEMES[lod.policy].parameter, None)
    if value is None:
        value = scheme_default(lod.policy, hm, cache=cache, device=device, **params)
    return scheme_source(lod.policy, hm, value, cache=cache, device=device, **params)


# ------------------------------------------------------------------------------------------------
# the built-in schemes, registered by name (terrainwarp.schemes)
# ------------------------------------------------------------------------------------------------
def _shared(scheme_cls: type, heightmap: Heightmap, cache: dict, params: dict, **value: Any) -> Any:
    """A copy of the scheme prepared once per structural keyword ``params`` (its pyramids, kept in ``cache``),
    with ``value`` (the main parameter and the knobs that change no prepared data) set on the copy."""
    key = ("scheme", scheme_cls.__name__, tuple(sorted(params.items())))
    if key not in cache:
        name, v = next(iter(value.items()))
        cache[key] = scheme_cls(heightmap, **{name: v}, **params)  # the other knobs are set per source
    scheme = copy.copy(cache[key])
    for k, v in value.items():
        setattr(scheme, k, v)
    return scheme


def _make_cdlod(heightmap: Heightmap, value: float, *, cache: dict, ratio: float = 2.0,
                morph_start_ratio: float = 0.7, grid: int = 32, **params: Any) -> CdlodSource:
    """CDLOD at first range ``value`` (m); ``grid`` is structural (the pyramids have ``tess = grid``)."""
    return CdlodSource(scheme=_shared(Cdlod, heightmap, cache, {"grid": grid, **params}, first_range=value,
                                      ratio=ratio, morph_start_ratio=morph_start_ratio), cache=cache)


def _make_clipmaps(heightmap: Heightmap, value: int, *, cache: dict, levels: int | None = None,
                   transition_ratio: float = 0.1, **params: Any) -> ClipmapSource:
    """Geometry clipmaps of ring size ``value`` (n, odd), ``levels`` (None: cover the terrain) and a transition
    width of ``transition_ratio * n`` grid units (GPU Gems' n / 10 by default); nothing is prepared."""
    m = (value - 1) // 2
    w = min(transition_ratio * value, (m - 1) / 2)  # the widest the ring allows
    return ClipmapSource(scheme=Clipmap(heightmap, n=value, levels=levels, transition=w, **params), cache=cache)


def _make_chunked(heightmap: Heightmap, value: float, *, cache: dict, tile: int = 32,
                  **params: Any) -> ChunkedSource:
    """Chunked LOD at maximum error ``value`` (px); ``tile`` is structural (the pyramids have ``tess = tile``)."""
    return ChunkedSource(scheme=_shared(ChunkedLod, heightmap, cache, {"tile": tile, **params}, max_sse_px=value),
                         cache=cache)


def _make_cesium(heightmap: Heightmap, value: float, *, cache: dict, **params: Any) -> CesiumSource:
    """Cesium's heightmap terrain at ``maximumScreenSpaceError`` ``value`` (px); its tiles and errors are prepared
    once per heightmap."""
    return CesiumSource(scheme=_shared(CesiumTerrain, heightmap, cache, params, max_sse_px=value), cache=cache)


def _cdlod_range(heightmap: Heightmap, cache: dict, params: dict) -> tuple[float, float]:
    """CDLOD's first range on ``heightmap`` (and the ``ratio`` and ``morph_start_ratio`` in ``params``): from
    its seam-free :attr:`terrainwarp.lod.cdlod.Cdlod.min_first_range` (at least one sample spacing) to twice the
    diagonal of the terrain's box (every point within the first range from any eye over the terrain: full
    detail)."""
    shaping = {k: params[k] for k in ("ratio", "morph_start_ratio") if params.get(k) is not None}
    structural = {"grid": 32, **{k: v for k, v in params.items() if k not in shaping and v is not None}}
    base = _shared(Cdlod, heightmap, cache, structural, first_range=1.0, **shaping)
    (x0, z0), (x1, z1) = heightmap.bounds_xz
    lo_h, hi_h = heightmap.height_range
    lo = max(base.min_first_range, min(heightmap.dx, heightmap.dz))
    return lo, max(2.0 * math.sqrt((x1 - x0) ** 2 + (z1 - z0) ** 2 + (hi_h - lo_h) ** 2), 2.0 * lo)


_STEPS = (8.0, 4.0, 2.0, 1.0)  # a report's settings of a built-in scheme: finer by each step's factor
# first_range in metres: its lower end is the scheme's own min_first_range (seams below it), its upper end any
# distance past the farthest visible point (everything at full detail); a report sweeps 8, 4, 2, 1 times the minimum
register_scheme("cdlod", _make_cdlod, parameter="first_range", lo=0.0,
                hi=math.inf, larger_is_finer=True, fit_range=_cdlod_range, builtin=True,
                sweep=lambda lo, hi: [min(lo * f, hi) for f in _STEPS],
                doc="CDLOD: distance-range quadtree selection with per-vertex morphing; first range, m",
                knobs=(SchemeKnob("ratio", 1.25, 4.0, 2.0, log=True,
                                  doc="LOD distance ratio: each level's band is ratio times the previous one"),
                       SchemeKnob("morph_start_ratio", 0.3, 0.95, 0.7,
                                  doc="where in its band a level starts morphing (0.7: over the last 30%)"),
                       SchemeKnob("grid", 8, 64, 32, integer=True, choices=(8, 16, 32, 64), structural=True,
                                  doc="quads per node side (the render grid's resolution)")))
# n odd, 2^k - 1 as GPU Gems': a report sweeps 255, 127, 63, 31
register_scheme("clipmaps", _make_clipmaps, parameter="n", lo=15, hi=4095,
                larger_is_finer=True, odd_integer=True, builtin=True, default=255,
                sweep=lambda lo, hi: [min(max(32 * f - 1, lo), hi) for f in _STEPS],
                doc="geometry clipmaps: nested rings around the snapped viewer; ring size n, odd",
                knobs=(SchemeKnob("levels", 1, 24, None, integer=True,
                                  doc="rings drawn (default: enough for the coarsest to cover the terrain; fewer "
                                      "leave the far terrain undrawn)"),
                       SchemeKnob("transition_ratio", 0.02, 0.24, 0.1,
                                  doc="transition width as a fraction of n (GPU Gems: 1/10), at most the ring's "
                                      "half width")))
# a report sweeps 1, 2, 4, 8 px (Cesium's default 2 among them)
register_scheme("chunked", _make_chunked, parameter="max_sse_px", lo=0.0,
                hi=64.0, larger_is_finer=False, builtin=True, default=2.0,
                sweep=lambda lo, hi: [min(max(8.0 / f, lo), hi) for f in _STEPS],
                doc="Chunked LOD with skirts: screen-space-error chunk selection; maximum error, px",
                knobs=(SchemeKnob("tile", 8, 64, 32, integer=True, choices=(8, 16, 32, 64), structural=True,
                                  doc="quads per chunk side"),))
# Cesium's maximumScreenSpaceError: a report sweeps 1, 2 (Cesium's default), 4 and 8 px
register_scheme("cesium", _make_cesium, parameter="max_sse_px", lo=0.0, hi=64.0, larger_is_finer=False, builtin=True,
                default=2.0, sweep=lambda lo, hi: [min(max(8.0 / f, lo), hi) for f in _STEPS],
                doc="Cesium's heightmap terrain: 65x65-sample tiles, Cesium's geometric error and SSE rule; "
                    "maximumScreenSpaceError, px")

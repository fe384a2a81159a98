"""``render(scene) -> Frame``: the pipeline, run backwards from the outputs the scene asks for.

Every frame in the project is made here: grid and LOD scenes, and prebuilt meshes (peer meshers, polytree
levels, bintree selections) passed as a :class:`MeshSource` (``render(scene, source=...)``).

Stages (each a small function of the frame in progress, :data:`_STAGES`):

=============  =============================================================================
stage          what
=============  =============================================================================
prepare        LOD scenes whose heightmap holds no Terrain of their layout yet: quadtree pyramids
               (min/max/error), then held by the heightmap for the frames after (see below)
normal_map     the heightmap's Sobel normal map (cached in the Terrain or the source when one is held)
curvature      heightmap curvature (three-normal, four directions)
select         LOD scenes: the visible patches (policy, balance, edge factors, culling); a source: the
               part of its call spent selecting (0 for a static mesh)
mesh           the full-resolution grid, the patches tessellated and displaced in one launch, or the
               source's mesh (the rest of its call)
raster         the visibility pass (triangle id, depth, barycentrics per pixel)
shade          resolve + hillshade (image, per-pixel normals)
reference      the full-resolution grid rasterized from the same camera (only for ``error``)
error          the primary error at the heightmap's samples (terrainwarp.measure.sample_error, visibility
               from the reference's depth), and the per-pixel grid-image error as secondary fields
               (terrainwarp.measure.error; it carries a triangulation floor): ``Frame.error``, a
               :class:`terrainwarp.measure.error.FrameError`
=============  =============================================================================

Which run, by output (LOD scenes add ``prepare`` and ``select`` wherever ``mesh`` runs; a source adds
``select``), is one table (``_NEEDS``: the stages, and what they must make for the output: mesh attributes,
the barycentric image); :func:`plan_for` turns a scene's outputs into the :class:`Plan` every stage reads:

=========  ==================================================
output     stages
=========  ==================================================
image      normal_map, mesh, raster, shade
normals    normal_map, mesh, raster, shade
depth      mesh, raster
mesh       mesh
patches    select (LOD scenes)
error      mesh, raster, reference, error
curvature  curvature
counters   mesh, raster (each counts its pipeline statistics: ``Report.counters``)
report     (none: the report of whatever ran)
=========  ==================================================

Frame cost (:attr:`Report.frame_ms`) is select + mesh + raster, for every kind of mesh: this simulator's CPU time.
:attr:`Report.host_ms` is the part of the whole call (:attr:`Report.render_ms`) spent outside kernel launches
(:func:`terrainwarp.kernels.parallel.kernel_clock`): the report's ``host`` line.
What a GPU would pay is :attr:`Report.counters` (a scene that asks for ``"counters"``): the pipeline statistics of
the frame's draws as the family issues them (the mesh stage: the tessellator's patch draw, or the mesh's indexed
draws, :class:`terrainwarp.mesh.Draws`) and of the rasterizer (:attr:`terrainwarp.kernels.raster.Fragments.
counters`), named as OpenGL's ARB_pipeline_statistics_query names them
(:data:`terrainwarp.kernels.counters.PIPELINE_COUNTERS`); a scene that does not ask counts nothing.

What persists between frames is held by the heightmap (``Heightmap.held``, per device and setting): a LOD scene's
:class:`terrainwarp.lod.Terrain` (pyramids, the one-launch walk, the normal map), kept for the last
``TERRAINS_HELD`` layouts (roots, tess) drawn, as the schemes' pyramids (CDLOD, chunked, clipmaps) and a streamed
heightmap's source are. So a loop of ``render(scene.with_(camera=c))`` prepares once, on its first frame, and its
``select`` is the prepared one's; ``terrain=`` hands in a Terrain instead (one prepared with another depth, say).
``heightmap.held.clear()`` lets it all go.

A held selection: ``render(scene, terrain, patches=held)`` skips ``select`` (and ``prepare``) and tessellates
the given :class:`terrainwarp.lod.PatchList` (its levels and edge factors as they were selected) for
``scene.camera``. That is the "held" frame of popping: :func:`pop_stats` measures the pop between the
selection of the previous camera and the current one, both drawn for the current camera.
"""

from __future__ import annotations

import functools
import time
import warnings
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import warp as wp

from ..camera import Camera, DepthPrecisionWarning, check_depth_range, relative_origin
from ..heightmap import Heightmap, StreamedHeightmap
from ..io.display import depth_picture, html_table, id_picture, png_bytes
from ..io.files import atomic_path, output_set, write_image, write_json
from ..kernels.checks import check_device
from ..kernels.counters import frame_counters, indexed_draw_counters
from ..kernels.displacement import drop_nonfinite_triangles, grid_mesh, sample_normal_map
from ..kernels.normals import sobel_normals
from ..kernels.parallel import kernel_clock, view
from ..kernels.raster import clip_coordinates, rasterize
from ..kernels.shading import shade, splat_map
from ..kernels.tessellator import tessellate_patches
from ..lod.policies import make_policy
from ..lod.quadtree import LodState, PatchList, Terrain, select
from ..measure.error import FrameError, frame_error
from ..measure.sample_error import PopStats, popping, sample_error
from ..mesh import Draws, Mesh
from ..scene import Scene
from ..surface.differential import compute_curvature
from .sources import MeshSource, StreamedSource, missing_members, scene_source

__all__ = ["render", "Frame", "Report", "StageRecord", "Plan", "plan_for", "stages_for", "MeshSource", "pop_stats",
           "EmptyFrameWarning"]

TERRAINS_HELD = 4  # quadtree layouts (roots, tess) a heightmap holds prepared, per device: the latest drawn
STAGE_ORDER = ("prepare", "normal_map", "curvature", "select", "mesh", "raster", "shade", "reference", "error")
# The one table of what each output needs: the stages that make it, and what those stages must make for it
# (mesh "attributes": uv, level and patch id; raster "barycentrics": the perspective-correct barycentric image).
_NEEDS: dict[str, tuple[frozenset[str], frozenset[str]]] = {
    "image": (frozenset({"normal_map", "mesh", "raster", "shade"}), frozenset({"attributes", "barycentrics"})),
    "normals": (frozenset({"normal_map", "mesh", "raster", "shade"}), frozenset({"attributes", "barycentrics"})),
    "depth": (frozenset({"mesh", "raster"}), frozenset()),
    "mesh": (frozenset({"mesh"}), frozenset({"attributes"})),
    "patches": (frozenset({"select"}), frozenset()),
    "error": (frozenset({"mesh", "raster", "reference", "error"}), frozenset({"barycentrics"})),
    "curvature": (frozenset({"curvature"}), frozenset()),
    "report": (frozenset(), frozenset()),
    "counters": (frozenset({"mesh", "raster"}), frozenset()),
}


@dataclass(frozen=True)
class Plan:
    """What one render of a scene runs and makes, from :data:`_NEEDS`: worked out once per kind of call
    (:func:`plan_for`, cached) and read by the stages.

    Attributes:
        stages: the stages to run, in pipeline order.
        attributes: the mesh carries uv, level and patch id (shading and the mesh output read them; depth,
            error and counters frames read positions and triangles only).
        barycentrics: the visibility pass makes the barycentric image (shading and the error interpolate with it).
        image: shading encodes the 8-bit image; normals: shading writes per-pixel normals.
        depth: the frame keeps its depth image (asked for; otherwise made for the error and dropped).
        counters: the mesh and raster stages count their pipeline statistics.
    """

    stages: tuple[str, ...]
    attributes: bool
    barycentrics: bool
    image: bool
    normals: bool
    depth: bool
    counters: bool


def stages_for(outputs: tuple[str, ...], mesh: str = "grid", have_terrain: bool = False,
               have_patches: bool = False) -> list[str]:
    """The stages that the given outputs need, in pipeline order.

    ``mesh``: ``"grid"``, ``"lod"`` or ``"source"`` (a prebuilt :class:`MeshSource`); ``have_patches``: a LOD
    scene drawn from a given (held) PatchList, which needs no ``select`` and no ``prepare``."""
    return list(plan_for(tuple(outputs), mesh, have_terrain, have_patches).stages)


@functools.lru_cache(maxsize=256)
def plan_for(outputs: tuple[str, ...], mesh: str = "grid", have_terrain: bool = False, have_patches: bool = False,
             provides_normals: bool = False) -> Plan:
    """The :class:`Plan` of a render: its scene's ``outputs`` and ``mesh`` kind (``"grid"``, ``"lod"`` or
    ``"source"``), whether the caller holds a Terrain or a PatchList (no ``prepare``; no ``select`` either), and
    whether a source's meshes carry their normals (no ``normal_map``)."""
    need: set[str] = set()
    made: set[str] = set()
    for o in outputs:
        stages, what = _NEEDS[o]
        need |= stages
        made |= what
    if mesh in ("lod", "source"):
        if "mesh" in need:
            need.add("select")
        if mesh == "lod" and have_patches:
            need.discard("select")
        if mesh == "lod" and "select" in need and not have_terrain:
            need.add("prepare")
    else:
        need.discard("select")
    if mesh == "source" and provides_normals:
        need.discard("normal_map")
    return Plan(tuple(s for s in STAGE_ORDER if s in need), "attributes" in made, "barycentrics" in made,
                "image" in outputs, "normals" in outputs, "depth" in outputs, "counters" in outputs)


@dataclass
class StageRecord:
    name: str
    time_ms: float
    counters: dict[str, Any] = field(default_factory=dict)


@dataclass
class Report:
    """What each stage cost: wall time (ms) and counters, in the order they ran; ``counters``, the frame's
    pipeline statistics (:data:`terrainwarp.kernels.counters.PIPELINE_COUNTERS`) when the scene asked for them
    (None otherwise): bit-identical across runs and thread counts."""

    stages: list[StageRecord] = field(default_factory=list)
    info: dict[str, Any] = field(default_factory=dict)
    counters: dict[str, int | float] | None = None
    render_ms: float = 0.0  # the whole render() call, wall time
    kernel_ms: float = 0.0  # the part of it spent inside kernel launches (kernels.parallel.kernel_clock)

    @property
    def total_ms(self) -> float:
        return float(sum(s.time_ms for s in self.stages))

    @property
    def host_ms(self) -> float:
        """The render() call's wall time outside kernel launches: validation, allocation, copies, numpy and
        Python between the launches (what a frame of this simulator pays beside its kernels)."""
        return max(self.render_ms - self.kernel_ms, 0.0)

    def stage(self, name: str) -> StageRecord | None:
        return next((s for s in self.stages if s.name == name), None)

    def stage_ms(self, name: str) -> float:
        """The stage's wall time in ms, 0.0 when it did not run."""
        rec = self.stage(name)
        return 0.0 if rec is None else rec.time_ms

    @property
    def frame_ms(self) -> float:
        """The frame's cost, as every table in the project counts it: select + mesh + raster (ms).

        Preparation (pyramids, peer meshes built once), shading and measuring are left out: they are not
        what an engine pays per frame for its LOD scheme."""
        return self.stage_ms("select") + self.stage_ms("mesh") + self.stage_ms("raster")

    def to_dict(self) -> dict:
        out = {"info": self.info, "total_ms": self.total_ms, "render_ms": self.render_ms, "kernel_ms": self.kernel_ms,
               "host_ms": self.host_ms,
               "stages": [{"name": s.name, "time_ms": s.time_ms, **s.counters} for s in self.stages]}
        if self.counters is not None:
            out["counters"] = dict(self.counters)
        return out

    def table(self) -> str:
        rows = [("stage", "time_ms", "counters")]
        for s in self.stages:
            rows.append((s.name, f"{s.time_ms:.1f}", ", ".join(f"{k}={v}" for k, v in s.counters.items())))
        rows.append(("total", f"{self.total_ms:.1f}", ""))
        rows.append(("host", f"{self.host_ms:.1f}", self._host_line()))
        if self.counters is not None:
            rows.append(("counters", "", ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                                                   for k, v in self.counters.items())))
        w0 = max(len(r[0]) for r in rows)
        w1 = max(len(r[1]) for r in rows)
        return "\n".join(f"{a:<{w0}}  {b:>{w1}}  {c}" for a, b, c in rows)

    def _host_line(self) -> str:
        share = 100.0 * self.host_ms / self.render_ms if self.render_ms > 0 else 0.0
        return (f"render() {self.render_ms:.1f} ms: kernels {self.kernel_ms:.1f} ms, outside kernels "
                f"{self.host_ms:.1f} ms ({share:.0f}%)")

    def _repr_html_(self) -> str:
        """The :meth:`table` as HTML (Jupyter), the frame cost under it; then the pipeline statistics, one row per
        counter, when the scene asked for them."""
        rows = [(s.name, s.time_ms, s.counters) for s in self.stages] + [("total", self.total_ms, {}),
                                                                        ("host", self.host_ms, self._host_line())]
        out = html_table(("stage", "time_ms", "counters"), rows,
                         caption=f"frame cost (select + mesh + raster): {self.frame_ms:.3g} ms")
        if self.counters is None:
            return out
        return out + html_table(("pipeline statistic", "value"), list(self.counters.items()),
                                caption="what a GPU would pay (terrainwarp.kernels.counters.PIPELINE_COUNTERS)")


@dataclass
class Frame:
    """A rendered frame. Fields not asked for by the scene are None.

    Attributes:
        image: (H, W, 3) uint8 sRGB hillshaded colour, row 0 at the top.
        depth: (H, W) float32 window depth in [0, 1], 1.0 on background.
        normals: (H, W, 3) float32 per-pixel unit normals (0 on background).
        triangle_id: (H, W) int32 visible triangle per pixel (-1 background), when raster ran.
        barycentrics: (H, W, 2) float32 perspective-correct barycentrics, when shading or the error ran.
        mesh: the :class:`Mesh` drawn.
        curvature: (H, W, 4) float32 curvature of the heightmap (not the image) in the directions x, z,
            diagonal (+x,+z), diagonal (+x,-z) (:func:`terrainwarp.compute_curvature`, three-normal), 1/m;
            only when the scene asks for ``"curvature"``.
        patches: the :class:`terrainwarp.lod.PatchList` of a LOD frame (the held one when given).
        error: :class:`terrainwarp.measure.error.FrameError`, when asked: ``p99_px``, ``max_px``, ``mean_px``
            the primary error at the heightmap's samples (0 for every family's full-detail mesh);
            ``image_err_*`` the per-pixel error against the fixed-diagonal grid (secondary: it carries a
            triangulation floor); see-through pixels, coverage, PSNR/SSIM.
        report: the :class:`Report`.
    """

    scene: Scene
    report: Report
    image: np.ndarray | None = None
    depth: np.ndarray | None = None
    normals: np.ndarray | None = None
    triangle_id: np.ndarray | None = None
    barycentrics: np.ndarray | None = None
    mesh: Mesh | None = None
    patches: PatchList | None = None
    error: FrameError | None = None
    curvature: np.ndarray | None = None

    def __repr__(self) -> str:
        """One line: the scene, the viewport, the outputs the frame holds, the mesh and the error."""
        cam, held = self.scene.camera, [n for n in ("image", "depth", "normals", "curvature", "patches")
                                        if getattr(self, n) is not None]
        mesh = "" if self.mesh is None else f", {self.mesh.n_triangles} triangles"
        err = "" if self.error is None else f", error p99 {self.error.p99_px:.3g} px"
        return (f"Frame({self.scene.name!r}, {cam.width}x{cam.height}, {'+'.join(held) or 'no images'}{mesh}{err}, "
                f"{self.report.frame_ms:.3g} ms)")

    def _repr_png_(self) -> bytes | None:
        """What Jupyter shows of a frame: its image, else a picture of its depth (near bright), else of its
        triangle ids (one colour each); None (the repr) for a frame without any of them."""
        if self.image is not None:
            return png_bytes(self.image)
        if self.depth is not None:
            return png_bytes(depth_picture(self.depth))
        return None if self.triangle_id is None else png_bytes(id_picture(self.triangle_id))

    def save(self, out_dir: str | Path) -> list[Path]:
        """Write what the frame has: ``frame.png``, ``depth.exr``, ``normals.exr``, ``curvature.exr``,
        ``mesh.vtp``, ``patches.csv``, with the error ``error_px.exr`` (the primary error per heightmap
        sample, rows x cols, NaN where not measured) and ``image_error_px.exr`` (the per-pixel grid-image
        error, H x W, NaN on background), and ``report.json`` (each written to a temporary name and
        renamed, and all renamed into place only once every one is written: a failure leaves the folder's
        previous set whole)."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        with output_set(out):
            return self._save(out)

    def _save(self, out: Path) -> list[Path]:
        written = []
        if self.image is not None:
            written.append(write_image(out / "frame.png", self.image))
        if self.depth is not None:
            written.append(write_image(out / "depth.exr", self.depth))
        if self.normals is not None:
            written.append(write_image(out / "normals.exr", self.normals.astype(np.float32)))
        if self.curvature is not None:
            written.append(write_image(out / "curvature.exr", self.curvature.astype(np.float32)))
        if self.mesh is not None and "mesh" in self.scene.outputs:
            with atomic_path(out / "mesh.vtp") as tmp:
                self.mesh.to_pyvista().save(str(tmp))
            written.append(out / "mesh.vtp")
        if self.patches is not None and "patches" in self.scene.outputs:
            self.patches.to_csv(out / "patches.csv")
            written.append(out / "patches.csv")
        if self.error is not None:
            if self.error.error_map is not None:
                written.append(write_image(out / "error_px.exr", self.error.error_map))
            if self.error.image_error_map is not None:
                written.append(write_image(out / "image_error_px.exr", self.error.image_error_map))
            self.report.info["error"] = self.error.row()
        written.append(write_json(out / "report.json", self.report.to_dict()))
        return written


# ------------------------------------------------------------------------------------------------
# the frame in progress
# ------------------------------------------------------------------------------------------------
@dataclass(eq=False)
class _Run:
    """What the stages of one ``render`` call share: its inputs, the frame they fill in, and the
    intermediate arrays that are not part of the frame."""

    scene: Scene
    frame: Frame
    plan: Plan
    device: str
    terrain: Terrain | None = None
    state: LodState | None = None
    reference: Frame | None = None
    source: MeshSource | None = None
    nmap: np.ndarray | None = None  # (H, W, 3) float32 heightmap normal map
    source_mesh_ms: float = 0.0  # the part of the source's call not spent selecting
    ref_tri: np.ndarray | None = None
    ref_depth: np.ndarray | None = None
    draw_counters: dict[str, int] | None = None  # the mesh's draws' pipeline statistics (when asked)
    raster_counters: dict[str, int] | None = None  # the rasterizer's (when asked)

    @property
    def counting(self) -> bool:
        return self.plan.counters

    @property
    def kind(self) -> str:
        """``"source"``, ``"lod"`` or ``"grid"``: where the mesh comes from."""
        return "source" if self.source is not None else self.scene.mesh

    @property
    def hm(self) -> Heightmap:
        """The heightmap as a grid in memory: the scene's, or a streamed one's :meth:`load` (kept with it), for
        the stages that read every sample (curvature, the reference and the error)."""
        hm = self.scene.heightmap
        if isinstance(hm, StreamedHeightmap):
            if hm.held.loaded is None:
                hm.held.loaded = hm.load()
            return hm.held.loaded
        return hm

    @property
    def cam(self) -> Camera:
        return self.scene.camera


def _start(scene: Scene, terrain: Terrain | None, state: LodState | None, reference: Frame | None,
           source: MeshSource | None, patches: PatchList | None, device: str) -> _Run:
    """Validate the arguments and open the frame's report."""
    if not isinstance(scene, Scene):
        raise TypeError(f"scene: expected a Scene, got {type(scene).__name__}")
    hm, cam = scene.heightmap, scene.camera
    _check_near(scene)
    if terrain is not None:
        if not isinstance(terrain, Terrain):
            raise TypeError(f"terrain: expected a Terrain, got {type(terrain).__name__}")
        if terrain.heightmap is not hm:
            raise ValueError("terrain: prepared for another heightmap than the scene's")
    if source is not None and missing_members(source):
        raise TypeError(f"source: expected a MeshSource (terrainwarp.rendering.SourceBase has the defaults), got "
                        f"{type(source).__name__} without {', '.join(missing_members(source))}")
    if source is None and scene.mesh == "lod" and scene.lod.is_scheme:  # a scheme drawn by name
        if patches is not None:
            raise ValueError(f"patches: a held PatchList is drawn by a quadtree policy, got the scheme "
                             f"{scene.lod.policy!r}")
        source = scene_source(scene, device)
    if isinstance(hm, StreamedHeightmap):
        held = source is None  # the source the heightmap holds for this configuration, made by render
        source = _streamed_source(scene, terrain, source, patches, device)
        if isinstance(source, StreamedSource) and (held or state is not None):
            # hysteresis across frames, as for an in-memory LOD scene; the held source keeps no earlier call's state
            source.state = state
        if isinstance(source, StreamedSource) and held:  # level and patch id only for what reads them
            source.attributes = bool({"mesh", "patches"} & set(scene.outputs)) or scene.shading in ("level", "patch")
    kind = "source" if source is not None else scene.mesh
    if terrain is None and kind == "lod":
        terrain = _held_terrain(hm, scene.lod, device)
    if patches is not None:
        if not isinstance(patches, PatchList):
            raise TypeError(f"patches: expected a PatchList, got {type(patches).__name__}")
        if kind != "lod":
            raise ValueError(f"patches: a held PatchList is drawn by a LOD scene (mesh='lod'), got {kind!r}")
    plan = plan_for(tuple(scene.outputs), kind, terrain is not None, patches is not None,
                    bool(source is not None and source.provides_normals))
    stages = list(plan.stages)
    report = Report(info={"scene": scene.name, "heightmap": hm.name, "shape": list(hm.shape),
                          "dx": hm.dx, "dz": hm.dz, "width": cam.width, "height": cam.height,
                          "mesh_policy": kind, "outputs": list(scene.outputs), "stages_run": stages,
                          "device": device})
    if kind == "lod" or (scene.mesh == "lod" and scene.lod.is_scheme):
        report.info["lod"] = dict(scene.lod.__dict__)
    if kind == "source":
        report.info["source"] = type(source).__name__
    if patches is not None:
        report.info["held_patches"] = len(patches)
    return _Run(scene, Frame(scene=scene, report=report, patches=patches), plan, device, terrain, state,
                reference, source)


def _check_near(scene: Scene) -> None:
    """Refuse a camera whose ``near`` blanks the terrain it looks at in float32 depth, warn
    (:class:`terrainwarp.camera.DepthPrecisionWarning`) when it loses the far terrain
    (:func:`terrainwarp.camera.check_depth_range`)."""
    hm, cam = scene.heightmap, scene.camera
    (x0, z0), (x1, z1) = hm.bounds_xz
    known = hm.known_height_range() if isinstance(hm, StreamedHeightmap) else hm.height_range
    lo, hi = known if known is not None else (cam.position[1], cam.position[1])  # a file's: its build's, later
    text = _depth_range_text(cam.position, cam.target, cam.up, cam.near, cam.far, (x0, lo, z0), (x1, hi, z1))
    if text is not None:
        warnings.warn(text, DepthPrecisionWarning, stacklevel=3)


@functools.lru_cache(maxsize=1024)
def _depth_range_text(position: tuple, target: tuple, up: tuple, near: float, far: float, box_min: tuple,
                      box_max: tuple) -> str | None:
    """:func:`terrainwarp.camera.check_depth_range`, once per camera and terrain box (a path renders many frames
    per camera)."""
    return check_depth_range(Camera(position=position, target=target, up=up, near=near, far=far), box_min, box_max)


def _streamed_source(scene: Scene, terrain: Terrain | None, source: MeshSource | None, patches: PatchList | None,
                     device: str) -> MeshSource:
    """The source that draws a streamed heightmap's frames: the caller's, else the one the heightmap holds
    for this LOD configuration and device (its pyramids and tile cache persist from frame to frame)."""
    if source is not None:
        return source
    hm = scene.heightmap
    if scene.mesh != "lod":
        raise ValueError(f"mesh: a streamed heightmap is drawn with mesh='lod' (its LOD reads only the tiles "
                         f"a frame needs), got {scene.mesh!r}; StreamedHeightmap.load() gives the whole grid")
    if scene.shading == "splat":
        raise ValueError("shading: 'splat' reads the whole heightmap's splat map; a streamed heightmap is "
                         "shaded 'hillshade', 'level' or 'wireframe'")
    if patches is not None:
        raise ValueError("patches: a streamed heightmap selects its own patches (hold its StreamedSource)")
    key = (tuple(sorted(scene.lod.__dict__.items())), device)
    held = hm.held.streamed_sources
    if key not in held:
        held[key] = StreamedSource(hm, scene.lod, device=device, terrain=terrain)
    return held[key]


# ------------------------------------------------------------------------------------------------
# stages: each fills in its part of the run and its record's counters; a stage that measured its own
# time (a source's selection and meshing share one call) returns it in ms, the others return None
# ------------------------------------------------------------------------------------------------
def _held_terrain(hm: Heightmap, lod: Any, device: str, prepared: Terrain | None = None) -> Terrain | None:
    """The Terrain the heightmap holds for the layout (roots, tess) of ``lod`` on ``device`` (None: none yet); with
    ``prepared``, held from now on (the least recently drawn of more than TERRAINS_HELD layouts let go)."""
    held = hm.held.terrains.setdefault(device, OrderedDict())
    key = (lod.roots, lod.tess)
    if prepared is not None:
        held[key] = prepared
        while len(held) > TERRAINS_HELD:
            held.popitem(last=False)
    t = held.get(key)
    if t is not None:
        held.move_to_end(key)
    return t


def _stage_prepare(run: _Run, rec: StageRecord) -> None:
    lod = run.scene.lod
    run.terrain = t = Terrain.prepare(run.hm, roots=lod.roots, tess=lod.tess, device=run.device)
    _held_terrain(run.hm, lod, run.device, t)
    rec.counters.update(roots=t.roots[0] * t.roots[1], depth=t.depth, tess=t.tess)


def _stage_normal_map(run: _Run, rec: StageRecord) -> None:
    hm, device = run.hm, run.device
    key = ("normal_map", device)
    holder = run.terrain if run.terrain is not None else run.source
    if holder is not None and holder.is_cached(key):
        rec.counters["cached"] = True
    else:
        rec.counters["samples"] = int(hm.heights.size)
    make = lambda: sobel_normals(hm.heights, hm.dx, hm.dz, border="clamp", device=device)  # noqa: E731
    run.nmap = make() if holder is None else holder.cached(key, make)


def _stage_curvature(run: _Run, rec: StageRecord) -> None:
    run.frame.curvature = compute_curvature(run.hm, "three_normal", device=run.device)
    rec.counters.update(samples=int(run.hm.heights.size), method="three_normal")


def _stage_select(run: _Run, rec: StageRecord) -> float | None:
    if run.source is not None:
        t0 = time.perf_counter()
        run.frame.mesh, select_ms = run.source.mesh_for(run.cam)
        run.source_mesh_ms = max((time.perf_counter() - t0) * 1e3 - select_ms, 0.0)
        if run.source.patches is not None:  # a source of quadtree patches (a streamed terrain's)
            run.frame.patches = run.source.patches
        rec.counters.update(run.source.last)  # e.g. what a streamed frame read: tiles, bytes, cache hits
        run.frame.report.info.update(run.source.report_info())
        return select_ms
    patches = select(run.terrain, run.cam, make_policy(run.scene.lod), run.state, device=run.device)
    run.frame.patches = patches
    rec.counters.update({k: v for k, v in patches.stats.items() if k in
                         ("nodes_visited", "patches", "culled", "forced_splits", "max_level")})
    return None


def _stage_mesh(run: _Run, rec: StageRecord) -> float | None:
    kind, frame = run.kind, run.frame
    if kind == "source":  # made by the source's call in the select stage (a streamed one selects patches)
        mesh, ms = frame.mesh, run.source_mesh_ms
        n_patches = len(frame.patches) if frame.patches is not None else 0
    elif kind == "lod":
        mesh, n_patches, ms = _lod_mesh(run.scene, frame.patches, run.nmap, run.plan.attributes, run.device,
                                        checked="select" in run.plan.stages, terrain=run.terrain), \
            len(frame.patches), None
    else:
        mesh, n_patches, ms = _grid_mesh(run.hm, run.cam, run.nmap, run.device), 1, None
    frame.mesh = mesh
    rec.counters.update(patches=n_patches, vertices=mesh.n_vertices, triangles=mesh.n_triangles)
    shape = run.scene.heightmap.shape  # (run.hm would load a streamed heightmap whole)
    if min(shape) < 2:  # said, not left to a puzzled look at an empty frame
        why = (f"heightmap: {shape[0]}x{shape[1]} samples make no triangle (a cell needs 2x2 "
               "samples); the frame is empty")
        frame.report.info["empty"] = why
        warnings.warn(why, EmptyFrameWarning, stacklevel=3)
    if run.counting:  # the draws' statistics, counted as part of the stage
        t0 = time.perf_counter()
        run.draw_counters = _draw_counters(mesh, run.device)
        if ms is not None:
            ms += (time.perf_counter() - t0) * 1e3
    return ms


def _draw_counters(mesh: Mesh, device: str) -> dict[str, int]:
    """The pipeline statistics of a mesh's draws: the tessellator's (``mesh.counters``) or its indexed draws'."""
    if mesh.counters is not None:
        return mesh.counters
    d = mesh.draws if mesh.draws is not None else Draws()
    tri = mesh.triangles if d.order is None else mesh.triangles[d.order]  # in the order the draws take them
    return indexed_draw_counters(tri, mesh.n_vertices, d.ranges, groups=d.groups,
                                 vertex_invocations=d.vertex_invocations, vertex_bytes=d.vertex_bytes,
                                 texels_per_vertex=d.texels_per_vertex, device=device)


def _stage_raster(run: _Run, rec: StageRecord) -> None:
    frame, cam, mesh = run.frame, run.cam, run.frame.mesh
    frags = rasterize(mesh.positions, mesh.triangles, cam.view_matrix(relative=True), cam.proj_matrix(),
                      cam.width, cam.height, cull_back=run.scene.cull_back, counters=run.counting,
                      checked=run.kind in ("lod", "grid"), device=run.device)  # meshes made here are valid
    rec.counters.update(frags.stats)
    run.raster_counters = frags.counters
    # the perspective-correct barycentric image (computed on first access) is part of the visibility pass
    # only when a later stage interpolates with it (the plan): depth alone leaves it out
    if run.plan.barycentrics:
        frame.barycentrics = frags.barycentrics
    frame.triangle_id = frags.triangle_id
    frame.depth = frags.depth


def _stage_shade(run: _Run, rec: StageRecord) -> None:
    scene, frame, mesh = run.scene, run.frame, run.frame.mesh
    normals = mesh.normals if mesh.normals is not None else _source_normals(run.hm, mesh, run.nmap, run.device)
    world_y = (mesh.positions[:, 1] + mesh.eye[1]).astype(np.float32, copy=False)
    rgb, pix_n, counters = shade(frame.triangle_id, frame.barycentrics, mesh.triangles, normals, world_y,
                                 mode=scene.shading, level=mesh.level, patch_id=mesh.patch_id, uv=mesh.uv,
                                 azimuth_deg=scene.light_azimuth_deg, elevation_deg=scene.light_elevation_deg,
                                 height_range=run.scene.heightmap.height_range,  # one tint for every mesh
                                 encode=run.plan.image, want_normals=run.plan.normals,  # only what is asked
                                 device=run.device, **_shade_inputs(run))
    if scene.shading != "hillshade":
        rec.counters.update(counters)
    rec.counters["pixels"] = int(frame.triangle_id.size)
    if run.plan.image:
        frame.image = rgb  # 8-bit sRGB, encoded by the shading kernel
    if run.plan.normals:
        frame.normals = pix_n


def _stage_reference(run: _Run, rec: StageRecord) -> None:
    ref, frame, cam = run.reference, run.frame, run.cam
    if ref is not None:
        if ref.scene.camera != cam or ref.triangle_id is None or ref.depth is None:
            raise ValueError("reference: expected a frame of the same camera with triangle ids and depth")
        run.ref_tri, run.ref_depth = ref.triangle_id, ref.depth
        rec.counters["given"] = True
    elif run.kind == "grid":  # the grid frame is its own reference
        run.ref_tri, run.ref_depth = frame.triangle_id, frame.depth
        rec.counters["reused"] = True
    else:
        ref_mesh = _grid_mesh(run.hm, cam, None, run.device)
        frags = rasterize(ref_mesh.positions, ref_mesh.triangles, cam.view_matrix(relative=True),
                          cam.proj_matrix(), cam.width, cam.height, cull_back=run.scene.cull_back,
                          device=run.device)
        run.ref_tri, run.ref_depth = frags.triangle_id, frags.depth
        rec.counters.update(triangles=ref_mesh.n_triangles, pixels_covered=frags.stats["pixels_covered"])


def _stage_error(run: _Run, rec: StageRecord) -> None:
    frame, mesh = run.frame, run.frame.mesh
    if run.reference is not None:
        ref_img = run.reference.image
    else:
        ref_img = frame.image if run.kind == "grid" else None
    primary = sample_error(run.hm, run.cam, mesh, run.ref_depth, keep_map=True, device=run.device)
    image = frame_error(run.hm, run.cam, mesh.positions, mesh.eye, mesh.triangles, frame.triangle_id,
                        frame.barycentrics, frame.depth, run.ref_tri, run.ref_depth,
                        image=frame.image if ref_img is not None else None, ref_image=ref_img, keep_maps=True,
                        device=run.device)
    frame.error = e = FrameError.combine(primary, image)
    rec.counters.update(max_px=round(e.max_px, 4), p99_px=round(e.p99_px, 4),
                        image_err_p99_px=round(e.image_err_p99_px, 4), see_through_px=e.see_through_px)


_STAGES: dict[str, Callable[[_Run, StageRecord], float | None]] = {
    "prepare": _stage_prepare, "normal_map": _stage_normal_map, "curvature": _stage_curvature,
    "select": _stage_select, "mesh": _stage_mesh, "raster": _stage_raster, "shade": _stage_shade,
    "reference": _stage_reference, "error": _stage_error}


# ------------------------------------------------------------------------------------------------
# render
# ------------------------------------------------------------------------------------------------
class EmptyFrameWarning(UserWarning):
    """A frame that can hold nothing whatever the camera (a heightmap with a side of one sample)."""


def _check_render_args(scene: object, terrain: object, state: object, reference: object, device: object) -> None:
    for name, v, cls in (("scene", scene, Scene), ("terrain", terrain, Terrain), ("state", state, LodState),
                         ("reference", reference, Frame)):
        if not isinstance(v, cls) and not (v is None and name != "scene"):
            what = f"a terrainwarp {cls.__name__}" + ("" if name == "scene" else " or None")
            raise TypeError(f"{name}: expected {what}, got {type(v).__name__} {v!r:.60}")
    check_device("device", device)


def render(scene: Scene, terrain: Terrain | None = None, state: LodState | None = None,
           reference: Frame | None = None, device: str = "cpu", *, source: MeshSource | None = None,
           patches: PatchList | None = None) -> Frame:
    """Render a scene, running only the stages its outputs need (see the module docstring).

    Args:
        scene: what to draw and which outputs to compute.
        terrain: a :class:`terrainwarp.lod.Terrain` prepared for this heightmap (pyramids, normal map);
            None: the one the heightmap holds for the scene's layout, prepared here on the first frame that
            needs it (timed as ``prepare``) and held by the heightmap after (see the module docstring).
        state: a :class:`terrainwarp.lod.LodState` for hysteresis across frames, or None.
        reference: a full-resolution frame of the same heightmap and camera (with ``depth``) to measure
            the error against, so a sweep renders each camera's reference once; None renders it here.
        source: a prebuilt :class:`MeshSource` to draw instead of the scene's ``mesh`` policy (the peers,
            polytree and bintree of :mod:`terrainwarp.rendering.sources`).
        patches: a held :class:`terrainwarp.lod.PatchList` (e.g. ``frame_t.patches``) to tessellate for
            ``scene.camera`` as it is, instead of selecting (LOD scenes only; ``select`` does not run).

    Returns:
        A :class:`Frame`; deterministic (bit-identical across runs for the same scene).

    Raises:
        TypeError: an argument of the wrong type (named). ValueError: a device Warp does not see (a CUDA device
            on a machine without a GPU says so).
    """
    _check_render_args(scene, terrain, state, reference, device)
    start = time.perf_counter()
    with kernel_clock() as in_kernels:
        run = _start(scene, terrain, state, reference, source, patches, device)
        for name in run.plan.stages:
            rec = StageRecord(name, 0.0)
            t0 = time.perf_counter()
            ms = _STAGES[name](run, rec)
            rec.time_ms = (time.perf_counter() - t0) * 1e3 if ms is None else ms
            run.frame.report.stages.append(rec)
        if run.counting:
            run.frame.report.counters = frame_counters(run.draw_counters or {}, run.raster_counters or {})
    if not run.plan.depth:
        run.frame.depth = None
    report = run.frame.report
    report.render_ms, report.kernel_ms = (time.perf_counter() - start) * 1e3, in_kernels[0] * 1e3
    return run.frame


def pop_stats(scene: Scene, previous: Camera, current: Frame, reference: Frame, *, terrain: Terrain | None = None,
              source: MeshSource | None = None, held: PatchList | None = None, threshold_px: float = 0.5,
              device: str = "cpu") -> PopStats:
    """The pop from camera ``previous`` to ``scene.camera``: the LOD selected at ``previous`` (held) and the
    LOD of ``current``, both drawn for ``scene.camera`` (:func:`terrainwarp.measure.sample_error.popping`).

    Args:
        scene: the scene of the current frame (its camera is camera t+1).
        previous: camera t.
        current: the frame of ``scene`` (its ``mesh``), from :func:`render`.
        reference: the full-resolution grid frame of ``scene.camera`` with ``depth`` (visibility).
        terrain: the caller's Terrain (LOD scenes).
        source: the :class:`MeshSource` ``current`` was drawn from; its held mesh is
            ``source.held_mesh_for(previous, scene.camera)`` (the selection of ``previous`` drawn by the
            vertex stage of ``scene.camera``: a scheme's per-frame morph or snapping is not a pop, as a held
            PatchList is tessellated for ``scene.camera``; :class:`SourceBase`'s default is
            ``mesh_for(previous)``, and a static mesh does not pop).
        held: the PatchList selected at ``previous`` (e.g. with hysteresis state); None re-selects it
            here, statelessly.

    Returns:
        :class:`terrainwarp.measure.sample_error.PopStats`; exactly 0 when the selection did not change.
        A grid scene does not pop (its pop is measured against its own mesh: 0).
    """
    if current.mesh is None or reference.depth is None:
        raise ValueError("current, reference: expected a frame with a mesh and a reference frame with depth")
    if source is None and scene.mesh == "lod" and scene.lod.is_scheme:
        source = scene_source(scene, device)
    if source is not None:
        held_mesh = source.held_mesh_for(previous, scene.camera)
    elif scene.mesh == "lod":
        if held is None:
            held = render(scene.with_(camera=previous, outputs=("patches",)), terrain, device=device).patches
        held_mesh = render(scene.with_(outputs=("mesh",)), terrain, device=device, patches=held).mesh
    else:
        held_mesh = current.mesh
    return popping(scene.heightmap, scene.camera, held_mesh, current.mesh, reference.depth,
                   threshold_px=threshold_px, device=device)


# ------------------------------------------------------------------------------------------------
# meshes and shading inputs
# ------------------------------------------------------------------------------------------------
def _shade_inputs(run: _Run) -> dict[str, Any]:
    """The extra per-vertex inputs of the wireframe and splat shading modes (``Scene.shading``)."""
    scene, mesh, cam = run.scene, run.frame.mesh, run.cam
    if scene.shading == "wireframe":
        return {"clip": clip_coordinates(mesh.positions, cam.view_matrix(relative=True), cam.proj_matrix(),
                                         device=run.device)}
    if scene.shading == "splat":
        xz = np.stack([mesh.positions[:, 0] + mesh.eye[0], mesh.positions[:, 2] + mesh.eye[2]], 1)
        return {"splat": splat_map(run.hm.heights, run.nmap, device=run.device),
                "world_xz": xz.astype(np.float32)}
    return {}


def _source_normals(hm: Heightmap, mesh: Mesh, nmap: np.ndarray, device: str) -> np.ndarray:
    """Vertex normals of a source's mesh: the normal map fetched where each vertex lies over the heightmap
    (its x, z in float64, as uv in [0, 1]; a source's own uv may not be heightmap coordinates)."""
    world = mesh.world_positions()
    uv = np.stack([(world[:, 0] - hm.origin[0]) / hm.dx / max(hm.shape[1] - 1, 1),
                   (world[:, 2] - hm.origin[1]) / hm.dz / max(hm.shape[0] - 1, 1)], 1)
    return sample_normal_map(nmap, np.clip(uv, 0, 1).astype(np.float32), device=device)


def _grid_mesh(hm: Heightmap, cam: Camera, nmap: np.ndarray | None, device: str) -> Mesh:
    eye = cam.position
    rel = relative_origin(hm.origin, eye)
    pos, uv, tri = grid_mesh(hm.heights, hm.dx, hm.dz, rel, device=device)
    n = len(pos)
    return Mesh(positions=pos, eye=eye, triangles=tri, uv=uv, level=np.zeros(n, np.int32),
                patch_id=np.zeros(n, np.int32), normals=None if nmap is None else nmap.reshape(-1, 3))


def _lod_mesh(scene: Scene, patches: PatchList, nmap: np.ndarray | None, attributes: bool, device: str,
              checked: bool = False, terrain: Terrain | None = None) -> Mesh:
    """Tessellate and displace the selected patches in one launch (the GPU's single draw call); uv, level and
    patch id only with ``attributes`` (the plan's); ``checked``: the patches are this frame's selection's (valid);
    ``terrain``: the heightmap's Terrain, which keeps the heights' device array from frame to frame."""
    hm = scene.heightmap
    cam = scene.camera
    heights = hm.heights if terrain is None else terrain.cached(("heights", device),
                                                                lambda: view(hm.heights, wp.float32, device))
    t = tessellate_patches({"origin_xz": patches.origin, "size": patches.size, "outer": patches.outer,
                            "inner": patches.inner, "level": patches.level}, heights, hm.dx, hm.dz,
                           cam.position, spacing=scene.lod.spacing, filter=scene.lod.filter, origin=hm.origin,
                           device=device, need=("uv", "level", "patch_id") if attributes else (), checked=checked)
    normals = None if nmap is None else sample_normal_map(nmap, t.uv, device=device)
    positions, triangles = t.positions, t.triangles
    if hm.has_nodata:  # no-data holes: no triangle may touch a vertex that sampled NaN
        positions, triangles = drop_nonfinite_triangles(positions, triangles, device=device)
    return Mesh(positions=positions, eye=cam.position, triangles=triangles, uv=t.uv, level=t.level,
                patch_id=t.patch_id, normals=normals, counters=t.counters)

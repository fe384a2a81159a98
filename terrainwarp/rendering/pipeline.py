"""``render(scene) -> Frame``: the pipeline, run backwards from the outputs the scene asks for.

Stages (each a pure function of arrays):

=============  =============================================================================
stage          what
=============  =============================================================================
prepare        LOD scenes without a caller-held Terrain: quadtree pyramids (min/max/error)
normal_map     the heightmap's Sobel normal map (cached in the Terrain when one is held)
curvature      heightmap curvature (three-normal, four directions)
select         LOD scenes: the visible patches (policy, balance, edge factors, culling)
mesh           the full-resolution grid, or the patches tessellated and displaced in one launch
raster         the visibility pass (triangle id, depth, barycentrics per pixel)
shade          resolve + hillshade (image, per-pixel normals)
reference      the full-resolution grid rasterized from the same camera (only for ``error``)
error          per-pixel screen-space error against the reference (terrainwarp.measure.error)
=============  =============================================================================

Which run, by output (LOD scenes add ``prepare`` and ``select`` wherever ``mesh`` runs):

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
report     (none: the report of whatever ran)
=========  ==================================================
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..camera import relative_origin
from ..io.files import write_image, write_json
from ..mesh import Mesh
from ..scene import Scene

__all__ = ["render", "Frame", "Report", "StageRecord", "stages_for"]

STAGE_ORDER = ("prepare", "normal_map", "curvature", "select", "mesh", "raster", "shade", "reference", "error")
_NEEDS = {
    "image": {"normal_map", "mesh", "raster", "shade"},
    "normals": {"normal_map", "mesh", "raster", "shade"},
    "depth": {"mesh", "raster"},
    "mesh": {"mesh"},
    "patches": {"select"},
    "error": {"mesh", "raster", "reference", "error"},
    "curvature": {"curvature"},
    "report": set(),
}


def stages_for(outputs: tuple[str, ...], mesh: str = "grid", have_terrain: bool = False) -> list[str]:
    """The stages that the given outputs need, in pipeline order."""
    need: set[str] = set()
    for o in outputs:
        need |= _NEEDS[o]
    if mesh == "lod":
        if "mesh" in need:
            need.add("select")
        if "select" in need and not have_terrain:
            need.add("prepare")
    else:
        need.discard("select")
    return [s for s in STAGE_ORDER if s in need]


@dataclass
class StageRecord:
    name: str
    time_ms: float
    counters: dict[str, Any] = field(default_factory=dict)


@dataclass
class Report:
    """What each stage cost: wall time (ms) and counters, in the order they ran."""

    stages: list[StageRecord] = field(default_factory=list)
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def total_ms(self) -> float:
        return float(sum(s.time_ms for s in self.stages))

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
        return {"info": self.info, "total_ms": self.total_ms,
                "stages": [{"name": s.name, "time_ms": s.time_ms, **s.counters} for s in self.stages]}

    def table(self) -> str:
        rows = [("stage", "time_ms", "counters")]
        for s in self.stages:
            rows.append((s.name, f"{s.time_ms:.1f}", ", ".join(f"{k}={v}" for k, v in s.counters.items())))
        rows.append(("total", f"{self.total_ms:.1f}", ""))
        w0 = max(len(r[0]) for r in rows)
        w1 = max(len(r[1]) for r in rows)
        return "\n".join(f"{a:<{w0}}  {b:>{w1}}  {c}" for a, b, c in rows)


@dataclass
class Frame:
    """A rendered frame. Fields not asked for by the scene are None.

    Attributes:
        image: (H, W, 3) uint8 sRGB hillshaded colour, row 0 at the top.
        depth: (H, W) float32 window depth in [0, 1], 1.0 on background.
        normals: (H, W, 3) float32 per-pixel unit normals (0 on background).
        triangle_id: (H, W) int32 visible triangle per pixel (-1 background), when raster ran.
        mesh: the :class:`Mesh` drawn.
        curvature: (H, W, 4) float32 curvature of the heightmap (not the image) in the directions x, z,
            diagonal (+x,+z), diagonal (+x,-z) (:func:`terrainwarp.compute_curvature`, three-normal), 1/m;
            only when the scene asks for ``"curvature"``.
        patches: the :class:`terrainwarp.lod.PatchList` of a LOD frame.
        error: :class:`terrainwarp.measure.error.ErrorStats` against the full-resolution reference, when asked.
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
    patches: Any = None
    error: Any = None
    curvature: np.ndarray | None = None

    def save(self, out_dir: str | Path) -> list[Path]:
        """Write what the frame has: ``frame.png``, ``depth.exr``, ``normals.exr``, ``mesh.vtp`` and
        ``report.json`` (each written to a temporary name and renamed)."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
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
            from ..io.files import atomic_path

            with atomic_path(out / "mesh.vtp") as tmp:
                self.mesh.to_pyvista().save(str(tmp))
            written.append(out / "mesh.vtp")
        if self.patches is not None and "patches" in self.scene.outputs:
            self.patches.to_csv(out / "patches.csv")
            written.append(out / "patches.csv")
        if self.error is not None:
            if self.error.error_map is not None:
                written.append(write_image(out / "error_px.exr", self.error.error_map))
            self.report.info["error"] = self.error.row()
        written.append(write_json(out / "report.json", self.report.to_dict()))
        return written


def _srgb8(rgb: np.ndarray) -> np.ndarray:
    c = np.clip(rgb, 0.0, 1.0)
    s = np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1.0 / 2.4) - 0.055)
    return np.round(s * 255.0).astype(np.uint8)


@contextmanager
def _timed(report: Report, name: str):
    rec = StageRecord(name, 0.0)
    t0 = time.perf_counter()
    yield rec
    rec.time_ms = (time.perf_counter() - t0) * 1e3
    report.stages.append(rec)


def render(scene: Scene, terrain=None, state=None, reference: Frame | None = None, device: str = "cpu") -> Frame:
    """Render a scene, running only the stages its outputs need.

    Args:
        scene: what to draw and which outputs to compute.
        terrain: a :class:`terrainwarp.lod.Terrain` prepared for this heightmap (pyramids, normal map),
            held by the caller across frames; prepared here (and timed as ``prepare``) when None and
            the scene needs it.
        state: a :class:`terrainwarp.lod.LodState` for hysteresis across frames, or None.
        reference: a full-resolution frame of the same heightmap and camera (with ``depth``) to measure
            the error against, so a sweep renders each camera's reference once; None renders it here.

    Returns:
        A :class:`Frame`; deterministic (bit-identical across runs for the same scene).
    """
    from ..kernels.normals import sobel_normals
    from ..kernels.raster import rasterize
    from ..kernels.shading import hillshade

    if not isinstance(scene, Scene):
        raise TypeError(f"scene: expected a Scene, got {type(scene).__name__}")
    cam = scene.camera
    hm = scene.heightmap
    lod = scene.mesh == "lod"
    if terrain is not None:
        from ..lod.quadtree import Terrain

        if not isinstance(terrain, Terrain):
            raise TypeError(f"terrain: expected a Terrain, got {type(terrain).__name__}")
        if terrain.heightmap is not hm:
            raise ValueError("terrain: prepared for another heightmap than the scene's")
    stages = stages_for(scene.outputs, scene.mesh, have_terrain=terrain is not None)
    report = Report(info={"scene": scene.name, "heightmap": hm.name, "shape": list(hm.shape),
                          "dx": hm.dx, "dz": hm.dz, "width": cam.width, "height": cam.height,
                          "mesh_policy": scene.mesh, "outputs": list(scene.outputs), "stages_run": stages,
                          "device": device})
    if lod:
        report.info["lod"] = dict(scene.lod.__dict__)
    frame = Frame(scene=scene, report=report)
    if "prepare" in stages:
        from ..lod.quadtree import Terrain

        with _timed(report, "prepare") as r:
            terrain = Terrain.prepare(hm, roots=scene.lod.roots, tess=scene.lod.tess, device=device)
            r.counters.update(roots=terrain.roots[0] * terrain.roots[1], depth=terrain.depth, tess=terrain.tess)
    nmap = None
    if "normal_map" in stages:
        with _timed(report, "normal_map") as r:
            key = ("normal_map", device)
            if terrain is not None and terrain.is_cached(key):
                r.counters["cached"] = True
            else:
                r.counters["samples"] = int(hm.heights.size)
            make = lambda: sobel_normals(hm.heights, hm.dx, hm.dz, border="clamp", device=device)  # noqa: E731
            nmap = make() if terrain is None else terrain.cached(key, make)
    if "curvature" in stages:
        from ..surface.differential import compute_curvature

        with _timed(report, "curvature") as r:
            frame.curvature = compute_curvature(hm, "three_normal", device=device)
            r.counters.update(samples=int(hm.heights.size), method="three_normal")
    if "select" in stages:
        from ..lod.quadtree import select

        with _timed(report, "select") as r:
            frame.patches = select(terrain, cam, scene.lod.make_policy(), state, device=device)
            r.counters.update({k: v for k, v in frame.patches.stats.items() if k in
                               ("nodes_visited", "patches", "culled", "forced_splits", "max_level")})
    mesh = None
    if "mesh" in stages:
        with _timed(report, "mesh") as r:
            mesh = _lod_mesh(scene, frame.patches, nmap, device) if lod else _grid_mesh(hm, cam, nmap, device)
            r.counters.update(patches=len(frame.patches) if lod else 1, vertices=mesh.n_vertices,
                              triangles=mesh.n_triangles)
        frame.mesh = mesh
    if "raster" in stages:
        with _timed(report, "raster") as r:
            frags = rasterize(mesh.positions, mesh.triangles, cam.view_matrix(relative=True), cam.proj_matrix(),
                              cam.width, cam.height, cull_back=scene.cull_back, device=device)
            r.counters.update(frags.stats)
            # the perspective-correct barycentric image (computed on first access) is part of the visibility
            # pass only when a later stage interpolates with it: depth alone leaves it out
            if "shade" in stages or "error" in stages:
                frame.barycentrics = frags.barycentrics
        frame.triangle_id = frags.triangle_id
        frame.depth = frags.depth
    rgb = None
    if "shade" in stages:
        with _timed(report, "shade") as r:
            world_y = (mesh.positions[:, 1] + mesh.eye[1]).astype(np.float32)
            if scene.shading == "hillshade":
                rgb, pix_n = hillshade(frame.triangle_id, frame.barycentrics, mesh.triangles, mesh.normals, world_y,
                                       azimuth_deg=scene.light_azimuth_deg,
                                       elevation_deg=scene.light_elevation_deg, device=device)
            else:
                rgb, pix_n, shade_counters = _shade_mode(scene, frame, mesh, world_y, nmap, device)
                r.counters.update(shade_counters)
            r.counters["pixels"] = int(frame.triangle_id.size)
        if "image" in scene.outputs:
            frame.image = _srgb8(rgb)
        if "normals" in scene.outputs:
            frame.normals = pix_n
    if "reference" in stages:
        with _timed(report, "reference") as r:
            if reference is not None:
                if reference.scene.camera != cam or reference.triangle_id is None or reference.depth is None:
                    raise ValueError("reference: expected a frame of the same camera with triangle ids and depth")
                ref_tri, ref_depth = reference.triangle_id, reference.depth
                r.counters["given"] = True
            elif lod:
                ref_mesh = _grid_mesh(hm, cam, None, device)
                ref = rasterize(ref_mesh.positions, ref_mesh.triangles, cam.view_matrix(relative=True),
                                cam.proj_matrix(), cam.width, cam.height, cull_back=scene.cull_back, device=device)
                ref_tri, ref_depth = ref.triangle_id, ref.depth
                r.counters.update(triangles=ref_mesh.n_triangles, pixels_covered=ref.stats["pixels_covered"])
            else:  # the grid frame is its own reference
                ref_tri, ref_depth = frame.triangle_id, frame.depth
                r.counters["reused"] = True
    if "error" in stages:
        from ..measure.error import frame_error

        with _timed(report, "error") as r:
            ref_img = reference.image if reference is not None else (frame.image if not lod else None)
            frame.error = frame_error(hm, cam, mesh.positions, mesh.eye, mesh.triangles, frame.triangle_id,
                                      frame.barycentrics, frame.depth, ref_tri, ref_depth,
                                      image=frame.image if ref_img is not None else None, ref_image=ref_img,
                                      keep_maps=True)
            r.counters.update(max_px=round(frame.error.max_px, 4), p99_px=round(frame.error.p99_px, 4),
                              cracks=frame.error.cracks)
    if "depth" not in scene.outputs:
        frame.depth = None
    return frame


def _shade_mode(scene: Scene, frame: Frame, mesh: Mesh, world_y: np.ndarray, nmap, device: str):
    """The non-default shading modes (``Scene.shading``), see ``kernels.shading.shade``."""
    from ..kernels.raster import clip_coordinates
    from ..kernels.shading import shade, splat_map

    cam = scene.camera
    kw = {}
    if scene.shading == "wireframe":
        kw["clip"] = clip_coordinates(mesh.positions, cam.view_matrix(relative=True), cam.proj_matrix(),
                                      device=device)
    if scene.shading == "splat":
        hm = scene.heightmap
        kw["splat"] = splat_map(hm.heights, nmap, device=device)
        kw["world_xz"] = np.stack([mesh.positions[:, 0] + mesh.eye[0], mesh.positions[:, 2] + mesh.eye[2]],
                                  1).astype(np.float32)
    return shade(frame.triangle_id, frame.barycentrics, mesh.triangles, mesh.normals, world_y, mode=scene.shading,
                 level=mesh.level, patch_id=mesh.patch_id, uv=mesh.uv, azimuth_deg=scene.light_azimuth_deg,
                 elevation_deg=scene.light_elevation_deg, device=device, **kw)


def _grid_mesh(hm, cam, nmap, device: str) -> Mesh:
    from ..kernels.displacement import grid_mesh

    eye = cam.position
    rel = relative_origin(hm.origin, eye)
    pos, uv, tri = grid_mesh(hm.heights, hm.dx, hm.dz, rel, device=device)
    n = len(pos)
    return Mesh(positions=pos, eye=eye, triangles=tri, uv=uv, level=np.zeros(n, np.int32),
                patch_id=np.zeros(n, np.int32), normals=None if nmap is None else nmap.reshape(-1, 3))


def _lod_mesh(scene: Scene, patches, nmap, device: str) -> Mesh:
    """Tessellate and displace the selected patches in one launch (the GPU's single draw call)."""
    from ..kernels.displacement import sample_normal_map
    from ..kernels.tessellator import tessellate_patches

    hm = scene.heightmap
    cam = scene.camera
    t = tessellate_patches({"origin_xz": patches.origin, "size": patches.size, "outer": patches.outer,
                            "inner": patches.inner, "level": patches.level}, hm.heights, hm.dx, hm.dz,
                           cam.position, spacing=scene.lod.spacing, filter=scene.lod.filter, origin=hm.origin,
                           device=device)
    normals = None if nmap is None else sample_normal_map(nmap, t.uv, device=device)
    positions, triangles = t.positions, t.triangles
    if np.isnan(hm.heights).any():  # no-data holes: no triangle may touch a vertex that sampled NaN
        from ..kernels.displacement import drop_nonfinite_triangles

        positions, triangles = drop_nonfinite_triangles(positions, triangles, device=device)
    return Mesh(positions=positions, eye=cam.position, triangles=triangles, uv=t.uv, level=t.level,
                patch_id=t.patch_id, normals=normals)

"""``render(scene) -> Frame``: the pipeline, run backwards from the outputs the scene asks for.

Stages (each a pure function of arrays): ``vertex_normals`` (heightmap normals, Sobel), ``mesh``
(displaced mesh, camera-relative), ``raster`` (visibility pass), ``shade`` (resolve + hillshade).
Which run:

=========  =========================================
output     stages
=========  =========================================
image      vertex_normals, mesh, raster, shade
normals    vertex_normals, mesh, raster, shade
depth      mesh, raster
mesh       mesh
curvature  curvature (heightmap curvature, three-normal, four directions; its own stage)
report     (none: the report of whatever ran)
=========  =========================================
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ._io import write_image, write_json
from .mesh import Mesh
from .scene import Scene

__all__ = ["render", "Frame", "Report", "StageRecord", "stages_for"]

STAGE_ORDER = ("vertex_normals", "curvature", "mesh", "raster", "shade")
_NEEDS = {
    "image": {"vertex_normals", "mesh", "raster", "shade"},
    "normals": {"vertex_normals", "mesh", "raster", "shade"},
    "depth": {"mesh", "raster"},
    "mesh": {"mesh"},
    "curvature": {"curvature"},
    "report": set(),
}


def stages_for(outputs: tuple[str, ...]) -> list[str]:
    """The stages that the given outputs need, in pipeline order."""
    need: set[str] = set()
    for o in outputs:
        need |= _NEEDS[o]
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
            from ._io import atomic_path

            with atomic_path(out / "mesh.vtp") as tmp:
                self.mesh.to_pyvista().save(str(tmp))
            written.append(out / "mesh.vtp")
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


def render(scene: Scene, device: str = "cpu") -> Frame:
    """Render a scene, running only the stages its outputs need.

    Returns:
        A :class:`Frame`; deterministic (bit-identical across runs for the same scene).
    """
    from .kernels.displacement import grid_mesh
    from .kernels.normals import sobel_normals
    from .kernels.raster import rasterize
    from .kernels.shading import hillshade

    if not isinstance(scene, Scene):
        raise TypeError(f"scene: expected a Scene, got {type(scene).__name__}")
    cam = scene.camera
    hm = scene.heightmap
    stages = stages_for(scene.outputs)
    report = Report(info={"scene": scene.name, "heightmap": hm.name, "shape": list(hm.shape),
                          "dx": hm.dx, "dz": hm.dz, "width": cam.width, "height": cam.height,
                          "mesh_policy": scene.mesh, "outputs": list(scene.outputs), "stages_run": stages,
                          "device": device})
    frame = Frame(scene=scene, report=report)
    vnormals = None
    if "vertex_normals" in stages:
        with _timed(report, "vertex_normals") as r:
            vnormals = sobel_normals(hm.heights, hm.dx, hm.dz, border="clamp", device=device).reshape(-1, 3)
            r.counters["samples"] = int(hm.heights.size)
    if "curvature" in stages:
        from .analysis import compute_curvature

        with _timed(report, "curvature") as r:
            frame.curvature = compute_curvature(hm, "three_normal", device=device)
            r.counters.update(samples=int(hm.heights.size), method="three_normal")
    mesh = None
    if "mesh" in stages:
        with _timed(report, "mesh") as r:
            eye = cam.position
            rel = (hm.origin[0] - eye[0], eye[1], hm.origin[1] - eye[2])  # float64 subtraction on the host
            pos, uv, tri = grid_mesh(hm.heights, hm.dx, hm.dz, rel, device=device)
            n = len(pos)
            mesh = Mesh(positions=pos, eye=eye, triangles=tri, uv=uv, level=np.zeros(n, np.int32),
                        patch_id=np.zeros(n, np.int32), normals=vnormals)
            r.counters.update(patches=1, vertices=n, triangles=int(len(tri)))
        frame.mesh = mesh
    if "raster" in stages:
        with _timed(report, "raster") as r:
            frags = rasterize(mesh.positions, mesh.triangles, cam.view_matrix(relative=True), cam.proj_matrix(),
                              cam.width, cam.height, cull_back=scene.cull_back, device=device)
            r.counters.update(frags.stats)
        frame.triangle_id, frame.barycentrics = frags.triangle_id, frags.barycentrics
        if "depth" in scene.outputs:
            frame.depth = frags.depth
    if "shade" in stages:
        with _timed(report, "shade") as r:
            world_y = (mesh.positions[:, 1] + mesh.eye[1]).astype(np.float32)
            rgb, pix_n = hillshade(frame.triangle_id, frame.barycentrics, mesh.triangles, vnormals, world_y,
                                   azimuth_deg=scene.light_azimuth_deg, elevation_deg=scene.light_elevation_deg,
                                   device=device)
            r.counters["pixels"] = int(frame.triangle_id.size)
        if "image" in scene.outputs:
            frame.image = _srgb8(rgb)
        if "normals" in scene.outputs:
            frame.normals = pix_n
    return frame

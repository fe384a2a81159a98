"""The MeshSource protocol: every member the pipeline reads, defaults in SourceBase, so a source of your own is
drawn, measured and popped like the built-in ones without reading the pipeline."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pytest

import terrainwarp as tw
from terrainwarp.lod import Terrain, select
from terrainwarp.lod.policies import ScreenErrorPolicy
from terrainwarp.mesh import Mesh
from terrainwarp.rendering import MeshSource, SourceBase, pop_stats
from terrainwarp.rendering.sources import missing_members


@pytest.fixture(scope="module")
def scene():
    hm = tw.Heightmap.fbm(65, seed=4, max_height=300.0, dx=10.0)
    return tw.Scene(hm, camera=tw.Camera.default_for(hm, 64, 48), outputs=("image", "depth", "error", "report"))


@dataclass(eq=False)
class GridEvery(SourceBase):
    """Every ``step``-th sample as a grid: the smallest honest scheme (only mesh_for written)."""

    heightmap: tw.Heightmap
    step: int = 2
    calls: list = field(default_factory=list)

    def mesh_for(self, camera):
        self.calls.append(camera.position)
        hm, s = self.heightmap, self.step
        rows, cols = (np.arange(0, n, s) for n in hm.shape)
        ii, jj = np.meshgrid(rows, cols, indexing="ij")
        eye = np.asarray(camera.position)
        pos = np.stack([jj * hm.dx - eye[0], hm.heights[ii, jj] - eye[1], ii * hm.dz - eye[2]], -1).reshape(-1, 3)
        k = len(cols)
        a = (np.arange(len(rows) - 1)[:, None] * k + np.arange(k - 1)).ravel()
        tri = np.concatenate([np.stack([a, a + k, a + 1], 1), np.stack([a + 1, a + k, a + k + 1], 1)])
        n = len(pos)
        return Mesh(positions=pos.astype(np.float32), eye=camera.position, triangles=tri.astype(np.int32),
                    uv=None, level=np.zeros(n, np.int32), patch_id=np.zeros(n, np.int32)), 0.25


def test_a_source_with_only_mesh_for_renders_measures_and_pops(scene):
    src = GridEvery(scene.heightmap, 2)
    assert isinstance(src, MeshSource) and missing_members(src) == []
    assert (src.provides_normals, src.build_ms, math.isnan(src.error_m), src.patches, dict(src.last)) == \
        (False, 0.0, True, None, {})
    f = tw.render(scene, source=src)
    assert f.report.info["source"] == "GridEvery"
    assert f.report.info["stages_run"] == ["normal_map", "select", "mesh", "raster", "shade", "reference", "error"]
    assert f.report.stage_ms("select") == 0.25  # the source's own selection time
    assert f.image.shape == (48, 64, 3) and f.patches is None
    assert f.error.p99_px > 0 and f.error.see_through_px == 0
    full = tw.render(scene, source=GridEvery(scene.heightmap, 1))
    # every sample drawn: no error as the field defines it, up to float32 rounding (this source subtracts the eye
    # in float64 and rounds once; the grid kernel adds float32 offsets to a rounded origin)
    assert full.error.max_px < 1e-4
    # held_mesh_for's default re-makes the previous camera's mesh: a static scheme does not pop
    ref = tw.render(scene.with_(outputs=("depth",)))
    assert pop_stats(scene, scene.camera, f, ref, source=src).max_px == 0.0
    assert len(src.calls) == 2
    # the normal map is kept in the source's cache for the next frame
    assert tw.render(scene, source=src).report.stage("normal_map").counters == {"cached": True}


def test_a_source_missing_members_is_refused_with_their_names(scene):
    class OnlyMesh:
        def mesh_for(self, camera):
            return GridEvery(scene.heightmap).mesh_for(camera)

    with pytest.raises(TypeError, match=r"source: expected a MeshSource .* OnlyMesh without held_mesh_for, cached, "
                                        r"is_cached, report_info, provides_normals, build_ms, error_m, patches, last"):
        tw.render(scene, source=OnlyMesh())
    with pytest.raises(TypeError, match="source: expected a MeshSource"):
        tw.render(scene, source="cdlod")


def test_normals_patches_counters_and_report_info_reach_the_frame(scene):
    terrain = Terrain.prepare(scene.heightmap, roots=4, tess=4)

    @dataclass(eq=False)
    class WithEverything(GridEvery):
        provides_normals: bool = True
        build_ms: float = 12.5

        def mesh_for(self, camera):
            m, ms = super().mesh_for(camera)
            self.patches = select(terrain, camera, ScreenErrorPolicy(2.0))
            self.last = {"chunks": 7}
            normals = np.tile(np.float32([0, 1, 0]), (m.n_vertices, 1))
            return Mesh(positions=m.positions, eye=m.eye, triangles=m.triangles, uv=None, level=m.level,
                        patch_id=m.patch_id, normals=normals), ms

        def report_info(self):
            return {"scheme": {"chunks": self.last["chunks"]}}

    src = WithEverything(scene.heightmap)
    f = tw.render(scene.with_(outputs=("normals", "patches")), source=src)
    assert "normal_map" not in f.report.info["stages_run"]  # the mesh carries its normals
    assert f.patches is src.patches and len(f.patches) > 0
    assert f.report.stage("select").counters["chunks"] == 7 and f.report.info["scheme"] == {"chunks": 7}
    # the source's normals (straight up) are the ones shaded, not the heightmap's
    drawn = f.triangle_id >= 0
    assert drawn.sum() > 100 and np.allclose(f.normals[drawn], (0.0, 1.0, 0.0), atol=1e-6)


@pytest.mark.parametrize("make", ["peer", "polytree", "bintree", "cdlod", "clipmaps", "chunked", "streamed"])
def test_every_builtin_source_is_a_complete_mesh_source(make):
    from terrainwarp.heightmap import StreamedHeightmap
    from terrainwarp.lod.bintree import Bintree
    from terrainwarp.lod.peers import martini_mesh
    from terrainwarp.lod.polytree import build_polytree, default_tolerances
    from terrainwarp.rendering import BintreeSource, PeerSource, PolytreeSource, StreamedSource
    from terrainwarp.schemes import scheme_source

    hm = tw.Heightmap.fbm(33, seed=5)
    src = {"peer": lambda: PeerSource(martini_mesh(hm, 1.0), hm),
           "polytree": lambda: PolytreeSource(build_polytree(hm, default_tolerances(hm, 4)), 1),
           "bintree": lambda: BintreeSource(Bintree.build(hm, 11)),
           "streamed": lambda: StreamedSource(StreamedHeightmap.of(hm))}.get(make)
    src = src() if src is not None else scheme_source(make, hm, {"cdlod": 200.0, "clipmaps": 31, "chunked": 2.0}[make])
    assert isinstance(src, MeshSource) and missing_members(src) == []
    mesh, select_ms = src.mesh_for(tw.Camera.default_for(hm, 32, 24))
    assert mesh.n_triangles > 0 and select_ms >= 0.0

"""A frame's pipeline statistics (``Report.counters``) against a real driver's: whole LOD frames drawn by Mesa's
llvmpipe with real tessellation shaders (:class:`terrainwarp.experiments.gl.GLTerrain`) and the same meshes as
plain indexed triangles of the same clip-space vertices (:class:`terrainwarp.experiments.gl.GLMesh`), in the three
spacings, read back through ARB_pipeline_statistics_query.

What must be equal and why the rest may differ:

* patches, control points, domain points (evaluation shader invocations), primitives generated and the clipper's
  input: the tessellator is llvmpipe's, bit for bit (tests/kernels/test_tessellator.py), so they are equal;
* the clipper's output and the llvmpipe fragment model (16 per 4x4 block a triangle touches) of the indexed draw:
  the rasterizer covers llvmpipe's pixels on the same vertices, so they are equal;
* samples passed of the indexed draw is within 0.5% (a few fragments in 100,000 here): a pixel's window depth is
  llvmpipe's to within a few float32 ulps (its depth plane is set up and stepped in its own order), so where two
  fragments lie that close the depth test may go either way;
* the tessellated draw's clipper output, fragment model and samples passed are within 0.5%: llvmpipe's
  evaluation shader computes each
  vertex's clip position with its own float rounding (a few pixels' coverage differs, tests/kernels/
  test_raster.py), and its primitive generator emits a patch's triangles in another order than ours (samples
  passed counts overdraw in draw order: a patch hiding part of itself counts other fragments).
"""

from __future__ import annotations

import gl_raster_oracle as gl  # noqa: E402
import numpy as np
import pytest

from terrainwarp import Camera, Heightmap, Scene, render
from terrainwarp.experiments.gl import FrameDriver
from terrainwarp.lod import PatchList, Terrain
from terrainwarp.lod.bintree import Bintree
from terrainwarp.lod.peers import delatin_mesh
from terrainwarp.rendering.sources import BintreeSource, PeerSource
from terrainwarp.scene import LodConfig
from terrainwarp.schemes import scheme_range, scheme_source

pytestmark = pytest.mark.skipif(not gl.available(), reason="no EGL / OpenGL 4.5 context (llvmpipe) on this machine")
W, H = 640, 360
TESS = ("vertices_submitted", "primitives_submitted", "vertex_shader_invocations", "tess_control_shader_patches",
        "tess_evaluation_shader_invocations", "primitives_generated", "clipping_input_primitives")
RASTER = ("clipping_output_primitives", "fragment_shader_invocations_llvmpipe", "samples_passed")


@pytest.fixture(scope="module")
def dem():
    hm = Heightmap.example()
    cams = Scene(hm, camera=Camera.default_for(hm, W, H)).camera_path(4)
    return hm, [Camera.default_for(hm, W, H), cams[2]], Terrain.prepare(hm)


def _frames(dem, spacing):
    """LOD frames of ``spacing``: the policy's own selection (sse; continuous for fractional_odd) from a camera
    seeing all the terrain and from a flyover camera (clipped at the near plane and the viewport), and the
    flyover's patches with random fractional levels (some patches culled by a level of 0)."""
    hm, cams, terrain = dem
    lod = LodConfig(policy="continuous", spacing="fractional_odd") if spacing == "fractional_odd" else \
        LodConfig(spacing=spacing)
    out = []
    for cam in cams:
        sc = Scene(hm, camera=cam, mesh="lod", lod=lod, outputs=("depth", "counters", "mesh", "patches"))
        out.append(render(sc, terrain=terrain))
    pl = out[-1].patches
    rng = np.random.default_rng(len(spacing))
    outer = rng.uniform(1.0, 20.0, pl.outer.shape).astype(np.float32)
    outer[rng.random(len(pl)) < 0.1, 0] = 0.0
    held = PatchList(**{**{k: getattr(pl, k) for k in PatchList._fields}, "outer": outer,
                        "inner": rng.uniform(1.0, 20.0, pl.inner.shape).astype(np.float32)})
    out.append(render(out[-1].scene, terrain=terrain, patches=held))
    return out


@pytest.fixture(scope="module")
def driver():
    d = FrameDriver()
    yield d
    d.close()


@pytest.mark.parametrize("spacing", ["equal", "fractional_even", "fractional_odd"])
def test_frame_counters_equal_llvmpipes(dem, driver, spacing):
    clipped = 0
    for f in _frames(dem, spacing):
        ours = f.report.counters
        tess = driver.statistics(f)
        for name in TESS:
            assert ours[name] == tess[name], (spacing, name, ours[name], tess[name])
        flat = driver.statistics(f, indexed=True)
        flat["fragment_shader_invocations_llvmpipe"] = flat["fragment_shader_invocations"]
        tess["fragment_shader_invocations_llvmpipe"] = tess["fragment_shader_invocations"]
        for name in RASTER[:2]:
            assert ours[name] == flat[name], (spacing, name, ours[name], flat[name])
        for name, theirs in (("samples_passed", flat["samples_passed"]), *((n, tess[n]) for n in RASTER)):
            assert abs(ours[name] - theirs) <= 0.005 * theirs, (spacing, name, ours[name], theirs)
        clipped += ours["clipping_output_primitives"] != ours["clipping_input_primitives"]
        assert ours["draw_calls"] == 1 and ours["tess_evaluation_shader_invocations"] == f.mesh.n_vertices
    assert clipped >= 2  # the flyover frames were clipped


@pytest.mark.parametrize("family", ["grid", "cdlod", "clipmaps", "chunked", "delatin", "bintree"])
def test_indexed_families_counters_equal_llvmpipes(dem, driver, family):
    """Every other family drawn as indexed triangles, one glDrawElements per draw call it issues (CDLOD per node,
    clipmaps per block and per level's stitches, chunked per chunk, the rest one draw): the input assembler's and
    the vertex shader's counters (llvmpipe's vertex cache model) are equal, the raster counters as above. Samples
    passed may differ more for CDLOD, whose draws take the quadrants node by node while our submission order is
    the vertex stage's (quadrant by quadrant)."""
    hm, cams, _ = dem
    cache: dict = {}
    src = {"grid": None, "cdlod": lambda: scheme_source("cdlod", hm, 2.0 * scheme_range("cdlod", hm)[0], cache=cache),
           "clipmaps": lambda: scheme_source("clipmaps", hm, 63, cache=cache),
           "chunked": lambda: scheme_source("chunked", hm, 2.0, cache=cache),
           "delatin": lambda: PeerSource(delatin_mesh(hm, 2.0), hm, cache=cache),
           "bintree": lambda: BintreeSource(Bintree.build(hm, 19), cache=cache)}[family]
    source = None if src is None else src()
    for cam in cams:
        f = render(Scene(hm, camera=cam, outputs=("depth", "counters", "mesh")), source=source)
        ours, d = f.report.counters, f.mesh.draws
        got = driver.statistics(f)
        assert ours["vertex_shader_invocations_llvmpipe"] == got["vertex_shader_invocations"], family
        for name in ("vertices_submitted", "primitives_submitted", "primitives_generated", "clipping_input_primitives",
                     "clipping_output_primitives"):
            assert ours[name] == got[name], (family, name)
        assert ours["fragment_shader_invocations_llvmpipe"] == got["fragment_shader_invocations"], family
        assert abs(ours["samples_passed"] - got["samples_passed"]) <= 0.005 * got["samples_passed"], family
        assert ours["draw_calls"] == (1 if d is None or d.ranges is None else len(d.ranges))

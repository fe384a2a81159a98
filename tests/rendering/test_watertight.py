"""check_watertight on hand-made frames: tilings that must be crack-free, and forced mismatches that
must be found and located."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import digest

from terrainwarp import Camera, Heightmap, LodConfig, Scene, check_watertight, render
from terrainwarp.kernels.tessellator import tessellate_patches
from terrainwarp.lod import ContinuousPolicy, DistancePolicy, LodState, ScreenErrorPolicy, Terrain, select
from terrainwarp.mesh import Mesh

SPACINGS = ["equal", "fractional_even", "fractional_odd"]


def _heights(n=65, seed=0):
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:n, 0:n] / (n - 1)
    return (40 * np.sin(5 * x) * np.cos(3 * y) + rng.normal(0, 2, (n, n))).astype(np.float32)


def _tiling_2x2(rng, spacing, size=16.0, origin=(1000.0, -500.0)):
    """2x2 equal patches; each shared edge has one factor, used by both sides; inner levels differ."""
    lo = 2.0 if spacing == "fractional_even" else 1.0
    f = lambda: float(rng.choice([lo, 3.0, 4.0, 7.5, 13.3, 32.0, 63.9, 64.0, rng.uniform(lo, 40)]))  # noqa: E731
    # vertical edges x = 0, 1, 2 (times size) for rows 0, 1; horizontal edges z = 0, 1, 2 for columns 0, 1
    vert = {(i, r): f() for i in range(3) for r in range(2)}
    hor = {(c, j): f() for c in range(2) for j in range(3)}
    org, outer, inner = [], [], []
    for r in range(2):
        for c in range(2):
            org.append((origin[0] + c * size, origin[1] + r * size))
            outer.append([vert[(c, r)], hor[(c, r)], vert[(c + 1, r)], hor[(c, r + 1)]])
            inner.append([f(), f()])
    return {"origin_xz": np.array(org), "size": np.full(4, size), "outer": np.array(outer, np.float32),
            "inner": np.array(inner, np.float32), "level": np.zeros(4, np.int32)}


def _quadtree(level, size=8.0, origin=(-300.0, 7000.0)):
    """2x2 roots of side 2*size; roots (0,0) and (1,1) split into 4 children. A coarse patch doubles
    the factor of each edge that faces finer neighbours: root (1,0) on its u=0 and v=1 edges, root
    (0,1) on its u=1 and v=0 edges, so every edge orientation meets a doubled neighbour."""
    org, sz, outer, lvl = [], [], [], []
    for r in range(2):
        for c in range(2):
            x0, z0 = origin[0] + 2 * size * c, origin[1] + 2 * size * r
            if (r, c) in ((0, 0), (1, 1)):
                for rr in range(2):
                    for cc in range(2):
                        org.append((x0 + size * cc, z0 + size * rr))
                        sz.append(size)
                        outer.append([level] * 4)
                        lvl.append(1)
            else:
                o = [level] * 4
                if (r, c) == (0, 1):
                    o[0] = o[3] = 2 * level
                else:
                    o[2] = o[1] = 2 * level
                org.append((x0, z0))
                sz.append(2 * size)
                outer.append(o)
                lvl.append(0)
    n = len(org)
    return {"origin_xz": np.array(org), "size": np.array(sz), "outer": np.array(outer, np.float32),
            "inner": np.full((n, 2), level, np.float32), "level": np.array(lvl, np.int32)}


def _frame(patches, spacing, filt="bilinear", eye=(1010.0, 300.0, -480.0), dx=0.5, dz=0.5, origin=None):
    h = _heights()
    if origin is None:
        origin = (float(patches["origin_xz"][:, 0].min()), float(patches["origin_xz"][:, 1].min()))
    return tessellate_patches(patches, h, dx, dz, eye, spacing=spacing, filter=filt, origin=origin)


@pytest.mark.parametrize("spacing", SPACINGS)
def test_tiling_2x2_mixed_levels_is_watertight(spacing):
    rng = np.random.default_rng(7)
    for trial in range(4):
        t = _frame(_tiling_2x2(rng, spacing), spacing, filt=["bilinear", "bicubic"][trial % 2])
        rep = check_watertight(t)
        assert rep.watertight, rep
        assert rep.n_border_edges > 0 and rep.n_triangles > 0


@pytest.mark.parametrize("spacing,level", [("equal", L) for L in (1, 2, 4, 8, 16, 32)]
                         + [("fractional_even", L) for L in (2, 4, 8, 32)])
def test_quadtree_doubled_edges_are_watertight(spacing, level):
    t = _frame(_quadtree(level), spacing, filt="bicubic")
    rep = check_watertight(t)
    assert rep.watertight, rep
    # the mesh is a disc: V - E + F = 1 for the merged mesh
    assert rep.n_vertices - (3 * rep.n_triangles + rep.n_border_edges) // 2 + rep.n_triangles == 1


def test_doubled_edge_with_non_power_of_two_level_cracks_like_the_gpu():
    """2^16/3 is not exact: the coarse edge's points (factor 6) miss the fine ones (factor 3) by 2^-16."""
    rep = check_watertight(_frame(_quadtree(3), "equal"))
    assert rep.n_open_edges > 0 and rep.n_t_junctions > 0


@pytest.mark.parametrize("spacing", SPACINGS)
def test_forced_mismatch_is_detected_and_located(spacing):
    rng = np.random.default_rng(3)
    p = _tiling_2x2(rng, spacing)
    p["outer"][:, :] = 6.0
    p["inner"][:, :] = 6.0
    p["outer"][0, 2] = 9.0  # patch 0's u=1 edge (x = x0 + size) no longer matches patch 1's u=0 edge
    t = _frame(p, spacing)
    rep = check_watertight(t)
    assert not rep.watertight
    assert rep.n_open_edges > 0 and rep.n_t_junctions > 0
    x_edge = p["origin_xz"][0, 0] + p["size"][0] - t.eye[0]
    z_range = (p["origin_xz"][0, 1] - t.eye[2], p["origin_xz"][0, 1] + p["size"][0] - t.eye[2])
    assert np.allclose(rep.open_edges[:, :, 0], x_edge, atol=1e-3)
    assert np.all((rep.open_edges[:, :, 2] >= z_range[0] - 1e-3) & (rep.open_edges[:, :, 2] <= z_range[1] + 1e-3))
    assert np.allclose(rep.t_junctions[:, 0, 0], x_edge, atol=1e-3)
    d = rep.to_dict()
    assert d["watertight"] is False and len(d["open_edges"]) == rep.n_open_edges


def test_border_modes_and_plain_arrays():
    # one quad as two triangles: 4 border edges, no cracks
    pos = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 1]], np.float32)
    tri = np.array([[0, 3, 1], [1, 3, 2]], np.int32)
    rep = check_watertight(pos, tri)
    assert rep.watertight and rep.n_border_edges == 4
    assert check_watertight((pos, tri), border=None).n_open_edges == 4
    assert check_watertight(pos, tri, border=(-1, 2, -1, 2)).n_open_edges == 4
    # a T-junction: a vertex in the middle of the shared diagonal on one side only
    pos2 = np.vstack([pos, [[0.5, 0.1, 0.5]]]).astype(np.float32)
    tri2 = np.array([[0, 3, 4], [0, 4, 1], [1, 3, 2]], np.int32)
    rep2 = check_watertight(pos2, tri2)
    assert rep2.n_open_edges == 3 and rep2.n_t_junctions == 1
    assert np.allclose(rep2.t_junctions[0, 0], [0.5, 0.1, 0.5])
    # degenerate triangles (two corners at the same bits) are dropped, not counted as cracks
    pos3 = np.vstack([pos, pos[[1]]]).astype(np.float32)
    tri3 = np.array([[0, 3, 1], [1, 3, 2], [1, 4, 2]], np.int32)
    rep3 = check_watertight(pos3, tri3)
    assert rep3.watertight and rep3.n_degenerate == 1
    empty = check_watertight(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))
    assert empty.watertight and empty.n_vertices == 0 and empty.n_triangles == 0


def test_bad_input():
    with pytest.raises(ValueError, match="positions"):
        check_watertight(np.zeros((3, 2)), np.zeros((1, 3), np.int32))
    with pytest.raises(ValueError, match="triangles"):
        check_watertight(np.zeros((3, 3)), np.array([[0, 1, 5]]))
    with pytest.raises(TypeError, match="mesh"):
        check_watertight(42)
    with pytest.raises(ValueError, match="border"):
        check_watertight(np.zeros((3, 3)), np.array([[0, 1, 2]]), border="box")


def test_report_is_deterministic():
    def run():
        rep = check_watertight(_frame(_quadtree(8), "equal"))
        return digest(rep.open_edges, np.frombuffer(str(rep.to_dict()).encode(), np.uint8))

    assert run() == run()


@pytest.mark.parametrize("name", ["jacksboro", "fbm"])
def test_lod_frames_are_watertight(name):
    """Frames selected by the LOD issue's policies (doubled edges, continuous per-edge factors)."""
    hm = Heightmap.example("jacksboro") if name == "jacksboro" else Heightmap.fbm(257, seed=3)
    terrain = Terrain.prepare(hm, roots=4, tess=16)
    cam = Camera.default_for(hm, 320, 240)
    levels = set()
    for pol, spacing in [(ScreenErrorPolicy(0.5), "equal"), (DistancePolicy(k=2.0), "fractional_even"),
                         (ContinuousPolicy(target_px=8.0, level=2), "fractional_odd")]:
        pl = select(terrain, cam, pol)
        t = tessellate_patches({"origin_xz": pl.origin, "size": pl.size, "outer": pl.outer, "inner": pl.inner,
                                "level": pl.level}, hm.heights, hm.dx, hm.dz, cam.position, spacing=spacing,
                               filter="bicubic", origin=hm.origin)
        rep = check_watertight(t)
        assert rep.watertight and rep.n_triangles > 1000, (type(pol).__name__, rep)
        levels |= set(np.unique(pl.level).tolist())
    assert len(levels) >= 2  # the frames mix levels


@pytest.mark.parametrize("spacing", SPACINGS)
def test_shared_edge_vertices_are_bit_identical(spacing):
    rng = np.random.default_rng(11)
    p = _tiling_2x2(rng, spacing)
    t = _frame(p, spacing, filt="bicubic")

    def edge(pid, axis, value):
        sel = (t.patch_id == pid) & (t.domain[:, axis] == value)
        return {r.tobytes() for r in t.positions[sel]}

    # patches: 0 (x0, z0), 1 (x0 + s, z0), 2 (x0, z0 + s), 3 (x0 + s, z0 + s)
    for a, b, axis in ((0, 1, 0), (2, 3, 0), (0, 2, 1), (1, 3, 1)):
        ea, eb = edge(a, axis, 1.0), edge(b, axis, 0.0)
        assert len(ea) >= 2 and ea == eb


# -- a frame's open edges, by kind (issue 20 item 6) ------------------------------------------------
@pytest.fixture(scope="module")
def flyover_frames():
    """The README's flyover: the demo DEM, sse 1 px, 16 roots of level 16, eight cameras along the default
    path (a smaller viewport than the README's 1280 x 720; the frames still cull patches)."""
    hm = Heightmap.example()
    lod = LodConfig(policy="sse", tolerance_px=1.0, roots=16, tess=16)
    scene = Scene(hm, camera=Camera.default_for(hm, 640, 360), mesh="lod", lod=lod, outputs=("mesh", "patches"))
    terrain, state = Terrain.prepare(hm, roots=16, tess=16), LodState()
    return [render(scene.with_(camera=c), terrain=terrain, state=state) for c in scene.camera_path(8)]


def test_flyover_has_no_cracks_and_reports_culled_neighbours_apart(flyover_frames):
    culled = []
    for f in flyover_frames:
        rep = check_watertight(f)
        assert rep.watertight and rep.n_cracks == 0 and rep.n_t_junctions == 0, rep
        assert rep.n_border_edges == rep.n_heightmap_border_edges + rep.n_culled_border_edges + rep.n_hole_border_edges
        assert rep.n_hole_border_edges == 0  # the demo DEM has no no-data
        # the same from the mesh with the frame's patches and heightmap
        same = check_watertight(f.mesh, patches=f.patches, heightmap=f.scene.heightmap)
        assert same.to_dict() == rep.to_dict()
        culled.append(rep.n_culled_border_edges)
        # what the README used to promise: the plain mesh check counts culled neighbours' edges as open
        if rep.n_culled_border_edges:
            assert check_watertight(f.mesh).n_open_edges > 0
    assert max(culled) > 0 and sum(c > 0 for c in culled) >= 4, culled


def test_a_moved_shared_vertex_is_a_crack(flyover_frames):
    f = flyover_frames[0]
    m, hm = f.mesh, f.scene.heightmap
    # a vertex two drawn patches share (bit-identical copies in both), away from the heightmap's border
    world = m.world_positions()
    (gx0, gz0), (gx1, gz1) = hm.bounds_xz
    keys = m.positions.view(np.uint32).reshape(-1, 3)
    _, first, inv, count = np.unique(keys, axis=0, return_index=True, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    shared = np.flatnonzero((count[inv] == 2) & (np.arange(len(keys)) != first[inv])
                            & (world[:, 0] > gx0 + 50) & (world[:, 0] < gx1 - 50)
                            & (world[:, 2] > gz0 + 50) & (world[:, 2] < gz1 - 50))
    assert len(shared) > 0
    kinds_before = check_watertight(f)
    pos = m.positions.copy()
    pos[shared[len(shared) // 2], 1] += np.float32(0.5)  # one patch's copy only: the seam opens
    broken = Mesh(positions=pos, eye=m.eye, triangles=m.triangles, uv=m.uv, level=m.level, patch_id=m.patch_id,
                  normals=m.normals)
    rep = check_watertight(broken, patches=f.patches, heightmap=hm)
    assert not rep.watertight and rep.n_cracks >= 2
    assert rep.n_culled_border_edges == kinds_before.n_culled_border_edges
    # the crack is located at the moved vertex
    moved = pos[shared[len(shared) // 2]].astype(np.float64)
    assert np.any(np.all(np.isclose(rep.open_edges, moved, atol=1e-3), axis=-1))


def test_hole_borders_and_heightmap_border_of_frames_with_no_data():
    h = _heights(65)
    h[20:23, 30:33] = np.nan
    hm = Heightmap.from_array(h, 1.0, allow_nan=True)
    cam = Camera(position=(32.0, 200.0, 32.001), target=(32.0, 0.0, 32.0), up=(0.0, 0.0, -1.0), width=96,
                 height=96, near=1.0, far=1000.0)
    for mesh in ("grid", "lod"):
        f = render(Scene(hm, camera=cam, mesh=mesh, lod=LodConfig(roots=4, tess=16), outputs=("mesh",)))
        rep = check_watertight(f)
        assert rep.watertight and rep.n_hole_border_edges > 0 and rep.n_heightmap_border_edges > 0, (mesh, rep)
        assert rep.n_culled_border_edges == 0  # the whole heightmap is in view
        d = rep.to_dict()
        assert d["n_hole_border_edges"] == rep.n_hole_border_edges and d["watertight"] is True
    with pytest.raises(ValueError, match="heightmap"):
        check_watertight(f.mesh, patches=f.patches)

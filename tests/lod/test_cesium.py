"""The cesium policy selects as Cesium's heightmap terrain does: 65x65-sample tiles, the geometric error of Cesium's
estimate (0.25 x W0 / (65 x 2^L)), the SSE test geometricError x height / (distance x 2 tan(fovy/2)) on the tile's
box, refining while the error is not below maximumScreenSpaceError; hand-computed cases, then a reference
traversal written from CesiumJS's QuadtreePrimitive rule against the one-launch walk on many cameras."""

import math

import numpy as np
import pytest

from terrainwarp import Camera, Heightmap, LodConfig, Scene, render
from terrainwarp.fit import fit_lod, knobs
from terrainwarp.kernels.lod import frustum_planes
from terrainwarp.lod.cesium import CesiumTerrain, cesium_roots, tile_sample_range
from terrainwarp.lod.policies import cesium_level_error, cesium_refines, cesium_sse
from terrainwarp.rendering.sources import scene_source


def test_the_rule_by_hand():
    # a 1280 m level-0 tile: 0.25 * 1280 / 65 = 4.923 m, halved per level
    assert cesium_level_error(0, 1280.0) == pytest.approx(4.923076923)
    assert cesium_level_error(2, 1280.0) == pytest.approx(1.230769231)
    # Cesium's own level 0 on WGS84 (2 tiles across): 6378137 * 2 pi * 0.25 / (65 * 2) = 77067.34 m
    assert cesium_level_error(0, 6378137.0 * 2 * math.pi / 2) == pytest.approx(77067.34, rel=1e-6)
    # 4.923 m at 1414.2 m, 100 px high, 60 degrees: 4.923 * 100 / (1414.2 * 2 tan 30) = 0.30147 px
    sse = cesium_sse(4.923076923, math.hypot(1000, 1000), 100, 60.0)
    assert sse == pytest.approx(0.30147, rel=1e-4)
    assert cesium_refines(sse, 0.30) and not cesium_refines(sse, 0.31)
    assert cesium_refines(2.0, 2.0)  # a tile meets the SSE only strictly below it
    assert cesium_sse(1.0, 0.0, 100, 60.0) == math.inf


def test_tiles_and_their_boxes():
    assert cesium_roots((129, 129)) == (1, 1) and cesium_roots((129, 257)) == (2, 1)  # 2:1, as Cesium starts
    assert cesium_roots((65, 65)) == (1, 1) and cesium_roots((300, 100)) == (1, 3)
    h = np.arange(129 * 129, dtype=np.float32).reshape(129, 129)
    mn, mx = tile_sample_range(h, (1, 1), 128.0, 0)  # the root tile samples every other sample: rows/cols 0..128
    assert mn[0, 0] == 0 and mx[0, 0] == h[128, 128]
    mn, mx = tile_sample_range(h, (1, 1), 128.0, 1)
    assert mn.shape == (2, 2) and mx[0, 0] == h[64, 64] and mn[1, 1] == h[64, 64]


@pytest.fixture(scope="module")
def flat():
    hm = Heightmap.from_array(np.zeros((129, 129), np.float32), 10.0, 10.0)
    return CesiumTerrain(hm, 0.30)


def test_a_hand_computed_frame_refines_or_not_at_the_threshold(flat):
    """A flat 1280 m terrain (one level-0 tile, 4 level-1 tiles); the eye 1000 m above and 1000 m south of its
    edge: the root tile's box is 1414.2 m away, its error 0.3015 px at 100 px high and 60 degrees."""
    cam = Camera(position=(640.0, 1000.0, 2280.0), target=(640.0, 0.0, 640.0), fov_y_deg=60.0, width=160,
                 height=100, near=1.0, far=1e5)
    assert flat.terrain.roots == (1, 1) and flat.terrain.depth == 1 and flat.level0_width_m == 1280.0
    flat.max_sse_px = 0.30
    sel = flat.select(cam)
    assert sorted(zip(sel.level.tolist(), sel.x.tolist(), sel.y.tolist())) == [(1, 0, 0), (1, 0, 1), (1, 1, 0),
                                                                             (1, 1, 1)]
    flat.max_sse_px = 0.31
    sel = flat.select(cam)
    assert sel.level.tolist() == [0]
    # Cesium's skirts: min(4 x the level's error, 1000) m, only where a neighbour lies inside the terrain
    flat.max_sse_px = 0.30
    sel = flat.select(cam)
    assert np.allclose(sel.skirt, 4 * 4.923076923 / 2, rtol=1e-6)


def _reference(c: CesiumTerrain, cam: Camera) -> set[tuple[int, int, int]]:
    """CesiumJS's traversal (QuadtreePrimitive.visitTile) written out: from the level-0 tiles, cull a tile whose box
    is outside the frustum, draw it when its SSE is below maximumScreenSpaceError or it has no children, else
    visit its four children. float64 throughout."""
    t, hm = c.terrain, c.heightmap
    planes = frustum_planes(cam.proj_matrix() @ cam.view_matrix()).astype(np.float64)
    eye = np.asarray(cam.position)
    out = set()
    todo = [(0, x, y) for y in range(t.roots[1]) for x in range(t.roots[0])]
    while todo:
        lvl, x, y = todo.pop()
        if not t.inside(lvl, np.array([x]), np.array([y]))[0]:
            continue
        sx, sz = t.node_size_world(lvl)
        mn, mx, _ = t.stats[lvl]
        lo = np.array([hm.origin[0] + x * sx, mn[y, x], hm.origin[1] + y * sz])
        hi = np.array([lo[0] + sx, mx[y, x], lo[2] + sz])
        corners = np.array([[a, b, cc, 1.0] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for cc in (lo[2], hi[2])])
        if any(np.all(corners @ p < 0) for p in planes):
            continue
        d = float(np.linalg.norm(np.maximum(np.maximum(lo - eye, eye - hi), 0.0)))
        sse = cesium_sse(cesium_level_error(lvl, c.level0_width_m), d, cam.height, cam.fov_y_deg)
        if lvl == t.depth or not cesium_refines(sse, c.max_sse_px):
            out.add((lvl, x, y))
        else:
            todo += [(lvl + 1, 2 * x + i, 2 * y + j) for j in (0, 1) for i in (0, 1)]
    return out


def test_the_walk_selects_the_tiles_cesiums_rule_does():
    hm = Heightmap.fbm(257, seed=5, dx=10.0, max_height=600.0)
    c = CesiumTerrain(hm)
    sc = Scene(hm, camera=Camera.default_for(hm, 320, 180))
    cams = sc.camera_path(6) + sc.camera_path(3, preset="high") + [sc.camera]
    levels = set()
    for cam in cams:
        for m in (0.5, 2.0, 8.0):
            c.max_sse_px = m
            sel = c.select(cam)
            got = set(zip(sel.level.tolist(), sel.x.tolist(), sel.y.tolist()))
            assert got == _reference(c, cam), (cam, m)
            levels |= set(sel.level.tolist())
    assert levels == {0, 1, 2}  # every level drawn somewhere: the cases cover refining and not


def test_a_cesium_setting_renders_saves_fits_and_lists_its_knob(tmp_path):
    hm = Heightmap.fbm(129, seed=1, dx=10.0, max_height=300.0)
    sc = Scene(hm, camera=Camera.default_for(hm, 96, 54), mesh="lod",
               lod=LodConfig(policy="cesium", params={"max_sse_px": 1.5}))
    assert [k.name for k in knobs("cesium", hm)] == ["max_sse_px"]
    a = render(sc.with_(outputs=("depth",)))
    back = Scene.load(sc.save(tmp_path / "c.toml"))
    assert back.lod == sc.lod and np.array_equal(render(back.with_(outputs=("depth",))).depth, a.depth)
    assert isinstance(scene_source(sc).scheme, CesiumTerrain)
    res = fit_lod(sc.with_(mesh="grid"), 1.0, policy="cesium", cameras=sc.camera_path(2))
    assert res.met and res.validated.worst_p99 <= 1.0 and "max_sse_px" in res.values
    assert res.to_dict()["pixel_knobs"]["max_sse_px"]["px"] == pytest.approx(res.values["max_sse_px"])
    assert f"maximumScreenSpaceError = {res.values['max_sse_px']:.4g} at 96x54, 60 degree fov gives a true " \
           f"worst-frame p99 of {res.validated.worst_p99:.3g} px" in res.message

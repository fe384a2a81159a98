import numpy as np
import pytest
from conftest import digest
from scipy import ndimage

from terrainwarp import Camera, Heightmap, LodConfig, Scene, check_watertight, render
from terrainwarp.camera import flyover
from terrainwarp.lod import Terrain
from terrainwarp.lod.bintree import Bintree
from terrainwarp.lod.cdlod import Cdlod
from terrainwarp.lod.peers import delatin_mesh
from terrainwarp.lod.polytree import build_polytree, default_tolerances
from terrainwarp.measure.sample_error import popping
from terrainwarp.rendering import rasterize
from terrainwarp.rendering.pipeline import plan_for, pop_stats, stages_for
from terrainwarp.rendering.sources import BintreeSource, PeerSource, PolytreeSource, scheme_source


@pytest.fixture(scope="module")
def demo_frame():
    return render(Scene(Heightmap.example(), outputs=("image", "depth", "normals", "report")))


def test_demo_frame_is_terrain_without_holes(demo_frame):
    f = demo_frame
    assert f.image.shape == (480, 640, 3) and f.image.dtype == np.uint8
    covered = f.triangle_id >= 0
    assert 0.15 < covered.mean() < 0.9
    # no holes inside the terrain: filling the covered mask's holes adds nothing
    assert np.array_equal(ndimage.binary_fill_holes(covered), covered)
    assert np.all((f.depth[covered] > 0) & (f.depth[covered] < 1))
    assert np.all(f.depth[~covered] == 1.0)
    n = f.normals[covered]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    assert np.all(n[:, 1] > 0)  # terrain normals point up
    # hillshade varies: it is not a flat colour
    assert f.image[covered].std() > 10


def test_render_is_deterministic(demo_frame):
    again = render(demo_frame.scene)
    assert digest(demo_frame.image, demo_frame.depth, demo_frame.normals) == \
        digest(again.image, again.depth, again.normals)


def test_report_lists_stages_with_counters(demo_frame):
    r = demo_frame.report
    assert [s.name for s in r.stages] == ["normal_map", "mesh", "raster", "shade"]
    mesh = r.stage("mesh").counters
    assert mesh["vertices"] == 344 * 403
    assert mesh["triangles"] == 2 * 343 * 402
    ras = r.stage("raster").counters
    assert ras["pixels_covered"] == int((demo_frame.triangle_id >= 0).sum())
    assert all(s.time_ms >= 0 for s in r.stages)
    d = r.to_dict()
    assert d["info"]["stages_run"] == ["normal_map", "mesh", "raster", "shade"]


def test_the_report_splits_the_call_into_kernels_and_host():
    hm = Heightmap.fbm(65, seed=2)
    f = render(Scene(hm, mesh="lod", lod=LodConfig(roots=4, tess=8), outputs=("depth",)))
    r = f.report
    assert r.render_ms >= r.total_ms > 0 and 0 < r.kernel_ms < r.render_ms
    assert r.host_ms == pytest.approx(r.render_ms - r.kernel_ms)
    host = [line for line in r.table().splitlines() if line.startswith("host")]
    assert len(host) == 1 and "outside kernels" in host[0] and f"{r.kernel_ms:.1f}" in host[0]
    d = r.to_dict()
    assert d["render_ms"] == r.render_ms and d["kernel_ms"] == r.kernel_ms and d["host_ms"] == r.host_ms
    assert "outside kernels" in r._repr_html_()


def test_one_plan_per_kind_of_call_says_what_each_stage_makes():
    depth = plan_for(("depth",), "lod", True)
    assert depth.stages == ("select", "mesh", "raster") and not (depth.attributes or depth.barycentrics)
    err = plan_for(("error",), "lod", True)
    assert err.barycentrics and not err.attributes and not err.depth
    img = plan_for(("image", "depth"), "source", provides_normals=True)
    assert img.attributes and img.barycentrics and img.image and img.depth and not img.normals
    assert "normal_map" not in img.stages and "normal_map" in plan_for(("image",), "source").stages
    assert plan_for(("mesh",), "grid").attributes and plan_for(("depth",), "lod", True) is depth  # worked out once
    f = render(Scene(Heightmap.fbm(33, seed=2), mesh="lod", lod=LodConfig(roots=2, tess=4), outputs=("depth",)))
    assert f.mesh.uv is None and f.barycentrics is None and f.depth is not None  # what the plan leaves out


def test_only_needed_stages_run():
    hm = Heightmap.fbm(33, seed=2)
    assert stages_for(("depth",)) == ["mesh", "raster"]
    assert stages_for(("mesh",)) == ["mesh"]
    assert stages_for(("report",)) == []
    f = render(Scene(hm, outputs=("depth",)))
    assert [s.name for s in f.report.stages] == ["mesh", "raster"]
    assert f.image is None and f.normals is None and f.depth is not None
    m = render(Scene(hm, outputs=("mesh",)))
    assert m.mesh.n_triangles == 2 * 32 * 32 and m.depth is None


def _wall_scene(wall: bool) -> Scene:
    h = np.zeros((64, 64), np.float32)
    if wall:
        h[32, :] = 1000.0
    hm = Heightmap.from_array(h, 1.0)
    cam = Camera(position=(31.5, 5.0, 90.0), target=(31.5, 0.0, 0.0), fov_y_deg=60, width=160, height=120,
                 near=0.1, far=1000.0)
    return Scene(hm, camera=cam, outputs=("depth",))


def test_occlusion_tall_wall_hides_what_is_behind():
    for wall in (False, True):
        f = render(_wall_scene(wall))
        tri = f.triangle_id
        cells_w = 63
        cell_row = (tri[tri >= 0] // 2) // cells_w  # triangle -> cell row i
        behind = int((cell_row < 31).sum())
        if wall:
            assert behind == 0
            assert int((cell_row >= 31).sum()) > 0
        else:
            assert behind > 0  # the check above is able to fail


def test_far_from_origin_terrain_renders_like_at_origin():
    # Camera-relative float32 positions: the same terrain 10,000 km away gives the same picture.
    h = Heightmap.fbm(65, seed=4, dx=10.0, max_height=200.0)
    far = Heightmap.from_array(h.heights, 10.0, origin=(1.0e7, -1.0e7))
    cam = Camera.default_for(h, 128, 96)
    off = np.array([1.0e7, 0.0, -1.0e7])
    cam_far = cam.with_(position=tuple(np.add(cam.position, off)), target=tuple(np.add(cam.target, off)))
    a = render(Scene(h, camera=cam, outputs=("depth",)))
    b = render(Scene(far, camera=cam_far, outputs=("depth",)))
    assert (a.triangle_id != b.triangle_id).mean() < 1e-3


def test_scene_validation():
    hm = Heightmap.fbm(9, seed=0)
    with pytest.raises(ValueError, match="outputs"):
        Scene(hm, outputs=("image", "sparkles"))
    with pytest.raises(ValueError, match="mesh"):
        Scene(hm, mesh="octree")
    with pytest.raises(TypeError, match="heightmap"):
        Scene(np.zeros((3, 3)))
    with pytest.raises(TypeError, match="scene"):
        render("scene.toml")


def test_scene_toml(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text('[heightmap]\nfbm = { rows = 33, seed = 3 }\n[camera]\nwidth = 64\nheight = 48\n'
                 '[render]\noutputs = ["depth"]\n')
    sc = Scene.load(p)
    assert sc.camera.width == 64 and sc.outputs == ("depth",)
    (tmp_path / "bad.toml").write_text("[heightmap\nexample=")
    with pytest.raises(ValueError, match="TOML"):
        Scene.load(tmp_path / "bad.toml")
    (tmp_path / "unk.toml").write_text('[heightmap]\nexample = "jacksboro"\ncolour = 3\n')
    with pytest.raises(ValueError, match="unknown key"):
        Scene.load(tmp_path / "unk.toml")
    with pytest.raises(FileNotFoundError, match="scene"):
        Scene.load(tmp_path / "nope.toml")


def test_frame_save_writes_files(tmp_path):
    hm = Heightmap.fbm(33, seed=5)
    f = render(Scene(hm, camera=Camera.default_for(hm, 64, 48), outputs=("image", "depth", "report", "mesh")))
    written = {p.name for p in f.save(tmp_path)}
    assert written == {"frame.png", "depth.exr", "report.json", "mesh.vtp"}
    back = Heightmap.load(tmp_path / "depth.exr")  # the depth image reads back bit-exact
    assert back.heights.tobytes() == f.depth.tobytes()
    assert not [p for p in tmp_path.iterdir() if ".tmp" in p.name]


def test_stage_plan_for_lod_scenes():
    assert stages_for(("image",), "lod") == ["prepare", "normal_map", "select", "mesh", "raster", "shade"]
    assert stages_for(("image",), "lod", have_terrain=True) == ["normal_map", "select", "mesh", "raster", "shade"]
    assert stages_for(("patches",), "lod", have_terrain=True) == ["select"]
    assert stages_for(("error",), "grid") == ["mesh", "raster", "reference", "error"]
    assert stages_for(("patches",), "grid") == []


def test_error_output_of_the_grid_is_zero(tmp_path):
    hm = Heightmap.fbm(65, seed=6, dx=5.0, max_height=150.0)
    f = render(Scene(hm, camera=Camera.default_for(hm, 96, 72), outputs=("error", "report")))
    assert f.error.max_px < 2e-3 and f.error.see_through_px == 0 and f.error.mismatched == 0
    assert f.report.stage("reference").counters["reused"] is True
    names = {p.name for p in f.save(tmp_path)}
    assert "error_px.exr" in names and "report.json" in names
    assert "image_error_px.exr" in names
    # the primary error per heightmap sample, the image error per pixel
    import OpenImageIO as oiio  # the maps hold NaN where not measured: read them as images

    assert oiio.ImageBuf(str(tmp_path / "error_px.exr")).get_pixels().shape[:2] == hm.shape
    assert oiio.ImageBuf(str(tmp_path / "image_error_px.exr")).get_pixels().shape[:2] == (72, 96)
    assert f.error.max_px == 0.0 and f.error.samples_visible > 500  # the grid passes through every sample


def test_lod_config_refuses_settings_that_crack():
    with pytest.raises(ValueError, match="fractional_odd"):
        LodConfig(policy="sse", spacing="fractional_odd")
    with pytest.raises(ValueError, match="power of two"):
        LodConfig(policy="sse", tess=12)
    LodConfig(policy="continuous", spacing="fractional_odd", tess=12)  # a uniform grid: no doubled edges


def test_lod_frame_is_watertight_and_close_to_the_reference():
    hm = Heightmap.example()
    cam = Camera.default_for(hm, 320, 240)
    terrain = Terrain.prepare(hm, roots=16, tess=16)
    for spacing in ("equal", "fractional_even"):
        sc = Scene(hm, camera=cam, mesh="lod", lod=LodConfig(tolerance_px=1.0, roots=16, tess=16, spacing=spacing),
                   outputs=("error", "mesh", "patches"))
        f = render(sc, terrain=terrain)
        wt = check_watertight(f.mesh)
        assert wt.n_open_edges == 0 and wt.n_t_junctions == 0
        assert f.error.see_through_px == 0
        assert f.error.p99_px < 1.0
        assert f.mesh.n_triangles < 2 * 343 * 402 / 2  # far fewer triangles than the grid
        assert "prepare" not in [s.name for s in f.report.stages]  # the caller's terrain was used


def test_a_render_loop_without_a_terrain_prepares_once_and_selects_as_a_prepared_one():
    """The heightmap holds the Terrain of a layout from the first frame that prepares it: the later frames of a
    plain loop run no prepare stage, select with that same Terrain (its one-launch walk and normal map kept), and
    make the frames a caller-held Terrain makes."""
    hm = Heightmap.fbm(65, seed=9, dx=15.0, max_height=300.0)
    sc = Scene(hm, camera=Camera.default_for(hm, 96, 64), mesh="lod", lod=LodConfig(roots=4, tess=8),
               outputs=("depth", "patches"))
    cams = sc.camera_path(3)
    frames = [render(sc.with_(camera=c)) for c in cams]
    assert [("prepare" in [s.name for s in f.report.stages]) for f in frames] == [True, False, False]
    (held,) = hm.held[("terrains", "cpu")].values()
    mine = Terrain.prepare(hm, roots=4, tess=8)
    for f, c in zip(frames, cams, strict=True):
        ref = render(sc.with_(camera=c), terrain=mine)
        assert digest(f.depth, f.patches.key) == digest(ref.depth, ref.patches.key)
    assert hm.held[("terrains", "cpu")][(4, 8)] is held  # the same Terrain every frame
    render(sc.with_(lod=LodConfig(roots=4, tess=16)))  # another layout: held beside it
    assert set(hm.held[("terrains", "cpu")]) == {(4, 8), (4, 16)}


def test_lod_config_with_policy():
    base = LodConfig(roots=4, tess=8, spacing="fractional_even")
    s = base.with_policy("sse", 2.5)
    assert s.tolerance_px == 2.5 and s.spacing == "fractional_even"
    assert base.with_policy("distance", 3).k == 3.0
    c = base.with_policy("continuous", 6.0)
    assert (c.policy, c.target_px, c.spacing) == ("continuous", 6.0, "fractional_odd")
    assert c.with_policy("sse", 1.0).spacing == "equal"  # fractional_odd cannot stitch a quadtree
    with pytest.raises(ValueError, match="policy"):
        base.with_policy("bogus", 1.0)


def test_render_draws_prebuilt_mesh_sources():
    """Peers, polytree levels and bintree selections are frames of ``render`` too: their mesh is drawn by the
    same rasterizer, shaded and measured by the same stages, and their cost is the same frame_ms."""
    hm = Heightmap.fbm(33, seed=4, dx=10.0, max_height=120.0)
    cam = Camera.default_for(hm, 64, 48)
    sc = Scene(hm, camera=cam, outputs=("image", "depth", "error"))
    cache: dict = {}
    sources = [PeerSource(delatin_mesh(hm, 1.0), hm, cache=cache),
               PolytreeSource(build_polytree(hm, default_tolerances(hm, 8)), 2, cache=cache),
               BintreeSource(Bintree.build(hm, 11), cache=cache)]
    for src in sources:
        f = render(sc, source=src)
        names = [s.name for s in f.report.stages]
        assert names == ["normal_map", "select", "mesh", "raster", "shade", "reference", "error"], names
        assert f.report.info["mesh_policy"] == "source" and f.patches is None
        r = f.report
        assert r.frame_ms == r.stage_ms("select") + r.stage_ms("mesh") + r.stage_ms("raster")
        if not isinstance(src, BintreeSource):
            assert r.stage_ms("select") == 0.0  # static meshes: no selection
        m, _ = src.mesh_for(cam)
        ref = rasterize(m.positions, m.triangles, cam.view_matrix(relative=True), cam.proj_matrix(), 64, 48)
        assert np.array_equal(f.triangle_id, ref.triangle_id) and np.array_equal(f.depth, ref.depth)
        assert f.image.shape == (48, 64, 3) and np.isfinite(f.error.max_px) and f.error.see_through_px == 0
        assert r.stage("mesh").counters["triangles"] == m.n_triangles
    assert ("normal_map", "cpu") in cache  # made once, shared by the sources
    assert [s.name for s in render(sc, source=sources[0]).report.stages][:1] == ["normal_map"]
    assert render(sc, source=sources[0]).report.stage("normal_map").counters == {"cached": True}
    with pytest.raises(TypeError, match="source"):
        render(sc, source=object())
    assert stages_for(("depth",), "source") == ["select", "mesh", "raster"]


def test_frame_error_is_the_primary_error_with_the_image_error_beside_it():
    """Frame.error.p99_px is the error at the heightmap's samples (terrainwarp.measure.sample_error against the
    grid frame's depth); the per-pixel grid-image error is kept as image_err_* fields."""
    from terrainwarp.measure.error import frame_error
    from terrainwarp.measure.sample_error import sample_error

    hm = Heightmap.fbm(65, seed=6, dx=5.0, max_height=150.0)
    cam = Camera.default_for(hm, 96, 72)
    sc = Scene(hm, camera=cam, mesh="lod", lod=LodConfig(tolerance_px=4.0, roots=4, tess=4), outputs=("error",))
    f = render(sc)
    ref = render(sc.with_(mesh="grid", outputs=("depth",)))
    s = sample_error(hm, cam, f.mesh, ref.depth)
    assert (f.error.p99_px, f.error.max_px, f.error.mean_px) == (s.p99_px, s.max_px, s.mean_px)
    assert f.error.samples_visible == s.visible > 0 and f.error.samples_hidden == s.hidden
    i = frame_error(hm, cam, f.mesh.positions, f.mesh.eye, f.mesh.triangles, f.triangle_id, f.barycentrics,
                    f.depth, ref.triangle_id, ref.depth)
    assert (f.error.image_err_p99_px, f.error.image_err_max_px, f.error.see_through_px) == \
        (i.p99_px, i.max_px, i.see_through_px)
    row = f.error.row()
    assert {"p99_px", "image_err_p99_px", "image_err_max_px", "see_through_px", "psnr_db"} <= set(row)
    assert f.report.stage("error").counters["image_err_p99_px"] == round(i.p99_px, 4)


def test_render_draws_a_held_selection_for_another_camera():
    """render(scene, terrain, patches=held) skips select and tessellates the held PatchList for scene.camera:
    the frame popping measures."""
    hm = Heightmap.fbm(65, seed=6, dx=5.0, max_height=150.0)
    sc = Scene(hm, camera=Camera.default_for(hm, 64, 48), mesh="lod", lod=LodConfig(tolerance_px=2.0, roots=4,
               tess=4), outputs=("mesh", "patches"))
    cams = sc.camera_path(3)
    terrain = Terrain.prepare(hm, roots=4, tess=4)
    f0 = render(sc.with_(camera=cams[0]), terrain)
    f1 = render(sc.with_(camera=cams[1]), terrain)
    held = render(sc.with_(camera=cams[1]), terrain, patches=f0.patches)
    assert [s.name for s in held.report.stages] == ["mesh"] and held.patches is f0.patches
    assert held.mesh.eye == cams[1].position and held.mesh.n_triangles == f0.mesh.n_triangles
    same = render(sc.with_(camera=cams[1]), terrain, patches=f1.patches)  # its own selection: the same frame
    assert np.array_equal(same.mesh.positions, f1.mesh.positions)
    assert np.array_equal(same.mesh.triangles, f1.mesh.triangles)
    assert stages_for(("error",), "lod", have_patches=True) == ["mesh", "raster", "reference", "error"]
    with pytest.raises(ValueError, match="^patches: "):
        render(sc.with_(mesh="grid"), patches=f0.patches)
    with pytest.raises(TypeError, match="^patches: expected a PatchList"):
        render(sc, terrain, patches=[1, 2])


def test_pop_stats_is_zero_for_a_static_camera_and_measured_when_the_selection_changes():
    hm = Heightmap.example()
    base = Scene(hm, camera=Camera.default_for(hm, 96, 72), mesh="lod", lod=LodConfig(tolerance_px=2.0),
                 outputs=("error",))
    cams = base.camera_path(3)
    terrain = Terrain.prepare(hm, roots=16, tess=16)
    sc = base.with_(camera=cams[2])
    ref = render(sc.with_(mesh="grid", outputs=("depth",)))
    f = render(sc, terrain, reference=ref)
    still = pop_stats(sc, cams[2], f, ref, terrain=terrain)
    assert (still.p99_px, still.max_px, still.popped) == (0.0, 0.0, 0) and still.visible > 0
    moved = pop_stats(sc, cams[0], f, ref, terrain=terrain)  # a long jump: the selection changes
    assert moved.max_px > 0.5 and moved.popped > 0
    held = render(base.with_(camera=cams[0], outputs=("patches",)), terrain).patches
    assert pop_stats(sc, cams[0], f, ref, terrain=terrain, held=held) == moved
    grid = render(sc.with_(mesh="grid"), reference=ref)
    assert pop_stats(sc.with_(mesh="grid"), cams[0], grid, ref).max_px == 0.0
    src = PeerSource(delatin_mesh(hm, 5.0), hm)
    fs = render(sc, source=src, reference=ref)
    assert pop_stats(sc, cams[0], fs, ref, source=src).popped == 0  # a static mesh does not pop


@pytest.mark.parametrize("name", ["cdlod", "clipmaps", "chunked"])
def test_pop_stats_of_a_scheme_source_holds_its_selection_and_draws_it_with_the_current_camera(name):
    """A scheme's held mesh is its previous selection drawn by the current camera's vertex stage: a static
    camera pops 0, and so does a small move that keeps the selection (CDLOD's morph, the clipmaps' blend
    follow the camera every frame; that is not a pop)."""
    hm = Heightmap.fbm(65, seed=3, dx=10.0, max_height=200.0)
    (x0, z0), (x1, z1) = hm.bounds_xz
    cams = flyover(hm, [(x0 + 0.2 * (x1 - x0), z0 + 0.3 * (z1 - z0)), (x0 + 0.8 * (x1 - x0), z0 + 0.7 * (z1 - z0))],
                   0.05 * (x1 - x0), 200, width=64, height=48)
    value = {"cdlod": 4 * Cdlod(hm, 1.0, grid=8).min_first_range, "clipmaps": 31, "chunked": 2.0}[name]
    params = {"cdlod": {"grid": 8}, "clipmaps": {}, "chunked": {"tile": 8}}[name]
    src = scheme_source(name, hm, value, **params)
    sc = Scene(hm, camera=cams[1], outputs=("depth", "mesh"))
    ref = render(sc.with_(outputs=("depth",)))
    f = render(sc, source=src)
    still = pop_stats(sc, cams[1], f, ref, source=src)
    assert (still.p99_px, still.max_px, still.popped) == (0.0, 0.0, 0) and still.visible > 0
    assert pop_stats(sc, cams[0], f, ref, source=src).max_px == 0.0  # a small move: the selection is kept
    if name != "chunked":  # drawn with the previous camera's morph / blend it would count as a pop
        assert popping(hm, cams[1], src.mesh_for(cams[0])[0], f.mesh, ref.depth).max_px > 0.0

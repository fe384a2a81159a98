"""Camera paths in and out: a recorded CSV path (time, position, target or yaw/pitch/roll, fov) read into cameras,
bad files refused naming the row and the column; explicit cameras saved in a scene file and read back exactly; the
scene's viewport and budget tables; the generated flyover never looks off the terrain."""

import math

import numpy as np
import pytest

from terrainwarp import Camera, Heightmap, Scene, render
from terrainwarp.camera import Viewport, camera_from_angles, flyover, read_camera_csv
from terrainwarp.scene import Budget, CameraPath


@pytest.fixture(scope="module")
def hm():
    return Heightmap.fbm(65, seed=3, dx=10.0, max_height=300.0)


def _write(tmp_path, text, name="flight.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_a_recorded_path_with_targets_loads_camera_by_camera(tmp_path):
    p = _write(tmp_path, "time_s,x,y,z,target_x,target_y,target_z,fov_y_deg,width,height\n"
                         "0.0,10,400,600,320,0,320,50,320,180\n"
                         "0.5,20,410,590,320,0,320,55,320,180\n"
                         "# a comment line\n\n"
                         "1.0,30,420,580,330,0,310,60,320,180\n")
    path = CameraPath.load(p)
    assert path.kind == "cameras" and path.n == 3 and path.times == (0.0, 0.5, 1.0) and path.file == str(p.resolve())
    c = path.cameras[1]
    assert c.position == (20.0, 410.0, 590.0) and c.target == (320.0, 0.0, 320.0)
    assert (c.fov_y_deg, c.width, c.height) == (55.0, 320, 180)
    cams, times = read_camera_csv(p)
    assert cams == list(path.cameras) and times == [0.0, 0.5, 1.0]


def test_yaw_pitch_roll_follow_the_stated_conventions(tmp_path):
    # heading 0 looks north (-z), 90 east (+x); pitch -90 straight down; roll 90 turns the up vector to the right
    north = camera_from_angles((0, 100, 0), 0.0, 0.0)
    east = camera_from_angles((0, 100, 0), 90.0, -30.0)
    np.testing.assert_allclose(north.forward, [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(east.forward, [math.cos(math.radians(30)), -0.5, 0], atol=1e-12)
    down = camera_from_angles((0, 100, 0), 0.0, -90.0)
    np.testing.assert_allclose(down.forward, [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(down.up, [0, 0, -1], atol=1e-12)  # the top of the image toward the heading
    banked = camera_from_angles((0, 100, 0), 0.0, 0.0, 90.0)
    np.testing.assert_allclose(banked.up, [1, 0, 0], atol=1e-12)  # right of a north heading is east
    p = _write(tmp_path, "t,pos_x,pos_y,pos_z,heading,pitch,roll\n0,0,100,0,90,-30,0\n")
    (cam,), _ = read_camera_csv(p)
    np.testing.assert_allclose(cam.forward, east.forward, atol=1e-12)


@pytest.mark.parametrize(("text", "match"), [
    ("x,y,z,yaw_deg,pitch_deg\n1,2,3,0,-10\n1,2,abc,0,-10\n", r"row 2 \(line 3\), column 'z': expected a number, "
                                                                r"got 'abc'"),
    ("x,y,z,yaw_deg,pitch_deg\n1,2,3,0,\n", r"row 1 \(line 2\), column 'pitch_deg': expected a number, got an empty"),
    ("x,y,z,yaw_deg,pitch_deg\n1,2,3,0,nan\n", r"row 1 \(line 2\), column 'pitch_deg': expected a finite number"),
    ("x,y,yaw_deg,pitch_deg\n1,2,0,-10\n", r"missing column 'z'"),
    ("x,y,z,fov_y_deg\n1,2,3,60\n", r"expected either the columns target_x, target_y, target_z or the columns "
                                    r"yaw_deg, pitch_deg"),
    ("x,y,z,target_x,target_y\n1,2,3,4,5\n", r"expected either the columns target_x"),
    ("x,y,z,yaw_deg,pitch_deg,speed\n1,2,3,0,0,9\n", r"column 6 'speed': unknown"),
    ("x,y,z,x,yaw_deg,pitch_deg\n1,2,3,1,0,0\n", r"column 4 'x': 'x' is given twice"),
    ("x,y,z,yaw_deg,pitch_deg\n1,2,3,0,-10,7\n", r"row 1 \(line 2\): expected 5 fields, got 6"),
    ("time_s,x,y,z,yaw_deg,pitch_deg\n0,1,2,3,0,0\n0,1,2,3,0,0\n", r"row 2 \(line 3\), column 'time_s': expected a "
                                                                   r"time after"),
    ("x,y,z,target_x,target_y,target_z\n1,2,3,1,2,3\n", r"row 1 \(line 2\), column 'target_x': must differ"),
    ("x,y,z,yaw_deg,pitch_deg,fov_y_deg\n1,2,3,0,0,200\n", r"row 1 \(line 2\), column 'fov_y_deg': expected a value "
                                                           r"in \(0, 180\)"),
    ("x,y,z,yaw_deg,pitch_deg,width\n1,2,3,0,0,12.5\n", r"row 1 \(line 2\), column 'width'"),
    ("x,y,z,yaw_deg,pitch_deg\n", r"no cameras"),
    ("", r"empty file"),
])
def test_a_bad_file_is_refused_naming_the_row_and_the_column(tmp_path, text, match):
    p = _write(tmp_path, text)
    with pytest.raises(ValueError, match=match):
        CameraPath.load(p)


def test_a_missing_file_is_refused(tmp_path):
    with pytest.raises(ValueError, match="no such camera-path file"):
        CameraPath.load(tmp_path / "nope.csv")


def test_explicit_cameras_save_and_load_back_exactly(hm, tmp_path):
    sc = Scene(hm, camera=Camera.default_for(hm, 96, 64))
    cams = [c.with_(width=80, height=60) for c in sc.camera_path(3)]
    saved = sc.with_(path=CameraPath.of(cams, [0.0, 1.5, 2.0]), viewport=Viewport(80, 60, 60.0),
                     budget=Budget(1.5, max_pop_px=2.0))
    back = Scene.load(saved.save(tmp_path / "s.toml"))
    assert back.camera_path() == cams and back.path.times == (0.0, 1.5, 2.0)
    assert back.viewport == (80, 60, 60.0) and back.budget == Budget(1.5, 2.0, "triangles")
    assert back.pixel_viewport == back.viewport and back.path_viewport == (80, 60, 60.0)
    assert back.camera_path(2) == [cams[0], cams[2]]  # n evenly spaced along the list
    with pytest.raises(ValueError, match="n: expected"):
        back.camera_path(4)
    assert "3 recorded cameras at 80x60, 60 degree fov" in back.path_info()["text"]
    a = render(back.with_(camera=back.camera_path()[1], outputs=("depth",))).depth
    b = render(sc.with_(camera=cams[1], outputs=("depth",))).depth
    assert np.array_equal(a, b)


def test_a_scene_file_names_a_recorded_path(hm, tmp_path):
    _write(tmp_path, "x,y,z,yaw_deg,pitch_deg\n300,500,600,0,-30\n320,500,560,10,-35\n")
    Scene(hm, camera=Camera.default_for(hm, 64, 48)).save(tmp_path / "base.toml")
    text = (tmp_path / "base.toml").read_text()
    head, _, _ = text.partition("[path]")
    (tmp_path / "rec.toml").write_text(head + '[path]\nkind = "cameras"\nfile = "flight.csv"\nfov_y_deg = 50\n')
    sc = Scene.load(tmp_path / "rec.toml")
    cams = sc.camera_path()
    assert len(cams) == 2 and (cams[0].width, cams[0].height, cams[0].fov_y_deg) == (64, 48, 50.0)
    assert sc.path.file == str((tmp_path / "flight.csv").resolve())
    back = Scene.load(sc.save(tmp_path / "again.toml"))  # names the file again (absolute)
    assert back.camera_path() == cams
    for bad, match in (({"kind": "cameras"}, "either file"), ({"kind": "cameras", "file": "x.csv", "n": 3},
                                                             "no such camera-path file"),
                       ({"kind": "cameras", "file": "flight.csv", "n": 3}, "path.n: the path has 2 cameras"),
                       ({"kind": "cameras", "file": "flight.csv", "clearance": 3.0}, "path.clearance: does not apply"),
                       ({"kind": "flyover", "file": "flight.csv"}, "path.file: does not apply")):
        with pytest.raises(ValueError, match=match):
            Scene.from_dict({"heightmap": {"fbm": {"rows": 17}}, "path": bad}, base_dir=tmp_path)


def test_viewport_and_budget_tables_are_checked(hm):
    base = {"heightmap": {"fbm": {"rows": 17}}}
    for table, match in (({"viewport": {"width": 960, "height": 540}}, "expected the keys width, height and "
                                                                       "fov_y_deg"),
                         ({"viewport": {"width": 960, "height": 0, "fov_y_deg": 60}}, "height: expected 1..16384"),
                         ({"viewport": {"width": 960, "height": 540, "fov_y_deg": 180}}, "fov_y_deg: expected"),
                         ({"budget": {"budget_px": 0}}, "budget.budget_px"),
                         ({"budget": {"budget_px": 1, "max_pop_px": -1}}, "budget.max_pop_px")):
        with pytest.raises(ValueError, match=match):
            Scene.from_dict({**base, **table})
    vp = Viewport.of(1920, 1080, 60.0)
    assert vp.focal_px == pytest.approx(1080 / (2 * math.tan(math.radians(30))))
    assert vp.to_pixels(vp.to_radians(3.0)) == pytest.approx(3.0)


def test_the_generated_flyover_looks_at_the_terrain_from_every_camera(hm):
    """The default path's last camera stood at the path's end looking past the terrain's corner (2,520 visible
    samples of 138,000 on the bundled DEM); every camera's look-ahead point now lies over the terrain."""
    (x0, z0), (x1, z1) = hm.bounds_xz
    for n in (2, 5, 8):
        for c in Scene(hm).camera_path(n):
            assert x0 <= c.target[0] <= x1 and z0 <= c.target[2] <= z1, c


def test_a_flyover_over_a_no_data_hole_takes_the_ground_between_its_rims():
    """A 17 x 17-sample hole (columns and rows 24..40) under a path along row 32: the cameras over it (and beside
    it, where the bilinear footprint touches it) stand ``clearance`` above the ground interpolated along the path
    between the last finite ground before it (x = 220 m) and the first after it (x = 410 m); the others as
    before; a target over the hole is a quarter clearance below its eye; a path wholly over the hole stands on the
    ring of finite ground around it."""
    h = Heightmap.fbm(65, seed=3, dx=10.0, max_height=300.0).heights.copy()
    h[24:41, 24:41] = np.nan
    holed = Heightmap.from_array(h, dx=10.0, dz=10.0, allow_nan=True)
    cams = flyover(holed, [(20.0, 320.0), (620.0, 320.0)], 25.0, 13, look_ahead=60.0)
    xs = np.array([c.position[0] for c in cams])
    assert xs.tolist() == [20.0 + 50.0 * k for k in range(13)]
    over = (xs > 220.0) & (xs < 410.0)
    assert over.sum() == 3  # x = 270, 320, 370
    ys = np.array([c.position[1] for c in cams])
    assert ys[over] - 25.0 == pytest.approx(np.interp(xs[over], [220.0, 410.0], [h[32, 22], h[32, 41]]), abs=1e-4)
    assert np.array_equal(ys[~over], holed.sample(xs[~over], np.full((~over).sum(), 320.0)).astype(np.float64) + 25.0)
    for c in cams:
        assert all(math.isfinite(v) for v in (*c.position, *c.target))
        if not math.isfinite(float(holed.sample([c.target[0]], [c.target[2]])[0])):
            assert c.target[1] == pytest.approx(c.position[1] - 0.25 * 25.0)
    inside = flyover(holed, [(300.0, 300.0), (340.0, 340.0)], 25.0, 3)
    lo, hi = holed.height_range
    for c in inside:
        assert lo <= c.position[1] - 25.0 <= hi and all(math.isfinite(v) for v in (*c.position, *c.target))

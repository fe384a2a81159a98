import math

import numpy as np
import pytest

from terrainwarp import Camera, Heightmap
from terrainwarp.camera import flyover, orbit


def test_view_matrix_hand_computed():
    # Eye at (0, 0, 5) looking at the origin: the view is a pure translation by -5 along z.
    c = Camera(position=(0, 0, 5), target=(0, 0, 0))
    np.testing.assert_allclose(c.view_matrix(), [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, -5], [0, 0, 0, 1]],
                               atol=1e-15)
    # Eye at (3, 0, 0) looking at the origin: +x of the eye is world -z... s = f x up = (-1,0,0)x(0,1,0) = (0,0,-1)
    c2 = Camera(position=(3, 0, 0), target=(0, 0, 0))
    v = c2.view_matrix()
    np.testing.assert_allclose(v[:3, :3], [[0, 0, -1], [0, 1, 0], [1, 0, 0]], atol=1e-15)
    np.testing.assert_allclose(v @ [3, 0, 0, 1], [0, 0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(v @ [0, 0, 0, 1], [0, 0, -3, 1], atol=1e-12)  # target is in front (-z)


def test_projection_matrix_hand_computed():
    c = Camera(position=(0, 0, 5), target=(0, 0, 0), fov_y_deg=90.0, width=200, height=100, near=1.0, far=3.0)
    p = c.proj_matrix()
    expect = np.array([[0.5, 0, 0, 0], [0, 1, 0, 0], [0, 0, -2.0, -3.0], [0, 0, -1, 0]])
    np.testing.assert_allclose(p, expect, atol=1e-15)
    # near plane maps to ndc z = -1 (window depth 0), far to +1 (window depth 1)
    for d, zn in ((1.0, -1.0), (3.0, 1.0)):
        clip = p @ [0, 0, -d, 1]
        assert clip[2] / clip[3] == pytest.approx(zn)
    assert c.focal_px == pytest.approx(50.0)


def test_relative_view_matrix_drops_translation():
    c = Camera(position=(1e7, 500.0, -3e6), target=(1e7 + 100, 0.0, -3e6 + 50))
    v, vr = c.view_matrix(), c.view_matrix(relative=True)
    np.testing.assert_array_equal(v[:3, :3], vr[:3, :3])
    np.testing.assert_array_equal(vr[:3, 3], 0.0)
    p = np.array([1e7 + 10.0, 20.0, -3e6 + 30.0])
    np.testing.assert_allclose(vr[:3, :3] @ (p - c.position), (v @ [*p, 1])[:3], atol=1e-6)


@pytest.mark.parametrize("kw,word", [
    ({"position": (np.nan, 0, 0)}, "position"),
    ({"target": (0, 0, np.inf)}, "target"),
    ({"fov_y_deg": 0.0}, "fov_y_deg"),
    ({"fov_y_deg": 180.0}, "fov_y_deg"),
    ({"fov_y_deg": float("nan")}, "fov_y_deg"),
    ({"width": 0}, "width"),
    ({"height": 2.5}, "height"),
    ({"near": 0.0}, "near"),
    ({"far": 0.5}, "far"),
    ({"target": (0, 0, 5)}, "target"),
    ({"up": (0, 0, 1)}, "up"),
    ({"position": (1, 2)}, "position"),
])
def test_bad_cameras(kw, word):
    base = {"position": (0, 0, 5), "target": (0, 0, 0), "near": 1.0, "far": 10.0}
    base.update(kw)
    if "up" in kw:
        base["target"] = (0, 0, 0)
        base["position"] = (0, 0, 5)
    with pytest.raises((ValueError, TypeError), match=word):
        Camera(**base)


def test_orbit_path():
    cams = orbit((10, 0, 20), radius=100.0, elevation=50.0, n=8)
    assert len(cams) == 8
    for c in cams:
        d = np.subtract(c.position, (10, 0, 20))
        assert math.hypot(d[0], d[2]) == pytest.approx(100.0)
        assert d[1] == pytest.approx(50.0)
        assert c.target == (10.0, 0.0, 20.0)


def test_flyover_keeps_clearance():
    hm = Heightmap.fbm(65, seed=1, dx=10.0, max_height=300.0)
    cams = flyover(hm, [(50, 50), (600, 300), (300, 600)], clearance=25.0, n=12)
    assert len(cams) == 12
    for c in cams:
        ground = float(hm.sample([c.position[0]], [c.position[2]])[0])
        assert c.position[1] == pytest.approx(ground + 25.0, abs=1e-3)
        assert c.target[1] < c.position[1]  # looks slightly down


def test_default_camera_sees_the_whole_terrain():
    hm = Heightmap.example()
    c = Camera.default_for(hm)
    (x0, z0), (x1, z1) = hm.bounds_xz
    m = c.proj_matrix() @ c.view_matrix()
    for x in (x0, x1):
        for z in (z0, z1):
            for y in hm.height_range:
                q = m @ [x, y, z, 1.0]
                assert q[3] > 0
                assert np.all(np.abs(q[:3] / q[3]) <= 1.0)


def test_default_camera_for_a_single_sample():
    c = Camera.default_for(Heightmap.from_array(np.array([[5.0]]), 2.0))
    assert c.far > c.near and np.isfinite(c.position).all()


# -- issue 43 (finding 9): a near that float32 depth cannot resolve is refused or warned about ------------------
def test_a_near_that_blanks_the_frame_is_refused_with_the_smallest_safe_value():
    import re
    import warnings

    from terrainwarp import Heightmap, Scene, render
    from terrainwarp.camera import DepthPrecisionWarning

    hm = Heightmap.example()
    cam = Camera.default_for(hm, 96, 64)
    covered = int((render(Scene(hm, camera=cam, outputs=("depth",))).depth < 1).sum())
    for near in (1e-5, 1e-4):  # a blank frame (0 pixels covered) while its error said p99 1e-6 px
        with pytest.raises(ValueError, match=r"camera.near: .* too small for float32 depth") as e:
            render(Scene(hm, camera=cam.with_(near=near), outputs=("depth",)))
    safe = float(re.search(r"use near >= ([0-9.e+-]+) m", str(e.value)).group(1))
    with warnings.catch_warnings():
        warnings.simplefilter("error", DepthPrecisionWarning)
        f = render(Scene(hm, camera=cam.with_(near=safe), outputs=("depth",)))  # neither refused nor warned
    assert int((f.depth < 1).sum()) == covered
    with pytest.warns(DepthPrecisionWarning, match=f"near >= {safe:g} m resolves it"):  # the far terrain at risk
        render(Scene(hm, camera=cam.with_(near=0.7 * safe), outputs=("depth",)))


def test_the_cli_refuses_a_blank_near_in_one_line(tmp_path):
    import subprocess
    import sys

    p = tmp_path / "near.toml"
    p.write_text('[heightmap]\nexample = "jacksboro"\n[camera]\nwidth = 48\nheight = 32\nnear = 1e-5\n')
    r = subprocess.run([sys.executable, "-m", "terrainwarp.cli", "render", str(p), "--out", str(tmp_path / "o")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.count("\n") == 1
    assert r.stderr.startswith("terrainwarp: error: camera.near: 1e-05 m is too small") and "use near >=" in r.stderr

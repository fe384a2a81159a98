"""Every key of a scene file is applied or refused, and every number is checked by type and range at the
boundary, by the one helper (terrainwarp.kernels.checks; issue 31, defect 7)."""

from __future__ import annotations

import math
import subprocess
import sys

import pytest

from terrainwarp import Camera, Heightmap, LodConfig, Scene
from terrainwarp.scene import CameraPath

FBM = {"fbm": {"rows": 17, "seed": 1}}


def test_camera_keys_without_a_position_are_applied():
    sc = Scene.from_dict({"heightmap": FBM, "camera": {"near": 2.5, "far": 9000.0, "up": [0, 0.8, 0.6],
                                                        "width": 96, "height": 64, "fov_y_deg": 50}})
    default = Camera.default_for(sc.heightmap, 96, 64, 50)
    c = sc.camera
    assert (c.near, c.far, c.up, c.width, c.height, c.fov_y_deg) == (2.5, 9000.0, (0.0, 0.8, 0.6), 96, 64, 50.0)
    assert (c.position, c.target) == (default.position, default.target)  # the default view, with what was given


@pytest.mark.parametrize(("table", "err", "match"), [
    ({"lod": {"tolerance_px": "1.0"}}, TypeError, r"lod.tolerance_px: expected a number, got '1.0'"),
    ({"lod": {"k": True}}, TypeError, r"lod.k: expected a number, got True"),
    ({"lod": {"level": 2.5}}, TypeError, r"lod.level: expected an integer, got 2.5"),
    ({"lod": {"level": -1}}, ValueError, r"lod.level: expected an integer >= 0, got -1"),
    ({"lod": {"hysteresis": math.nan}}, ValueError, r"lod.hysteresis: expected a finite number, got nan"),
    ({"lod": {"tess": 16.0}}, TypeError, r"lod.tess: expected an integer level"),
    ({"lod": {"roots": True}}, TypeError, r"lod.roots: expected an int or \(nx, nz\)"),
    ({"lod": {"spacing": 3}}, TypeError, r"lod.spacing: expected one of"),
    ({"lod": {"policy": "ssee"}}, ValueError, r"lod.policy: expected one of \['sse', 'distance', 'continuous'\]"),
    ({"heightmap": {"example": "jacksboro", "dx": math.nan}}, ValueError,
     r"heightmap.dx: applies to a 'path' heightmap only; an example takes its own spacing"),
    ({"heightmap": {"example": "jacksboro", "dx": -30}}, ValueError, r"heightmap.dx: applies to a 'path'"),
    ({"heightmap": {"fbm": {"rows": 17}, "max_height": 10}}, ValueError,
     r"heightmap.max_height: applies to a 'path' heightmap only; an fbm takes it in its own table"),
    ({"heightmap": {"fbm": {"rows": 17}, "example": "jacksboro"}}, ValueError, r"heightmap: expected one of the keys"),
    ({"heightmap": {"path": 3}}, TypeError, r"heightmap.path: expected a file path string"),
    ({"camera": {"width": "640"}}, TypeError, r"width: expected a positive integer number of pixels"),
    ({"camera": {"near": -1.0}}, ValueError, r"near: expected > 0"),
    ({"camera": {"up": [0, 0, 0]}}, ValueError, r"up: must not be parallel"),
    ({"render": {"cull_back": "yes"}}, TypeError, r"cull_back: expected true or false, got 'yes'"),
    ({"render": {"light_azimuth_deg": math.inf}}, ValueError, r"light_azimuth_deg: expected a finite number"),
    ({"render": {"outputs": ["image", "depht"]}}, ValueError, r"outputs: unknown \['depht'\]"),
    ({"path": {"kind": "spiral"}}, ValueError, r"path.kind: expected one of \['flyover', 'orbit'\]"),
    ({"path": {"n": 0}}, ValueError, r"path.n: expected an integer >= 1 and <= 100000, got 0"),
    ({"path": {"n": "8"}}, TypeError, r"path.n: expected an integer, got '8'"),
    ({"path": {"radius": 0.5}}, ValueError, r"path.radius: does not apply to kind = 'flyover'"),
    ({"path": {"kind": "orbit", "clearance": 50.0}}, ValueError, r"path.clearance: does not apply to kind = 'orbit'"),
    ({"path": {"preset": "high", "clearance": 50.0}}, ValueError, r"path.clearance: give a clearance in metres or"),
    ({"path": {"clearance": -5.0}}, ValueError, r"path.clearance: expected a finite number > 0.0, got -5.0"),
    ({"path": {"waypoints": [[0.1, 0.2]]}}, ValueError, r"path.waypoints: expected at least 2"),
    ({"path": {"waypoints": [[0.1, 0.2], [1.5, 0.2]]}}, ValueError,
     r"path.waypoints\[1\]\[0\]: expected a finite number >= 0.0 and <= 1.0, got 1.5"),
    ({"path": {"waypoints": [[300.0, 20.0], [300.0, 20.0]], "units": "m"}}, ValueError,
     r"path.waypoints: the path has zero length"),
    ({"path": {"n": 2**31}}, ValueError, r"path.n: expected an integer >= 1 and <= 100000, got 2147483648"),
    ({"render": {"outputs": 1}}, TypeError, r"render.outputs: expected a list of output names, got 1"),
    ({"path": {"preset": "low"}}, ValueError, r"path.preset: expected one of \['ground', 'high'\]"),
    ({"path": {"speed": 3}}, ValueError, r"path: unknown key\(s\) \['speed'\]"),
])
def test_every_bad_value_is_refused_naming_the_key(table, err, match):
    data = {"heightmap": FBM, **table}
    with pytest.raises(err, match=match):
        Scene.from_dict(data)


def test_the_path_is_parsed_once_into_a_typed_camera_path_and_checked_again_per_call():
    sc = Scene.from_dict({"heightmap": FBM, "path": {"kind": "orbit", "n": 3, "radius": 0.8, "units": "fraction"}})
    assert sc.path == CameraPath(kind="orbit", n=3, radius=0.8)
    assert len(sc.camera_path()) == 3 and len(sc.camera_path(5)) == 5
    with pytest.raises(TypeError, match=r"n: expected an integer, got 2.0"):
        sc.camera_path(2.0)
    with pytest.raises(ValueError, match=r"preset: expected one of"):
        sc.camera_path(preset="mid")
    with pytest.raises(TypeError, match=r"path: expected a CameraPath"):
        Scene(Heightmap.fbm(17), path=[1, 2])
    assert Scene(Heightmap.fbm(17), path={"n": 4}).path.n == 4  # a table is parsed as a scene file's


def test_lod_numbers_are_converted_to_plain_python_values():
    import numpy as np

    cfg = LodConfig(tolerance_px=np.float32(1.5), level=np.int64(2), roots=[4, 2], tess=np.int32(8))
    assert (type(cfg.tolerance_px), type(cfg.level), cfg.roots, type(cfg.tess)) == (float, int, (4, 2), int)


def test_the_command_refuses_a_string_number_in_one_line(tmp_path):
    s = tmp_path / "s.toml"
    s.write_text('[heightmap]\nfbm = { rows = 17 }\n[lod]\ntolerance_px = "1.0"\n[render]\nmesh = "lod"\n')
    r = subprocess.run([sys.executable, "-m", "terrainwarp.cli", "render", str(s), "--out", str(tmp_path / "o")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.strip() == \
        "terrainwarp: error: lod.tolerance_px: expected a number, got '1.0'"
    assert not (tmp_path / "o").exists()

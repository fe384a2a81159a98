"""Every key of a scene file is applied or refused, and every number is checked by type and range at the
boundary, by the one helper (terrainwarp.kernels.checks; issue 31, defect 7)."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
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
    ({"lod": {"policy": "ssee"}}, ValueError,
     r"lod.policy: expected one of \['sse', 'distance', 'continuous', 'cdlod', 'clipmaps', 'chunked', 'cesium'\]"),
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
    ({"path": {"kind": "spiral"}}, ValueError, r"path.kind: expected one of \['flyover', 'orbit', 'cameras'\]"),
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


def _frame_digest(sc):
    from conftest import digest

    from terrainwarp import render

    f = render(sc)
    return digest(f.image), digest(f.depth)


@pytest.mark.parametrize("lod", [
    LodConfig(tolerance_px=1.5, level_log_scale=(0.0, 0.7, -0.4), hysteresis=0.2, tess=8),
    LodConfig(policy="cdlod", params={"first_range": 900.0, "ratio": 2.5, "morph_start_ratio": 0.6, "grid": 16}),
    LodConfig(policy="clipmaps", params={"n": 31, "transition_ratio": 0.2}),
    LodConfig(policy="chunked", params={"max_sse_px": 3.0, "tile": 16}),
])
def test_a_scene_saved_to_toml_loads_back_and_renders_the_same_frame(tmp_path, lod):
    hm = Heightmap.fbm(65, seed=3, dx=15.0, max_height=400.0)
    sc = Scene(hm, camera=Camera.default_for(hm, 96, 64), mesh="lod", lod=lod, outputs=("image", "depth"),
               path=CameraPath(n=3, preset="high"), name="saved")
    back = Scene.load(sc.save(tmp_path / "saved.toml"))
    assert back.lod == sc.lod and back.path == sc.path and back.camera == sc.camera and back.outputs == sc.outputs
    assert np.array_equal(back.heightmap.heights, hm.heights) and (back.heightmap.dx, back.heightmap.dz) == (hm.dx,
                                                                                                            hm.dz)
    assert _frame_digest(back) == _frame_digest(sc)


def test_saving_names_the_heightmap_a_scene_file_cannot_name(tmp_path):
    hm = Heightmap.from_array(np.zeros((9, 9), np.float32), 5.0, name="scratch")
    with pytest.raises(ValueError, match="heightmap: 'scratch' was not read from a file"):
        Scene(hm).save(tmp_path / "x.toml")
    assert not (tmp_path / "x.toml").exists()
    np.save(tmp_path / "h.npy", np.arange(81, dtype=np.float32).reshape(9, 9))
    sc = Scene(Heightmap.load(tmp_path / "h.npy", dx=4.0), name="file")
    back = Scene.load(sc.save(tmp_path / "file.toml"))
    assert np.array_equal(back.heightmap.heights, sc.heightmap.heights) and back.heightmap.dx == 4.0
    assert Scene.from_dict(Scene(Heightmap.example()).to_dict()).heightmap.name == "jacksboro"


@pytest.mark.parametrize(("lod", "err", "match"), [
    ({"policy": "cdlod", "params": {"grid": 12}}, ValueError, r"lod.cdlod.grid: expected one of \[8, 16, 32, 64\]"),
    ({"policy": "cdlod", "params": {"bogus": 1}}, ValueError, r"lod.cdlod: expected a knob of"),
    ({"policy": "chunked", "params": {"max_sse_px": -1.0}}, ValueError, r"lod.chunked.max_sse_px"),
    ({"policy": "sse", "params": {"grid": 16}}, ValueError, r"lod.params: the quadtree policy 'sse'"),
    ({"policy": "cdlod", "params": "x"}, TypeError, r"lod.params: expected a table"),
    ({"level_log_scale": [0.0, 11.0]}, ValueError, r"lod.level_log_scale\[1\]: expected a finite number"),
    ({"level_log_scale": 1.0}, TypeError, r"lod.level_log_scale: expected a list"),
])
def test_scheme_knobs_and_level_scales_are_checked_in_the_scene_file(lod, err, match):
    with pytest.raises(err, match=match):
        Scene.from_dict({"heightmap": FBM, "lod": lod})


# ------------------------------------------------------------------------------------------------
# issue 43 (finding 2): every source kind saves to a scene file and loads back to the same heights
# ------------------------------------------------------------------------------------------------
def _sources(tmp: Path) -> dict:
    """A heightmap of every kind a scene file can name, by label, each with how it was made."""
    from terrainwarp.heightmap import StreamedHeightmap
    from terrainwarp.io.geotiff import write_tiled

    fbm = Heightmap.fbm(97, 65, seed=2, dx=12.0, max_height=300.0)
    holes = fbm.heights.copy()
    holes[10:20, 30:45] = np.nan
    tif = write_tiled(tmp / "dem.tif", fbm.shape, lambda r0, c0, a, b: holes[r0:r0 + a, c0:c0 + b], dx=12.0)
    np.save(tmp / "holes.npy", holes)
    png = tmp / "dem.png"
    Heightmap.from_array(np.round(fbm.heights).astype(np.uint16), 3.0).save(png)
    return {
        "example": lambda: Heightmap.example("topobathy"),
        "example streamed": lambda: StreamedHeightmap.of(Heightmap.example("topobathy")),
        "fbm": lambda: fbm,
        "fbm streamed": lambda: StreamedHeightmap.fbm(97, 65, seed=2, dx=12.0, max_height=300.0),
        "png scaled": lambda: Heightmap.load(png, dx=3.0, max_height=50.0),
        "npy with holes": lambda: Heightmap.load(tmp / "holes.npy", dx=2.0, allow_nan=True),
        "geotiff": lambda: Heightmap.load(tif),
        "geotiff window": lambda: Heightmap.load(tif, window=((8, 72), (4, 50))),
        "geotiff decimated": lambda: Heightmap.load(tif, decimate=3, resampling="mode"),
        "geotiff streamed": lambda: Heightmap.open(tif, dx=5.0),
        "geotiff window streamed": lambda: StreamedHeightmap.of(Heightmap.load(tif, window=((8, 72), (4, 50)))),
    }


def _grid(hm) -> np.ndarray:
    from terrainwarp.heightmap import StreamedHeightmap

    return hm.load().heights if isinstance(hm, StreamedHeightmap) else hm.heights


def test_every_source_kind_saves_and_loads_back_to_the_same_heights(tmp_path):
    for label, make in _sources(tmp_path).items():
        hm = make()
        back = Scene.load(Scene(hm, name=label).save(tmp_path / "s.toml")).heightmap
        assert type(back) is type(hm), label
        assert back.shape == hm.shape and (back.dx, back.dz) == (hm.dx, hm.dz), label
        assert np.array_equal(_grid(back), _grid(hm), equal_nan=True), label
        text = (tmp_path / "s.toml").read_text()
        # a whole raster has no window key (decimating 97 x 65 by 3 reads whole blocks: 96 x 63 of it)
        assert ("window" in text) == ("window" in label or "decimated" in label), label
        assert ("stream = true" in text) == ("streamed" in label), label


def test_designed_heightmaps_are_refused_not_saved_as_their_source(tmp_path):
    hm = Heightmap.example("topobathy").designed(height_scale=2.0)  # meta still names the example
    with pytest.raises(ValueError, match="heightmap: 'topobathy-designed' was made in memory"):
        Scene(hm).save(tmp_path / "x.toml")


def test_a_scene_file_refuses_raster_keys_that_would_not_apply(tmp_path):
    np.save(tmp_path / "h.npy", np.ones((9, 9), np.float32))
    with pytest.raises(ValueError, match=r"heightmap.window: applies to a GDAL raster"):
        Scene.from_dict({"heightmap": {"path": "h.npy", "window": [[0, 4], [0, 4]]}}, base_dir=tmp_path)
    with pytest.raises(ValueError, match=r"heightmap.decimate: applies to a 'path' heightmap only"):
        Scene.from_dict({"heightmap": {"example": "jacksboro", "decimate": 2}})

"""Every command honours every key of its scene file (issue 43, finding 5): ``lod``, ``render``, ``report`` and
``fit`` read every table, streamed scenes included; a flag that overrides a key says so; ``lod --policy`` takes
every family. One scene sets a non-default value in every key; each command's outputs show it: the effect where
the key acts on the command (the patches, the sweep's own setting, the path, the fitted policy), and the scene
it ran, written beside its outputs (``scene.toml``; report.json's ``scene_file``; fit's ``fitted.toml``).
"""

from __future__ import annotations

import csv
import io
import json
from dataclasses import fields

import pytest

from terrainwarp import LodConfig, Scene
from terrainwarp.cli import main
from terrainwarp.scene import LOD_POLICIES, SCENE_FILE
from terrainwarp.schemes import SCHEMES

EVERY_KEY = """
[heightmap]
fbm = { rows = 97, cols = 81, seed = 7, max_height = 600.0, dx = 12.0, dz = 14.0, feature_size = 128.0, octaves = 6, \
gain = 0.45, lacunarity = 2.2, ridged = true }
[camera]
position = [600.0, 1500.0, 2400.0]
target = [500.0, 300.0, 600.0]
up = [0.0, 1.0, 0.1]
width = 80
height = 60
fov_y_deg = 50.0
near = 2.0
far = 50000.0
[render]
outputs = ["image", "depth", "error", "report"]
mesh = "lod"
light_azimuth_deg = 200.0
light_elevation_deg = 30.0
cull_back = true
shading = "level"
[lod]
policy = "distance"
tolerance_px = 3.0
k = 3.0
target_px = 12.0
level = 2
hysteresis = 0.1
roots = 4
tess = 8
spacing = "fractional_even"
filter = "bicubic"
level_log_scale = [0.0, 0.3]
[path]
kind = "flyover"
n = 3
waypoints = [[100.0, 900.0], [800.0, 200.0]]
units = "m"
clearance = 40.0
fov_y_deg = 55.0
[viewport]
width = 120
height = 90
fov_y_deg = 48.0
[budget]
budget_px = 2.0
max_pop_px = 50.0
cost = "fragment_shader_invocations"
"""


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory):
    p = tmp_path_factory.mktemp("keys") / "every_key.toml"
    p.write_text(EVERY_KEY)
    return p


def test_the_scene_sets_every_key_away_from_its_default(scene_file):
    import tomllib

    tables = tomllib.loads(scene_file.read_text())
    defaults = {"lod": {f.name: f.default for f in fields(LodConfig)}}
    assert set(tables) == {t for t in SCENE_FILE if "." not in t}
    for table in ("camera", "render", "lod", "path", "viewport", "budget"):
        left = set(SCENE_FILE[table]) - set(tables[table])
        # the keys left out: a flyover cannot take an orbit's or a recorded path's, clearance excludes preset, and
        # params is a scheme's
        assert left <= {"radius", "elevation", "preset", "params", "cameras", "file"}, (table, left)
    assert all(tables["lod"][k] != v for k, v in defaults["lod"].items() if k in tables["lod"])
    assert set(tables["heightmap"]["fbm"]) == set(SCENE_FILE["heightmap.fbm"])


def _scene_keys(path) -> dict:
    return Scene.load(path).to_dict()


def test_render_reports_the_scene_it_drew(scene_file, tmp_path, capsys):
    assert main(["render", str(scene_file), "--out", str(tmp_path)]) == 0
    info = json.loads((tmp_path / "report.json").read_text())["info"]
    assert info["scene_file"] == json.loads(json.dumps(_scene_keys(scene_file)))
    assert info["outputs"] == ["image", "depth", "error", "report"] and "error" in info
    assert info["lod"]["policy"] == "distance" and info["lod"]["filter"] == "bicubic" and info["width"] == 80


def test_lod_selects_with_the_scenes_lod_table_and_says_which_flag_overrides_it(scene_file, tmp_path, capsys):
    assert main(["lod", str(scene_file), "--out", str(tmp_path / "a")]) == 0
    stats = json.loads(capsys.readouterr().out.splitlines()[0])
    assert stats["roots"] == 4 and stats["tess"] == 8
    rows = list(csv.DictReader(io.StringIO((tmp_path / "a" / "patches.csv").read_text())))
    assert {float(r["inner0"]) for r in rows} == {8.0}
    assert Scene.load(tmp_path / "a" / "scene.toml").to_dict() == _scene_keys(scene_file)
    plain = tmp_path / "plain.toml"  # the same scene without its [lod] table: other patches
    plain.write_text(EVERY_KEY.split("[lod]")[0] + "[path]" + EVERY_KEY.split("[path]")[1])
    assert main(["lod", str(plain), "--out", str(tmp_path / "b")]) == 0
    capsys.readouterr()
    assert (tmp_path / "a" / "patches.csv").read_bytes() != (tmp_path / "b" / "patches.csv").read_bytes()
    assert main(["lod", str(scene_file), "--k", "1.5", "--out", str(tmp_path / "c")]) == 0
    assert "terrainwarp: note: --k 1.5 overrides the scene's [lod] k = 3.0" in capsys.readouterr().err
    assert Scene.load(tmp_path / "c" / "scene.toml").lod.k == 1.5


@pytest.mark.parametrize("policy", [*LOD_POLICIES, *(s for s in SCHEMES if SCHEMES[s].builtin)])
def test_lod_takes_every_family(policy, tmp_path, capsys):
    assert main(["lod", "--policy", policy, "--width", "64", "--height", "48", "--out", str(tmp_path)]) == 0
    stats = json.loads(capsys.readouterr().out.splitlines()[0])
    assert stats.get("patches", stats.get("pieces")) > 0
    assert (tmp_path / "lod.png").stat().st_size > 0 and Scene.load(tmp_path / "scene.toml").lod.policy == policy


def test_report_sweeps_with_the_scenes_lod_path_and_own_setting(scene_file, tmp_path, capsys):
    assert main(["report", str(scene_file), "--quick", "--policies", "grid,distance", "--workers", "0",
                 "--no-images", "--no-progress", "--out", str(tmp_path)]) == 0
    md = (tmp_path / "report.md").read_text()
    assert "LOD: 4 roots, tess 8." in md and "3 cameras at 80x60" in md
    assert "Cost (`cost`): `fragment_shader_invocations` per frame" in md  # the scene's [budget] cost
    assert "40 m above the ground" in md and "55 degree fov" in md
    settings = {r["setting"] for r in csv.DictReader(io.StringIO((tmp_path / "frames.csv").read_text()))}
    assert "distance=3" in settings  # the scene's own setting, beside the sweep's
    assert Scene.load(tmp_path / "scene.toml").to_dict() == _scene_keys(scene_file)


def test_fit_fits_the_scenes_policy_and_keeps_every_other_key(scene_file, tmp_path, capsys):
    assert main(["fit", str(scene_file), "--no-progress", "--out", str(tmp_path)]) in (0, 1)  # [budget]'s budget
    doc = json.loads((tmp_path / "fit.json").read_text())
    assert doc["policy"] == "distance"  # it fitted sse before
    assert (doc["budget_px"], doc["max_pop_px"]) == (2.0, 50.0) and "fragment_shader_invocations" in doc["cost"]
    got, want = Scene.load(tmp_path / "fitted.toml").to_dict(), _scene_keys(scene_file)
    assert all(got[t] == want[t] for t in ("heightmap", "camera", "render", "budget"))
    assert {k: v for k, v in got["lod"].items() if k != "k"} == {k: v for k, v in want["lod"].items() if k != "k"}
    # the fitted scene records the path it was fitted on (the [path]'s 3 cameras, 55 degree fov) and its viewport
    assert got["path"]["kind"] == "cameras" and len(got["path"]["cameras"]) == 3
    assert all(c["fov_y_deg"] == 55.0 for c in got["path"]["cameras"])
    assert got["viewport"] == {"width": 80, "height": 60, "fov_y_deg": 55.0}
    capsys.readouterr()
    assert main(["fit", str(scene_file), "--policy", "sse", "--frames", "2", "--budget-px", "2", "--no-progress",
                 "--out", str(tmp_path / "o")]) in (0, 1)
    err = capsys.readouterr().err
    assert "--policy sse overrides the scene's [lod] policy = 'distance'" in err
    assert "--frames 2 overrides the scene's [path] n = 3" in err
    assert "--budget-px 2.0 overrides" not in err  # the same value: nothing overridden


def test_streamed_scenes_reach_every_command(tmp_path, capsys):
    p = tmp_path / "s.toml"
    p.write_text('[heightmap]\nfbm = { rows = 65, seed = 3 }\nstream = true\n[camera]\nwidth = 48\nheight = 32\n'
                 '[render]\nmesh = "lod"\n[lod]\ntolerance_px = 4.0\n')
    for argv in (["lod"], ["render"], ["report", "--quick", "--frames", "2", "--policies", "grid,sse", "--workers", "0",
                                       "--no-images", "--no-progress"],
                 ["fit", "--frames", "2", "--budget-px", "2", "--no-progress"]):
        assert main([argv[0], str(p), *argv[1:], "--out", str(tmp_path / argv[0])]) in (0, 1), argv[0]
    assert Scene.load(tmp_path / "fit" / "fitted.toml").heightmap.__class__.__name__ == "StreamedHeightmap"
    assert "sse=4" in (tmp_path / "report" / "frames.csv").read_text()

"""The README's scene file (issue 20, item 10): its [path] table is labelled as the default path, so it
must give the very cameras the scene gives without a [path] table (a 45 degree field of view in it once
made the same fit give 2.016 from the API and 2.44 from the CLI). The default path flies at ground level: 2% of
the extent (issue 17)."""

import re
import tomllib
from pathlib import Path

import pytest

import terrainwarp as tw
from terrainwarp.scene import GROUND_CLEARANCE, HIGH_CLEARANCE, PATH_FOV_Y_DEG, PATH_PRESETS, Scene

README = Path(__file__).resolve().parents[2] / "README.md"


def _readme_scene() -> dict:
    blocks = re.findall(r"```toml\n(.*?)```", README.read_text(), flags=re.S)
    scenes = [tomllib.loads(b) for b in blocks if "[path]" in b]
    assert len(scenes) == 1
    return scenes[0]


def test_readme_path_example_is_the_default_path():
    data = _readme_scene()
    assert data["heightmap"] == {"example": "jacksboro"}
    with_path = Scene.from_dict(data).camera_path()
    without = Scene.from_dict({k: v for k, v in data.items() if k != "path"}).camera_path()
    assert len(with_path) == 8
    assert with_path == without
    assert {c.fov_y_deg for c in with_path} == {60.0}
    assert data["path"]["preset"] == "ground"


def test_default_path_flies_at_two_percent_of_the_extent_and_high_at_ten():
    sc = Scene.from_dict({"heightmap": {"fbm": {"rows": 33, "seed": 2, "dx": 10.0}}})
    (x0, z0), (x1, z1) = sc.heightmap.bounds_xz
    ext = max(x1 - x0, z1 - z0)
    info = sc.path_info()
    assert info["preset"] == "ground" and info["clearance_fraction"] == pytest.approx(GROUND_CLEARANCE) == 0.02
    assert info["clearance_m"] == pytest.approx(0.02 * ext) and "2.0%" in info["text"]
    ground, high = sc.camera_path(3), sc.camera_path(3, preset="high")
    assert HIGH_CLEARANCE == 0.10 and PATH_PRESETS == {"ground": 0.02, "high": 0.10}
    for g, h in zip(ground, high):  # same track, 8% of the extent higher
        assert h.position[1] - g.position[1] == pytest.approx(0.08 * ext)
    in_file = Scene.from_dict({"heightmap": {"fbm": {"rows": 33, "seed": 2, "dx": 10.0}},
                               "path": {"preset": "high"}}).camera_path(3)
    assert in_file == high
    metres = Scene.from_dict({"heightmap": {"fbm": {"rows": 33, "seed": 2, "dx": 10.0}},
                              "path": {"clearance": 17.0}})
    assert metres.path_info()["preset"] == "custom" and metres.path_info()["clearance_m"] == 17.0
    assert metres.camera_path(2, preset="high") == sc.camera_path(2, preset="high")  # the option wins
    with pytest.raises(ValueError, match="^preset: expected one of"):
        sc.camera_path(preset="low")


def test_a_path_table_without_a_field_of_view_uses_sixty_degrees_like_no_table():
    data = {"heightmap": {"fbm": {"rows": 33, "seed": 2}}, "camera": {"fov_y_deg": 45.0}}
    without = Scene.from_dict(data).camera_path(2)
    with_table = Scene.from_dict({**data, "path": {"n": 2}}).camera_path()
    assert with_table == without and {c.fov_y_deg for c in with_table} == {PATH_FOV_Y_DEG} == {60.0}


def test_scene_files_bad(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[heightmap\nexample = ")
    with pytest.raises(ValueError, match="scene"):
        tw.Scene.load(bad)
    unk = tmp_path / "unk.toml"
    unk.write_text('[heightmap]\nexample = "jacksboro"\ncolour = 3\n')
    with pytest.raises(ValueError, match="heightmap: unknown key"):
        tw.Scene.load(unk)
    ex = tmp_path / "ex.toml"
    ex.write_text('[heightmap]\nexample = "atlantis"\n')
    with pytest.raises(ValueError, match="heightmap.example"):
        tw.Scene.load(ex)

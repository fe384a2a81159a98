"""The README's scene file (issue 20, item 10): its [path] table is labelled as the default path, so it
must give the very cameras the scene gives without a [path] table (a 45 degree field of view in it once
made the same fit give 2.016 from the API and 2.44 from the CLI)."""

import re
import tomllib
from pathlib import Path

from terrainwarp.scene import Scene

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

"""Bad input that used to get past the core types (issue 20): each is refused up front with one clear
ValueError naming the argument, instead of failing later inside numpy, Warp or a division."""

import numpy as np
import pytest

from terrainwarp import Camera, Heightmap, flyover, orbit
from terrainwarp.scene import Scene


# -- item 7: the constructor validates as from_array does ------------------------------------------
@pytest.mark.parametrize("h,word", [
    (np.full((3, 4), np.nan, np.float32), "every height is NaN"),
    (np.zeros((0, 5), np.float32), "non-empty"),
    (np.zeros((5, 0), np.float32), "non-empty"),
    (np.array([[1.0, np.inf], [0.0, 1.0]], np.float32), "infinite"),
])
def test_constructor_refuses_what_from_array_refuses(h, word):
    with pytest.raises(ValueError, match=f"^heights: .*{word}"):
        Heightmap(heights=h)
    with pytest.raises(ValueError, match=f"^a: .*{word}"):
        Heightmap.from_array(h, allow_nan=True)


def test_constructor_accepts_holes_and_repr_works():
    h = np.array([[1.0, np.nan], [2.0, 3.0]], np.float32)
    hm = Heightmap(heights=h, dx=2.0)
    assert repr(hm) == "Heightmap('heightmap', shape=(2, 2), dx=2, dz=1, heights=[1, 3] m)"
    assert np.array_equal(hm.heights, Heightmap.from_array(h, 2.0, 1.0, allow_nan=True).heights, equal_nan=True)


# -- item 5: a field of view of 0 (or 180, NaN, ...) is refused wherever a camera is made ----------
def _hm():
    return Heightmap.from_array(np.arange(20.0).reshape(4, 5), 10.0)


@pytest.mark.parametrize("fov", [0, 0.0, -10.0, 180.0, float("nan"), float("inf")])
def test_default_camera_refuses_a_bad_field_of_view(fov):
    with pytest.raises(ValueError, match=r"^fov_y_deg: expected a value in \(0, 180\) degrees, got|"
                                         r"^fov_y_deg: expected a finite number, got"):
        Camera.default_for(_hm(), 640, 480, fov)


@pytest.mark.parametrize("kw,msg", [
    ({"width": 0}, r"^width: expected 1\.\.16384 pixels, got 0$"),
    ({"height": 2.5}, r"^height: expected a positive integer number of pixels, got 2\.5$"),
    ({"fov_y_deg": "wide"}, r"^fov_y_deg: expected a number, got 'wide'$"),
])
def test_default_camera_names_the_bad_argument(kw, msg):
    with pytest.raises((ValueError, TypeError), match=msg):
        Camera.default_for(_hm(), **kw)


def test_scene_file_fov_zero_without_a_position(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text('[heightmap]\nfbm = { rows = 17, seed = 1 }\n[camera]\nfov_y_deg = 0\n')
    with pytest.raises(ValueError, match=r"^fov_y_deg: expected a value in \(0, 180\) degrees, got 0$"):
        Scene.load(p)
    p.write_text('[heightmap]\nfbm = { rows = 17, seed = 1 }\n[camera]\nposition = [0, 500, 400]\n'
                 'target = [80, 0, 80]\nfov_y_deg = 0\n')
    with pytest.raises(ValueError, match=r"^fov_y_deg: expected a value in \(0, 180\)"):
        Scene.load(p)
    sc = Scene.from_dict({"heightmap": {"fbm": {"rows": 17}}, "path": {"fov_y_deg": 0}})
    with pytest.raises(ValueError, match=r"^fov_y_deg: expected a value in \(0, 180\)"):
        sc.camera_path()


def test_camera_paths_refuse_a_bad_field_of_view():
    with pytest.raises(ValueError, match="^fov_y_deg: "):
        orbit((0, 0, 0), 100.0, 50.0, 4, fov_y_deg=0.0)
    with pytest.raises(ValueError, match="^fov_y_deg: "):
        flyover(_hm(), [(0, 0), (40, 30)], 5.0, 3, fov_y_deg=180.0)

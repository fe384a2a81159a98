"""Bad input that used to get past the core types (issue 20): each is refused up front with one clear
ValueError naming the argument, instead of failing later inside numpy, Warp or a division."""

import numpy as np
import pytest

from terrainwarp import Heightmap


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

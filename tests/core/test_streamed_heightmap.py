"""StreamedHeightmap: a Heightmap's interface over tiles, bit for bit the in-memory answers."""

from __future__ import annotations

import numpy as np
import pytest

from terrainwarp import Heightmap, Scene
from terrainwarp.heightmap import StreamedHeightmap


def test_sampling_and_loading_match_the_in_memory_heightmap():
    hm = Heightmap.from_array(Heightmap.fbm(700, 900, seed=4).heights, 7.3, 3.1, origin=(1e5, -2e3))
    st = StreamedHeightmap.of(hm)
    rng = np.random.default_rng(0)
    x = rng.uniform(1e5 - 100, 1e5 + 7.3 * 900 + 100, 50000)  # some outside: clamped as in memory
    z = rng.uniform(-2e3 - 50, -2e3 + 3.1 * 700 + 50, 50000)
    assert np.array_equal(hm.sample(x, z), st.sample(x, z))
    assert st.sample(x[:6].reshape(2, 3), z[:6].reshape(2, 3)).shape == (2, 3)
    assert np.array_equal(st.load().heights, hm.heights)
    assert st.bounds_xz == hm.bounds_xz and st.height_range == hm.height_range
    assert "StreamedHeightmap('array'" in repr(StreamedHeightmap.of(Heightmap.from_array(np.ones((3, 3)))))


def test_streamed_fbm_is_heightmap_fbm():
    st = StreamedHeightmap.fbm(513, 257, seed=9, max_height=300.0, dx=2.0)
    hm = Heightmap.fbm(513, 257, seed=9, max_height=300.0, dx=2.0)
    assert np.array_equal(st.load().heights, hm.heights) and (st.dx, st.dz) == (hm.dx, hm.dz)
    lo, hi = st.height_range  # of an overview, widened by what it can miss
    assert lo <= hm.height_range[0] and hi >= hm.height_range[1] and hi - lo < 1.5 * np.ptp(hm.height_range)
    assert Scene(st).camera.position == Scene(st).camera.position  # defaults work without the grid


def test_open_refuses_missing_and_unreadable_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="path: no such file"):
        Heightmap.open(tmp_path / "nope.tif")
    bad = tmp_path / "bad.tif"
    bad.write_bytes(b"not a tiff at all" * 10)
    with pytest.raises(ValueError, match="path: cannot read"):
        Heightmap.open(bad)
    with pytest.raises(TypeError, match="heightmap: expected a Heightmap"):
        StreamedHeightmap.of(np.zeros((3, 3), np.float32))


def test_scene_files_stream_with_stream_true(tmp_path):
    sc = Scene.from_dict({"heightmap": {"fbm": {"rows": 513, "seed": 2}, "stream": True}})
    assert isinstance(sc.heightmap, StreamedHeightmap)
    assert np.array_equal(sc.heightmap.load().heights, Heightmap.fbm(513, seed=2).heights)
    assert isinstance(Scene.from_dict({"heightmap": {"example": "jacksboro", "stream": True}}).heightmap,
                      StreamedHeightmap)
    with pytest.raises(TypeError, match="heightmap.stream: expected true or false"):
        Scene.from_dict({"heightmap": {"example": "jacksboro", "stream": "yes"}})
    p = tmp_path / "h.tif"
    Heightmap.example().save(p)
    with pytest.raises(ValueError, match="heightmap.max_height"):
        Scene.from_dict({"heightmap": {"path": str(p), "stream": True, "max_height": 10.0}})
    sc = Scene.from_dict({"heightmap": {"path": str(p), "stream": True}})
    assert isinstance(sc.heightmap, StreamedHeightmap) and sc.heightmap.shape == Heightmap.load(p).shape


def test_fits_and_sweeps_refuse_a_streamed_heightmap():
    from terrainwarp import fit_lod
    from terrainwarp.experiments.pareto import sweep

    sc = Scene(StreamedHeightmap.fbm(257), mesh="lod")
    with pytest.raises(ValueError, match="scene.heightmap: fit_lod"):
        fit_lod(sc, 1.0, cameras=[sc.camera])
    with pytest.raises(ValueError, match="scene.heightmap: a sweep"):
        sweep(sc, [sc.camera], [])

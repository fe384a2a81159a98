"""Line and hatch shading (terrainwarp/strokes.py, curtis2004 "Utilizing curvature")."""

import numpy as np
import pytest
from analytic_surfaces import cylinder_ridge, grid
from conftest import digest

from terrainwarp import Heightmap
from terrainwarp.surface.strokes import Strokes, hatch_strokes, line_strokes


def ridge_map(dx=1.0, dz=1.0, along="x", n=33):
    """A sharp ridge: a tent along x (or z) through the middle of the grid."""
    c = (n - 1) / 2
    i, j = np.mgrid[0:n, 0:n].astype(np.float64)
    d = np.abs(i - c) if along == "x" else np.abs(j - c)
    return Heightmap.from_array((10.0 - d).astype(np.float32), dx, dz)


def test_line_follows_ridge_along_x():
    hm = ridge_map(along="x")
    s = line_strokes(hm, method="three_vertex", threshold=0.5, min_length=5)
    assert isinstance(s, Strokes) and s.kind == "line" and len(s) > 0
    seg = s.segments
    # every segment lies on the crest row (z = 16), runs along x, one sample long
    assert np.all(seg[:, :, 2] == 16.0)
    assert np.allclose(np.abs(seg[:, 1, 0] - seg[:, 0, 0]), 1.0)
    assert np.all(seg[:, :, 1] == 10.0) and np.all(s.alpha == 1.0)
    # the crest minus the two ends where no stencil fits the diagonal... all 33 vertices link: one path
    assert s.n_paths == 1 and len(s) == 32


def test_line_follows_ridge_along_z_with_spacing():
    hm = ridge_map(dx=2.0, dz=0.5, along="z")
    s = line_strokes(hm, method="three_vertex", threshold=0.1, min_length=5)
    seg = s.segments
    assert len(s) == 32 and np.all(seg[:, :, 0] == 32.0)  # column 16 at dx = 2
    assert np.allclose(np.abs(seg[:, 1, 2] - seg[:, 0, 2]), 0.5)


def test_min_length_and_threshold():
    # a short crest of 4 samples: kept with min_length 4, dropped with 5
    h = np.zeros((11, 11), np.float32)
    h[5, 3:7] = 1.0
    hm = Heightmap.from_array(h)
    k = line_strokes(hm, method="three_vertex", threshold=1.0, min_length=4)
    assert k.n_paths == 1 and len(k) == 3
    assert len(line_strokes(hm, method="three_vertex", threshold=1.0, min_length=5)) == 0
    assert len(line_strokes(hm, method="three_vertex", threshold=10.0, min_length=2)) == 0
    with pytest.raises(ValueError, match="min_length"):
        line_strokes(hm, min_length=1)
    with pytest.raises(ValueError, match="threshold"):
        line_strokes(hm, threshold=float("nan"))


def test_two_paths_counted_and_alpha_from_curvature():
    # crests of 1.0 and 0.6 m: |y''| = 2 and 1.2 on the crests, 1 and 0.6 on their feet
    h = np.zeros((21, 21), np.float32)
    h[5, 2:19] = 1.0
    h[15, 2:19] = 0.6
    hm = Heightmap.from_array(h)
    s = line_strokes(hm, method="three_vertex", threshold=1.1, min_length=5)
    assert s.n_paths == 2 and set(np.unique(s.path_id)) == {0, 1}
    assert set(np.unique(s.segments[:, :, 2])) == {5.0, 15.0} and np.all(s.alpha == 1.0)
    s2 = line_strokes(hm, method="three_vertex", threshold=0.5, min_length=5, scale=0.3)
    assert s2.n_paths == 1 and np.allclose(s2.alpha, 0.6)  # only the high crest (0.3 * 2) is left


def test_precomputed_curvature_shape_checked():
    hm = ridge_map()
    with pytest.raises(ValueError, match="curvature"):
        line_strokes(hm, curvature=np.zeros((3, 3, 4), np.float32))
    with pytest.raises(TypeError, match="heightmap"):
        line_strokes(np.zeros((3, 3), np.float32))


def test_hatch_directions_on_cylinder():
    s = cylinder_ridge(30.0)
    h, _, _ = grid(s, 20, 20, 1.0, 1.0)
    hm = Heightmap.from_array(h)
    w = hatch_strokes(hm, method="three_vertex", direction="with", length=0.75, threshold=1e-3)
    p = hatch_strokes(hm, method="three_vertex", direction="perp", length=0.75, threshold=1e-3)
    assert w.kind == "hatch" and len(w) == len(p) > 0
    ww = hm.shape[1]
    inner = (w.path_id % ww >= 2) & (w.path_id % ww < ww - 2)  # the border columns see shifted stencils
    assert np.array_equal(w.path_id, p.path_id) and inner.sum() > 50
    dw = (w.segments[:, 1] - w.segments[:, 0])[inner]
    dp = (p.segments[:, 1] - p.segments[:, 0])[inner]
    # length 0.75 sample spacings, on the tangent plane
    assert np.allclose(np.linalg.norm(dw, axis=1), 0.75, atol=1e-5)
    assert np.allclose(np.linalg.norm(dp, axis=1), 0.75, atol=1e-5)
    # "with" the maximum curvature: across the ridge (no x component); "perp": along it, exactly x
    assert np.all(np.abs(dp[:, 2]) < 1e-5) and np.all(np.abs(dp[:, 1]) < 1e-5)
    assert np.all(np.abs(dw[:, 0]) < 1e-5)
    assert np.allclose(np.sum(dw * dp, axis=1), 0, atol=1e-5)
    assert np.all((w.alpha >= 0) & (w.alpha <= 1))


def test_hatch_bad_arguments():
    hm = ridge_map()
    with pytest.raises(ValueError, match="direction"):
        hatch_strokes(hm, direction="across")
    with pytest.raises(ValueError, match="length"):
        hatch_strokes(hm, length=0.0)


def test_nan_holes_draw_nothing_there():
    h = ridge_map().heights.copy()
    h[16, 10] = np.nan
    hm = Heightmap.from_array(h, allow_nan=True)
    s = line_strokes(hm, method="three_vertex", threshold=0.5, min_length=2)
    assert np.all(np.isfinite(s.segments)) and s.n_paths == 2  # the hole splits the crest
    t = hatch_strokes(hm, method="three_vertex", threshold=0.5)
    assert np.all(np.isfinite(t.segments)) and not np.any(t.path_id == 16 * 33 + 10)


def test_pictures_and_determinism(tmp_path):
    hm = Heightmap.example("topobathy")
    sp = 0.5 * (hm.dx + hm.dz)
    a = line_strokes(hm, method="three_normal", distance=2, scale=6 * sp, threshold=0.5, min_length=4)
    b = line_strokes(hm, method="three_normal", distance=2, scale=6 * sp, threshold=0.5, min_length=4)
    assert len(a) > 0 and digest(a.segments, a.alpha, a.path_id) == digest(b.segments, b.alpha, b.path_id)
    h = hatch_strokes(hm, method="two_normal", scale=4 * sp, length=0.75, threshold=0.05)
    a.picture(tmp_path / "lines.png", heightmap=hm, contours=True, title="3 norm, d=2")
    h.picture(tmp_path / "hatch.png", line_width=0.5)
    from matplotlib.image import imread

    img = imread(tmp_path / "lines.png")
    assert img.shape[1] == 800 and img[..., :3].min() < 0.2  # dark strokes on white
    assert (tmp_path / "hatch.png").stat().st_size > 1000
    with pytest.raises(ValueError, match="heightmap"):
        a.picture(contours=True)

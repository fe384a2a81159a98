import numpy as np
import pytest

from terrainwarp import Camera, Heightmap
from terrainwarp.lod.peers import delatin_mesh, martini_mesh, mesh_vertical_error
from terrainwarp.rendering import rasterize


@pytest.fixture(scope="module")
def hm():
    return Heightmap.fbm(97, 120, seed=11, dx=10.0, max_height=300.0)


@pytest.mark.parametrize("err", [0.5, 2.0, 8.0])
def test_delatin_respects_its_max_error(hm, err):
    p = delatin_mesh(hm, err)
    measured = mesh_vertical_error(hm, p)
    assert measured <= err * (1 + 1e-5) + 1e-4
    assert p.n_triangles < 2 * 96 * 119


def test_martini_error_is_a_threshold_not_a_bound(hm):
    rows = []
    for err in (1.0, 4.0, 16.0):
        p = martini_mesh(hm, err)
        rows.append((err, mesh_vertical_error(hm, p), p.n_triangles))
        assert "edge replication" in p.note
    assert any(measured > setting for setting, measured, _ in rows)  # measured, not assumed
    assert rows[0][2] > rows[-1][2]


def test_peer_meshes_are_ccw_from_above_and_render(hm):
    cam = Camera.default_for(hm, 96, 72)
    for p in (martini_mesh(hm, 2.0), delatin_mesh(hm, 2.0)):
        m = p.to_mesh(hm, cam)
        a, b, c = (m.positions[m.triangles[:, k]].astype(np.float64) for k in range(3))
        ny = np.cross(b - a, c - a)[:, 1]
        assert np.all(ny > 0)
        f = rasterize(m.positions, m.triangles, cam.view_matrix(relative=True), cam.proj_matrix(), 96, 72,
                      cull_back=True)
        assert (f.triangle_id >= 0).sum() > 1000


def _matplotlib_vertical_error(hm, p) -> float:
    """The reference: matplotlib's linear interpolation of the mesh at every sample (what the function did; its
    trifinder took ~3.5 s per mesh of the DEM, most of a small report's time)."""
    import matplotlib.tri as mtri

    h = hm.heights.astype(np.float64)
    rows, cols = h.shape
    interp = mtri.LinearTriInterpolator(mtri.Triangulation(p.grid_xy[:, 0], p.grid_xy[:, 1], p.triangles), p.heights)
    jj, ii = np.meshgrid(np.arange(cols, dtype=np.float64), np.arange(rows, dtype=np.float64))
    return float(np.nanmax(np.abs(np.ma.filled(interp(jj.ravel(), ii.ravel()), np.nan) - h.ravel())))


@pytest.mark.parametrize("make,err", [(delatin_mesh, 0.5), (delatin_mesh, 8.0), (martini_mesh, 1.0),
                                      (martini_mesh, 16.0)])
def test_vertical_error_agrees_with_matplotlibs_interpolation(hm, make, err):
    p = make(hm, err)
    want = _matplotlib_vertical_error(hm, p)
    assert mesh_vertical_error(hm, p) == pytest.approx(want, rel=1e-9, abs=1e-9)
    assert mesh_vertical_error(hm, p, chunk=997) == mesh_vertical_error(hm, p)  # the grouping changes nothing

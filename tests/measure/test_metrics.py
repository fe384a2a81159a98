import numpy as np
import pytest

from terrainwarp import Camera, Heightmap
from terrainwarp.kernels.displacement import grid_mesh
from terrainwarp.measure.error import frame_error, reference_height
from terrainwarp.rendering import rasterize


def _grid(hm, cam, dy=0.0):
    e = cam.position
    pos, _, tri = grid_mesh(hm.heights, hm.dx, hm.dz, (hm.origin[0] - e[0], e[1], hm.origin[1] - e[2]))
    pos = pos.copy()
    pos[:, 1] += np.float32(dy)
    return pos, tri


def _draw(pos, tri, cam):
    return rasterize(pos, tri, cam.view_matrix(relative=True), cam.proj_matrix(), cam.width, cam.height)


def test_reference_height_matches_the_grid_triangles():
    h = np.array([[0.0, 1.0], [2.0, 7.0]], np.float32)
    hm = Heightmap.from_array(h, 2.0, 4.0)
    # corners, and the diagonal (i, j+1)-(i+1, j) splits the cell
    assert reference_height(hm, np.array([0.0, 2.0, 0.0, 2.0]), np.array([0.0, 0.0, 4.0, 4.0])).tolist() == \
        [0.0, 1.0, 2.0, 7.0]
    assert reference_height(hm, np.array([0.5]), np.array([1.0]))[0] == pytest.approx(0.25 * 1 + 0.25 * 2)
    assert reference_height(hm, np.array([1.5]), np.array([3.0]))[0] == pytest.approx(7 - 0.25 * 5 - 0.25 * 6)


def test_error_is_exactly_zero_for_the_reference_mesh():
    hm = Heightmap.fbm(65, seed=3, dx=5.0, max_height=200.0)
    cam = Camera.default_for(hm, 160, 120)
    pos, tri = _grid(hm, cam)
    f = _draw(pos, tri, cam)
    st = frame_error(hm, cam, pos, cam.position, tri, f.triangle_id, f.barycentrics, f.depth,
                     f.triangle_id, f.depth)
    assert st.covered > 1000
    assert st.mismatched == 0 and st.see_through_px == 0
    # float32 positions and barycentrics: the reprojection differs by rounding only
    assert st.max_px < 2e-3


def test_known_vertical_offset_projects_as_computed_by_hand():
    hm = Heightmap.from_array(np.zeros((65, 65), np.float32), 1.0)
    cam = Camera(position=(32.0, 3.0, 80.0), target=(32.0, 3.0, 0.0), fov_y_deg=60, width=200, height=150,
                 near=0.1, far=500.0)  # looks horizontally along -z
    h = 0.25
    pos, tri = _grid(hm, cam, dy=h)
    f = _draw(pos, tri, cam)
    st = frame_error(hm, cam, pos, cam.position, tri, f.triangle_id, f.barycentrics, keep_maps=True)
    from terrainwarp.measure.error import pixel_positions

    rel = pixel_positions(pos, tri, f.triangle_id, f.barycentrics)
    cov = f.triangle_id >= 0
    depth_view = -rel[cov][:, 2]  # the camera looks along -z with no pitch
    expect = h * cam.focal_px / depth_view
    np.testing.assert_allclose(st.error_map[cov], expect, rtol=1e-4)
    assert st.max_px == pytest.approx(expect.max(), rel=1e-4)


def test_forced_crack_is_detected_and_located():
    hm = Heightmap.fbm(129, seed=1, dx=5.0, max_height=50.0)
    cam = Camera(position=(320.0, 700.0, 320.0), target=(320.0, 0.0, 320.0), up=(0, 0, -1), fov_y_deg=60,
                 width=160, height=160, near=1.0, far=2000.0)  # about 5 m per pixel: a one-cell slit is ~1 px
    pos, tri = _grid(hm, cam)
    ref = _draw(pos, tri, cam)
    # open a slit: drop the triangles of one row of cells in the middle
    cells_w = 128
    row = 64
    keep = np.ones(len(tri), bool)
    keep[2 * row * cells_w: 2 * (row + 1) * cells_w] = False
    tri2 = tri[keep]
    f = _draw(pos, tri2, cam)
    st = frame_error(hm, cam, pos, cam.position, tri2, f.triangle_id, f.barycentrics, f.depth,
                     ref.triangle_id, ref.depth, keep_maps=True)
    assert st.see_through_px > 30
    rows_hit = np.nonzero(st.see_through_mask.any(axis=1))[0]
    assert abs(float(rows_hit.mean()) - 80.0) < 6.0  # the slit crosses the middle of the image
    ok = frame_error(hm, cam, pos, cam.position, tri, ref.triangle_id, ref.barycentrics, ref.depth,
                     ref.triangle_id, ref.depth)
    assert ok.see_through_px == 0


def test_kernel_error_matches_the_numpy_formula():
    from terrainwarp.measure.error import pixel_positions

    hm = Heightmap.fbm(65, seed=8, dx=7.0, max_height=300.0)
    cam = Camera.default_for(hm, 120, 90)
    pos, tri = _grid(hm, cam, dy=0.5)
    f = _draw(pos, tri, cam)
    st = frame_error(hm, cam, pos, cam.position, tri, f.triangle_id, f.barycentrics, keep_maps=True)
    cov = f.triangle_id >= 0
    p = pixel_positions(pos, tri, f.triangle_id, f.barycentrics)[cov]
    e = np.asarray(cam.position)
    ry = reference_height(hm, p[:, 0] + e[0], p[:, 2] + e[2]) - e[1]
    m = cam.proj_matrix() @ cam.view_matrix(relative=True)

    def pix(q):
        c = np.c_[q, np.ones(len(q))] @ m.T
        return np.stack([(c[:, 0] / c[:, 3] * 0.5 + 0.5) * 120, (c[:, 1] / c[:, 3] * 0.5 + 0.5) * 90], 1)

    ref = np.linalg.norm(pix(p) - pix(np.c_[p[:, 0], ry, p[:, 2]]), axis=1)
    np.testing.assert_allclose(st.error_map[cov], ref, rtol=1e-5, atol=1e-6)


def test_tiny_viewport_with_images_has_no_ssim_but_no_crash():
    hm = Heightmap.fbm(17, seed=1, dx=5.0, max_height=40.0)
    cam = Camera.default_for(hm, 5, 4)
    pos, tri = _grid(hm, cam)
    f = _draw(pos, tri, cam)
    img = np.zeros((4, 5, 3), np.uint8)
    st = frame_error(hm, cam, pos, cam.position, tri, f.triangle_id, f.barycentrics, image=img, ref_image=img + 1)
    # SSIM needs a 7x7 window; PSNR of images 1 level apart everywhere: MSE 1, so 20 log10(255) = 48.13 dB
    assert st.ssim is None and st.psnr_db == pytest.approx(20 * np.log10(255.0), abs=1e-9)


def test_a_percentile_over_infinite_errors_is_infinite_not_nan():
    """A point behind the eye is +inf px; numpy's interpolation made the p99 NaN (inf - inf) with a warning."""
    import warnings

    from terrainwarp.measure.sample_error import percentile

    a = np.array([1.0, 2.0, np.inf] * 50)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert percentile(a, 99) == np.inf and percentile(a, 10) == 1.0
        assert percentile(np.arange(101.0), 99) == 99.0

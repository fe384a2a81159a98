"""The visibility pass against GPU rules and against Mesa's llvmpipe (OpenGL 4.5 via EGL) as an oracle."""

from __future__ import annotations

import gl_raster_oracle as gl  # noqa: E402
import numpy as np
import pytest
from conftest import digest

import terrainwarp as tw
from terrainwarp.kernels.raster import SUBPIXEL, clip_coordinates, rasterize, rasterize_clip

HAVE_GL = gl.available()
needs_gl = pytest.mark.skipif(not HAVE_GL, reason="no EGL / OpenGL 4.5 context (llvmpipe) on this machine")
I4 = np.eye(4)


def window_to_clip(xy: np.ndarray, width: int, height: int, z: float | np.ndarray = 0.0) -> np.ndarray:
    """(n, 2) window coordinates (GL: origin bottom-left, pixels of size 1) -> (n, 4) clip, w = 1."""
    xy = np.asarray(xy, np.float64)
    out = np.empty((len(xy), 4), np.float64)
    out[:, 0] = xy[:, 0] / width * 2.0 - 1.0
    out[:, 1] = xy[:, 1] / height * 2.0 - 1.0
    out[:, 2] = z
    out[:, 3] = 1.0
    return out.astype(np.float32)


def coverage_counts(clip, tris, width, height, device="cpu"):
    """How many of the triangles cover each pixel, drawing each alone."""
    cnt = np.zeros((height, width), np.int32)
    for t in tris:
        f = rasterize_clip(clip, np.asarray([t], np.int32), width, height, device=device)
        cnt += f.triangle_id >= 0
    return cnt


def frame_hash(f) -> str:
    return digest(f.triangle_id, f.depth, f.barycentrics)


def terrain_frame(rows=96, width=160, height=120, device="cpu"):
    from terrainwarp.kernels.displacement import grid_mesh

    hm = tw.Heightmap.fbm(rows, rows, seed=3)
    cam = tw.Camera.default_for(hm, width=width, height=height)
    eye = cam.position
    pos, _, tri = grid_mesh(hm.heights, hm.dx, hm.dz, (hm.origin[0] - eye[0], eye[1], hm.origin[1] - eye[2]),
                            device=device)
    return pos, tri, cam


# -- fill rule ---------------------------------------------------------------------------------------


def test_shared_edge_through_pixel_centres_covers_each_pixel_once(device):
    w, h = 16, 12
    # a square whose corners and diagonal lie exactly on pixel centres
    xy = np.array([[2.5, 2.5], [12.5, 2.5], [12.5, 9.5], [2.5, 9.5]])
    clip = window_to_clip(xy, w, h)
    tris = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    cnt = coverage_counts(clip, tris, w, h, device=device)
    assert cnt.max() == 1
    both = rasterize_clip(clip, tris, w, h, device=device).triangle_id
    assert np.array_equal(both >= 0, cnt == 1)
    # the diagonal's centres (x - 2.5 == (y - 2.5) * 10 / 7 has none here besides corners); use a
    # 45-degree square as well, whose diagonal passes through 8 pixel centres
    xy = np.array([[2.5, 1.5], [10.5, 1.5], [10.5, 9.5], [2.5, 9.5]])
    clip = window_to_clip(xy, w, h)
    cnt = coverage_counts(clip, tris, w, h, device=device)
    assert cnt.max() == 1
    # inside pixels all covered: columns 3..10 (centres 3.5..10.5 ... left edge at 2.5 included)
    ids = rasterize_clip(clip, tris, w, h, device=device).triangle_id
    assert (ids >= 0).sum() == (cnt == 1).sum() == 8 * 8


def test_fan_around_a_pixel_centre_covers_each_pixel_once(device):
    w, h = 24, 24
    c = np.array([12.5, 12.5])  # a pixel centre
    k = 7
    ang = np.linspace(0.0, 2 * np.pi, k, endpoint=False) + 0.3
    ring = c + 9.0 * np.stack([np.cos(ang), np.sin(ang)], 1)
    # snap the ring onto pixel centres too, so many edges pass through centres
    ring = np.floor(ring) + 0.5
    xy = np.vstack([c, ring])
    clip = window_to_clip(xy, w, h)
    tris = np.array([[0, 1 + i, 1 + (i + 1) % k] for i in range(k)], np.int32)
    cnt = coverage_counts(clip, tris, w, h, device=device)
    assert cnt.max() == 1
    assert cnt[h - 1 - 12, 12] == 1  # the centre pixel itself, exactly once
    ids = rasterize_clip(clip, tris, w, h, device=device).triangle_id
    assert np.array_equal(ids >= 0, cnt == 1)


@needs_gl
def test_fill_convention_matches_llvmpipe_on_a_grid_through_pixel_centres():
    rng = np.random.default_rng(0)
    w, h, n = 64, 48, 9
    gx, gy = np.meshgrid(np.round(np.linspace(0, w, n)) + 0.5, np.round(np.linspace(0, h, n)) + 0.5)
    clip = window_to_clip(np.stack([gx.ravel(), gy.ravel()], 1), w, h, rng.uniform(-0.5, 0.5, n * n))
    front, back = [], []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            front += [[a, a + 1, a + n + 1], [a, a + n + 1, a + n]]
            back += [[a + 1, a, a + n]]  # clockwise: back-facing, overlapping the front ones
    front, back = np.array(front, np.int32), np.array(back, np.int32)
    cases = [(front, False), (back, False), (np.vstack([front, back]), True), (np.vstack([back, front]), True)]
    for tris, cull in cases:
        f = rasterize_clip(clip, tris, w, h, cull_back=cull)
        ids, dep = gl.gl_rasterize(clip, tris, w, h, cull_back=cull)
        assert np.array_equal(f.triangle_id, ids), (f.triangle_id != ids).sum()
        m = ids >= 0
        assert m.sum() > 0.6 * w * h
        assert np.abs(f.depth[m] - dep[m]).max() < 1e-6


# -- agreement with llvmpipe -------------------------------------------------------------------------


def _random_sets(rng, m):
    v = rng.uniform(-1.2, 1.2, (3 * m, 4))
    v[:, 3] = rng.uniform(0.5, 2.0, 3 * m)
    v[:, :3] *= v[:, 3:4]
    c = rng.uniform(-1, 1, (m, 1, 2))
    d = rng.normal(0, 0.05, (m, 3, 2))
    small = np.concatenate([(c + d).reshape(-1, 2), rng.uniform(-0.9, 0.9, (3 * m, 1)), np.ones((3 * m, 1))], 1)
    tiny = small.copy()
    tiny[:, :2] = (c + d * 0.02).reshape(-1, 2)  # sub-pixel triangles
    near = rng.uniform(-3, 3, (3 * m, 4))
    near[:, 3] = rng.uniform(-1, 3, 3 * m)
    big = rng.uniform(-2.5, 2.5, (3 * m // 10, 4))  # large, binned triangles, many off-screen
    big[:, 3] = 1.0
    return {"random": v, "small": small, "tiny": tiny, "near-crossing": near, "large": big}


@needs_gl
@pytest.mark.parametrize("seed", [0, 1])
def test_agrees_with_llvmpipe_on_random_triangles(seed):
    rng = np.random.default_rng(seed)
    w, h, m = 80, 60, 2000
    for name, v in _random_sets(rng, m).items():
        clip = v.astype(np.float32)
        tris = np.arange(len(clip) - len(clip) % 3, dtype=np.int32).reshape(-1, 3)
        f = rasterize_clip(clip, tris, w, h)
        ids, dep = gl.gl_rasterize(clip, tris, w, h)
        differ = int((f.triangle_id != ids).sum())
        # near-plane crossing triangles are clipped by both in float32, along slightly different paths:
        # a handful of pixels on clipped edges may differ; everything else matches exactly
        allowed = 0.002 * w * h if name == "near-crossing" else 0
        assert differ <= allowed, (name, differ)
        same = (f.triangle_id == ids) & (ids >= 0)
        # depth: same float32 plane equation up to rounding (steep random triangles: ~1e-5)
        assert np.abs(f.depth[same] - dep[same]).max() < 2e-4, name
        if name == "large":
            assert f.stats["triangles_binned"] > 0 and f.stats["tile_entries"] > 0


@needs_gl
def test_agrees_with_llvmpipe_on_a_terrain_frame():
    pos, tri, cam = terrain_frame()
    view, proj = cam.view_matrix(relative=True), cam.proj_matrix()
    f = rasterize(pos, tri, view, proj, cam.width, cam.height)
    ids, dep = gl.gl_rasterize(clip_coordinates(pos, view, proj), tri, cam.width, cam.height)
    assert np.array_equal(f.triangle_id, ids)
    same = (f.triangle_id == ids) & (ids >= 0)
    assert np.abs(f.depth[same] - dep[same]).max() < 1e-6


# -- clipping, snapping, depth -----------------------------------------------------------------------


def _reference_coverage(clip64, w, h):
    """Pixel centres inside the triangle's visible part (in front of the near plane), in float64:
    a centre is inside iff the perspective-correct barycentrics are all > 0 and the point has
    z >= -w (computed exactly from homogeneous clip coordinates)."""
    ys, xs = np.mgrid[0:h, 0:w]
    nx = (xs + 0.5) / w * 2 - 1
    ny = ((h - 1 - ys) + 0.5) / h * 2 - 1
    a = clip64[None, None, :, 0] - nx[..., None] * clip64[None, None, :, 3]
    c = clip64[None, None, :, 1] - ny[..., None] * clip64[None, None, :, 3]
    b = np.cross(a, c)
    s = b.sum(-1, keepdims=True)
    bb = b / s
    p = np.einsum("hwk,kc->hwc", bb, clip64)
    inside = np.all(bb > 0, -1) & (p[..., 3] > 0) & (p[..., 2] >= -p[..., 3]) & (p[..., 2] <= p[..., 3])
    margin = np.min(np.abs(bb), -1)
    return inside, margin


def test_near_plane_crossing_triangle_is_drawn_correctly_never_flipped(device):
    w, h = 64, 48
    near, far = 0.5, 100.0
    cam_proj = tw.Camera(position=(0, 0, 0), target=(0, 0, -1), width=w, height=h, near=near,
                         far=far, fov_y_deg=60).proj_matrix()
    # a big floor triangle under the camera reaching behind it (z > 0 is behind the eye)
    pos = np.array([[-4.0, -1.0, 3.0], [4.0, -1.0, 3.0], [0.0, -1.0, -30.0]], np.float32)
    for order in ([0, 1, 2], [1, 0, 2]):
        tri = np.array([order], np.int32)
        clip64 = np.c_[pos.astype(np.float64), np.ones(3)] @ (cam_proj @ I4).T
        ref, margin = _reference_coverage(clip64, w, h)
        f = rasterize(pos, tri, I4, cam_proj, w, h, device=device)
        got = f.triangle_id >= 0
        assert ref.sum() > 200
        assert np.all(got[ref & (margin > 1e-3)])
        assert not np.any(got & ~ref & (margin > 1e-3))
        # the floor is below the horizon: nothing drawn in the upper half (a flipped triangle would be)
        assert not got[: h // 2 - 1].any()
        # facing is preserved through clipping: the first order is counter-clockwise seen from above
        # (normal +y), so it faces the camera above the floor and culling keeps it; the other is culled
        culled = rasterize(pos, tri, I4, cam_proj, w, h, cull_back=True, device=device).triangle_id >= 0
        if order == [0, 1, 2]:
            assert np.array_equal(culled, got)
        else:
            assert not culled.any()


def test_moving_a_vertex_by_less_than_half_a_subpixel_changes_no_pixel(device):
    rng = np.random.default_rng(5)
    w, h = 48, 40
    # vertices exactly on the 1/256-pixel grid, away from pixel centres by construction of rounding
    xy = rng.integers(0, [w * SUBPIXEL, h * SUBPIXEL], (600, 2)) / SUBPIXEL
    # one depth for all (ties go by id), so that only coverage can change
    clip = window_to_clip(xy, w, h, 0.3)
    tris = np.arange(600, dtype=np.int32).reshape(-1, 3)
    f0 = rasterize_clip(clip, tris, w, h, device=device)
    for _ in range(3):
        d = rng.uniform(-0.45, 0.45, xy.shape) / SUBPIXEL  # < 1/512 px: same snapped position
        f1 = rasterize_clip(window_to_clip(xy + d, w, h, clip[:, 2]), tris, w, h, device=device)
        assert np.array_equal(f0.triangle_id, f1.triangle_id)
        assert np.array_equal(f0.depth, f1.depth)
    # and a move by a whole sub-pixel step does change something somewhere
    f2 = rasterize_clip(window_to_clip(xy + 3.0 / SUBPIXEL, w, h, clip[:, 2]), tris, w, h, device=device)
    assert not np.array_equal(f0.triangle_id, f2.triangle_id)


def test_depth_ties_go_to_the_lower_triangle_id_whatever_the_order(device):
    w, h = 32, 32
    xy = np.array([[2.0, 3.0], [30.0, 5.0], [9.0, 29.0]])
    clip = window_to_clip(np.vstack([xy, xy]), w, h, 0.25)
    for tris in (np.array([[0, 1, 2], [3, 4, 5]], np.int32), np.array([[3, 4, 5], [0, 1, 2]], np.int32)):
        ids = rasterize_clip(clip, tris, w, h, device=device).triangle_id
        assert set(np.unique(ids)) == {-1, 0}
    # nearer wins regardless of id
    clip2 = clip.copy()
    clip2[3:, 2] = 0.1
    ids = rasterize_clip(clip2, np.array([[0, 1, 2], [3, 4, 5]], np.int32), w, h, device=device).triangle_id
    assert set(np.unique(ids)) == {-1, 1}


def test_depth_is_window_depth_and_matches_an_analytic_plane(device):
    w, h = 40, 30
    cam = tw.Camera(position=(0, 5, 0), target=(0, 0, -20), width=w, height=h, near=1.0, far=200.0)
    view, proj = cam.view_matrix(), cam.proj_matrix()
    pos = np.array([[-50, 0, 5], [50, 0, 5], [0, 0, -150]], np.float32)  # the ground plane y = 0
    f = rasterize(pos, np.array([[0, 1, 2]], np.int32), view, proj, w, h, device=device)
    m = f.triangle_id >= 0
    assert m.sum() > 100
    # analytic: intersect each pixel's ray with y = 0, project, window depth
    ys, xs = np.nonzero(m)
    nx = (xs + 0.5) / w * 2 - 1
    ny = ((h - 1 - ys) + 0.5) / h * 2 - 1
    inv = np.linalg.inv(proj @ view)
    p0 = np.c_[nx, ny, -np.ones_like(nx), np.ones_like(nx)] @ inv.T
    p1 = np.c_[nx, ny, np.ones_like(nx), np.ones_like(nx)] @ inv.T
    p0 = p0[:, :3] / p0[:, 3:]
    p1 = p1[:, :3] / p1[:, 3:]
    t = p0[:, 1] / (p0[:, 1] - p1[:, 1])
    hit = p0 + t[:, None] * (p1 - p0)
    c = np.c_[hit, np.ones(len(hit))] @ (proj @ view).T
    ref = 0.5 * c[:, 2] / c[:, 3] + 0.5
    assert np.abs(f.depth[m] - ref).max() < 2e-6
    assert np.all(f.depth[~m] == 1.0)


# -- edge cases -------------------------------------------------------------------------------------


def test_empty_mesh_and_degenerate_triangles_draw_nothing(device):
    w, h = 16, 16
    f = rasterize(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), I4, I4, w, h, device=device)
    assert (f.triangle_id == -1).all() and (f.depth == 1.0).all() and f.stats["triangles_in"] == 0
    pos = np.array([[0, 0, 0], [0.5, 0.5, 0], [-0.5, -0.5, 0], [0.3, -0.7, 0]], np.float32)
    tris = np.array([[0, 0, 0], [0, 1, 2], [1, 1, 3], [3, 3, 3]], np.int32)  # point, collinear, line, point
    f = rasterize(pos, tris, I4, I4, w, h, device=device)
    assert (f.triangle_id == -1).all()
    assert f.stats["triangles_rasterized"] == 0 and f.stats["pixels_covered"] == 0
    # triangles entirely behind the eye or beyond the far plane
    f = rasterize(np.array([[0, 0, 2], [1, 0, 2], [0, 1, 2]], np.float32), np.array([[0, 1, 2]]), I4, I4, w, h,
                  device=device)
    assert (f.triangle_id == -1).all()


def test_bad_input_is_rejected_with_the_argument_named():
    pos = np.zeros((3, 3), np.float32)
    tri = np.array([[0, 1, 2]], np.int32)
    with pytest.raises(ValueError, match="positions"):
        rasterize(np.zeros((3, 2)), tri, I4, I4, 8, 8)
    with pytest.raises(ValueError, match="triangles"):
        rasterize(pos, np.array([[0, 1, 3]]), I4, I4, 8, 8)
    with pytest.raises(TypeError, match="triangles"):
        rasterize(pos, tri.astype(np.float32), I4, I4, 8, 8)
    with pytest.raises(ValueError, match="width"):
        rasterize(pos, tri, I4, I4, 0, 8)
    with pytest.raises(TypeError, match="height"):
        rasterize(pos, tri, I4, I4, 8, 8.0)
    with pytest.raises(ValueError, match="proj"):
        rasterize(pos, tri, I4, np.eye(3), 8, 8)
    with pytest.raises(ValueError, match="clip"):
        rasterize_clip(np.zeros((3, 3), np.float32), tri, 8, 8)
    with pytest.raises(ValueError, match="positions"):
        rasterize(np.full((3, 3), np.nan, np.float32), tri, I4, I4, 8, 8)
    with pytest.raises(TypeError, match="checked"):
        rasterize(pos, tri, I4, I4, 8, 8, checked=1)
    with pytest.raises(TypeError, match="triangles"):  # a mesh vouched for still has its dtype checked
        rasterize(pos, tri.astype(np.float32), I4, I4, 8, 8, checked=True)


def test_a_mesh_vouched_for_is_drawn_as_a_checked_one():
    """``checked=True`` (the meshes render makes) skips the scans of the indices and positions, nothing else."""
    pos, tri, cam = terrain_frame(rows=40, width=96, height=64)
    args = (pos, tri, cam.view_matrix(relative=True), cam.proj_matrix(), cam.width, cam.height)
    a, b = rasterize(*args, counters=True), rasterize(*args, counters=True, checked=True)
    assert frame_hash(a) == frame_hash(b) and a.stats == b.stats and a.counters == b.counters


def test_one_pixel_viewport(device):
    pos = np.array([[-1, -1, 0], [1, -1, 0], [0, 1, 0]], np.float32)
    f = rasterize(pos, np.array([[0, 1, 2]], np.int32), I4, I4, 1, 1, device=device)
    assert f.triangle_id.shape == (1, 1) and f.triangle_id[0, 0] == 0
    assert abs(float(f.depth[0, 0]) - 0.5) < 1e-6
    f = rasterize(pos * 0.2 + np.float32([0.5, 0.5, 0]), np.array([[0, 1, 2]], np.int32), I4, I4, 1, 1, device=device)
    assert f.triangle_id[0, 0] == -1  # does not reach the single centre


def test_8192_viewport_covers_exactly_like_a_scaled_small_one(device):
    w = 8192
    pos = np.array([[-0.9, -0.8, 0.1], [0.95, -0.3, 0.2], [-0.2, 0.85, -0.4], [0.9, 0.9, 0.5]], np.float32)
    tris = np.array([[0, 1, 2], [1, 3, 2]], np.int32)
    f = rasterize(pos, tris, I4, I4, w, w, device=device)
    assert f.triangle_id.shape == (w, w)
    cnt = np.bincount(f.triangle_id.ravel() + 1, minlength=3)
    # areas in pixels: ndc area * (w / 2)^2, to within the perimeter
    def area(a, b, c):
        u, v = pos[b, :2] - pos[a, :2], pos[c, :2] - pos[a, :2]
        return 0.5 * abs(float(u[0] * v[1] - u[1] * v[0])) * (w / 2) ** 2

    a0, a1 = area(0, 1, 2), area(1, 3, 2)
    assert abs(cnt[1] - a0) < 3 * w and abs(cnt[2] - a1) < 3 * w
    assert f.stats["triangles_binned"] == 2
    # the corner pixels lie outside
    assert f.triangle_id[0, 0] == -1 and f.triangle_id[-1, -1] == -1


def test_deterministic_and_counts_reported(device):
    pos, tri, cam = terrain_frame(device=device)
    args = (pos, tri, cam.view_matrix(relative=True), cam.proj_matrix(), cam.width, cam.height)
    f1, f2 = rasterize(*args, device=device), rasterize(*args, device=device)
    assert frame_hash(f1) == frame_hash(f2)
    s = f1.stats
    assert s["triangles_in"] == len(tri)
    assert 0 < s["triangles_rasterized"] <= s["triangles_in"]
    assert s["fragments_tested"] >= s["fragments_inside"] >= s["pixels_written"] >= s["pixels_covered"] > 0
    # back-face culling of a terrain seen from above keeps the same image (the terrain faces up)
    f3 = rasterize(*args, cull_back=True, device=device)
    assert f3.stats["triangles_rasterized"] <= s["triangles_rasterized"]
    assert ((f3.triangle_id >= 0) != (f1.triangle_id >= 0)).mean() < 0.01


def test_barycentrics_reconstruct_the_pixel_centre(device):
    pos, tri, cam = terrain_frame(rows=48, width=64, height=48, device=device)
    view, proj = cam.view_matrix(relative=True), cam.proj_matrix()
    f = rasterize(pos, tri, view, proj, cam.width, cam.height, device=device)
    ys, xs = np.nonzero(f.triangle_id >= 0)
    t = f.triangle_id[ys, xs]
    b = f.barycentrics[ys, xs].astype(np.float64)
    bw = np.c_[b, 1 - b.sum(1)]
    p = np.einsum("nk,nkc->nc", bw, pos[tri[t]].astype(np.float64))
    c = np.c_[p, np.ones(len(p))] @ (proj @ view).T
    px = (c[:, 0] / c[:, 3] + 1) * cam.width / 2
    py = (c[:, 1] / c[:, 3] + 1) * cam.height / 2
    assert np.abs(px - (xs + 0.5)).max() < 1e-2
    assert np.abs(py - (cam.height - 1 - ys + 0.5)).max() < 1e-2
    assert (bw > -1e-3).all()


@needs_gl
def test_agrees_with_llvmpipe_when_the_camera_is_down_in_the_terrain():
    # a low camera: nearby terrain triangles cross the near plane and the viewport's edges
    from terrainwarp.kernels.displacement import grid_mesh

    hm = tw.Heightmap.fbm(64, 64, seed=5, max_height=300.0)
    (x0, z0), (x1, z1) = hm.bounds_xz
    cx, cz = 0.5 * (x0 + x1), 0.5 * (z0 + z1)
    h = float(hm.heights[32, 32])
    cam = tw.Camera(position=(cx, h + 3.0, cz), target=(cx + 200.0, h - 20.0, cz - 150.0), width=96, height=72,
                    near=2.0, far=5000.0, fov_y_deg=70.0)
    eye = cam.position
    pos, _, tri = grid_mesh(hm.heights, hm.dx, hm.dz, (hm.origin[0] - eye[0], eye[1], hm.origin[1] - eye[2]))
    view, proj = cam.view_matrix(relative=True), cam.proj_matrix()
    clip = clip_coordinates(pos, view, proj)
    crossing = np.any(clip[tri][..., 2] < -clip[tri][..., 3], axis=1) & np.any(
        clip[tri][..., 2] > -clip[tri][..., 3], axis=1)
    assert crossing.sum() > 0
    f = rasterize(pos, tri, view, proj, cam.width, cam.height)
    ids, dep = gl.gl_rasterize(clip, tri, cam.width, cam.height)
    assert (f.triangle_id >= 0).mean() > 0.3
    assert (f.triangle_id != ids).sum() <= 2, (f.triangle_id != ids).sum()
    same = (f.triangle_id == ids) & (ids >= 0)
    # clipped triangles: our clipped vertices and Mesa's round differently (float32): ~1e-5 on steep ones
    assert np.abs(f.depth[same] - dep[same]).max() < 1e-4


def test_binning_tests_only_tiles_a_large_triangle_can_cover(device):
    w, h = 512, 512
    # a long thin diagonal triangle: its bounding box is the whole screen, its area ~1% of it
    xy = np.array([[4.0, 2.0], [508.0, 500.0], [500.0, 510.0]])
    clip = window_to_clip(xy, w, h, 0.0)
    f = rasterize_clip(clip, np.array([[0, 1, 2]], np.int32), w, h, device=device)
    s = f.stats
    assert s["triangles_binned"] == 1
    covered = s["pixels_covered"]
    assert covered > 1000
    # only tiles along the diagonal are visited: far fewer than the box's 512 * 512 pixel centres
    assert s["tile_entries"] < 0.2 * (w // 16) * (h // 16)
    assert s["fragments_tested"] < 20 * covered
    assert s["fragments_tested"] == s["tile_entries"] * 16 * 16 or s["fragments_tested"] < s["tile_entries"] * 256


@needs_gl
def test_depth_one_is_not_drawn_as_gl_less_against_a_cleared_buffer(device):
    w, h = 32, 24
    clip = np.array([[-0.9, -0.9, 1.0, 1.0], [0.9, -0.8, 1.0, 1.0], [0.0, 0.9, 1.0, 1.0],  # on the far plane
                     [-0.9, 0.9, 0.0, 1.0], [0.9, 0.9, 2.0, 1.0], [0.0, -0.9, 0.0, 1.0]], np.float32)  # crosses it
    tris = np.array([[0, 1, 2], [3, 4, 5]], np.int32)
    f = rasterize_clip(clip, tris, w, h, device=device)
    ids, dep = gl.gl_rasterize(clip, tris, w, h)
    assert not (f.triangle_id == 0).any()
    assert (f.triangle_id == 1).sum() > 50
    assert np.array_equal(f.triangle_id, ids)


# -- pooled buffers: lists' room kept between frames, output images reused once dropped --------------------


def _scenes(w=160, h=120):
    """Draws at one viewport size that cover different rows and tiles: a terrain (many rows, large triangles
    binned), a thin band of small triangles, large clipped triangles (some behind the camera), an empty draw."""
    pos, tri, cam = terrain_frame(rows=12, width=w, height=h)  # small triangles and large (binned) ones
    clip_t = clip_coordinates(pos, cam.view_matrix(relative=True), cam.proj_matrix())
    rng = np.random.default_rng(5)
    band = window_to_clip(np.c_[rng.uniform(-5, w + 5, 60), rng.uniform(0.42 * h, 0.47 * h, 60)], w, h)
    band[:, 2] = rng.uniform(-0.9, 0.9, 60)
    big = window_to_clip(rng.uniform(-0.3, 1.3, (12, 2)) * [w, h], w, h)
    big[:, 2] = rng.uniform(-1.2, 1.2, 12)
    big[:, 3] = rng.uniform(0.5, 2.0, 12)
    big[:, :3] *= big[:, 3:4]
    big[::5, 3] *= -0.5
    seq = lambda n: np.arange(n, dtype=np.int32).reshape(-1, 3)  # noqa: E731
    return {"terrain": (clip_t, tri), "band": (band, seq(60)), "big": (big, seq(12)),
            "empty": (np.zeros((0, 4), np.float32), np.zeros((0, 3), np.int32))}, (w, h)


def _fresh_pools():
    from terrainwarp.kernels import pool

    pool.release_buffers()


def _result(f):
    stats = {k: v for k, v in f.stats.items() if k != "pixels_written"}  # the one order-dependent counter
    return f.triangle_id.copy(), f.depth.copy(), f.barycentrics.copy(), stats


def _same(a, b):
    return all(np.array_equal(x, y) for x, y in zip(a[:3], b[:3], strict=True)) and a[3] == b[3]


def test_pooled_buffers_reused_by_other_draws_give_the_fresh_result():

    scenes, (w, h) = _scenes()
    fresh = {}
    for name, (clip, tri) in scenes.items():
        _fresh_pools()
        fresh[name] = _result(rasterize_clip(clip, tri, w, h))
    assert (fresh["terrain"][0] >= 0).sum() > 2000 and (fresh["band"][0] >= 0).sum() > 50
    assert fresh["terrain"][3]["triangles_binned"] > 0 and fresh["big"][3]["triangles_binned"] > 0
    assert (fresh["empty"][0] == -1).all() and (fresh["empty"][2] == 0).all()
    # every draw after every other (a draw after one that covered more rows, or other tiles), through the pools
    order = ["terrain", "band", "terrain", "empty", "big", "band", "big", "terrain", "empty", "band"]
    for prev, name in zip(order, order[1:], strict=False):
        r = _result(rasterize_clip(*scenes[name], w, h))
        assert _same(r, fresh[name]), f"{name} after {prev}"
    # the tiles' lists: binned in one pass into the room kept from the frame before (which a denser frame outgrows,
    # then binned again with exact room) or counted then emitted, the same frame
    _fresh_pools()
    assert _same(_result(rasterize_clip(*scenes["terrain"], w, h)), fresh["terrain"])  # counted, then emitted
    assert _same(_result(rasterize_clip(*scenes["terrain"], w, h)), fresh["terrain"])  # one pass, in the room


def test_images_held_by_the_caller_are_never_reused_and_changes_to_dropped_ones_do_not_leak():
    scenes, (w, h) = _scenes()
    _fresh_pools()
    want = {name: _result(rasterize_clip(*scenes[name], w, h)) for name in ("terrain", "band")}
    f1 = rasterize_clip(*scenes["terrain"], w, h)
    view_of_ids = f1.triangle_id[10:]  # a view alone keeps the image taken
    depth_only = f1.depth
    del f1
    for _ in range(3):  # more frames of the size than images are kept
        f2 = rasterize_clip(*scenes["band"], w, h)
        assert _same(_result(f2), want["band"])
    assert np.array_equal(view_of_ids, want["terrain"][0][10:]) and np.array_equal(depth_only, want["terrain"][1])
    # the caller writes into a frame's images, then drops it: the next frame that takes them starts clean
    f2.triangle_id[:] = 7
    f2.depth[:] = 0.25
    f2.barycentrics[:] = 0.5
    del f2, view_of_ids, depth_only
    for name in ("band", "terrain", "band"):
        assert _same(_result(rasterize_clip(*scenes[name], w, h)), want[name]), name


def test_barycentrics_computed_after_later_draws_are_unchanged():
    scenes, (w, h) = _scenes()
    _fresh_pools()
    want = _result(rasterize_clip(*scenes["terrain"], w, h))
    f = rasterize_clip(*scenes["terrain"], w, h)
    for name in ("band", "big", "empty"):
        rasterize_clip(*scenes[name], w, h).barycentrics  # noqa: B018 -- the lazy resolve, in between
    assert _same(_result(f), want)


@pytest.mark.parametrize("threads", [2, 3])
def test_identical_for_any_thread_count_with_pooled_buffers(threads):
    from terrainwarp.kernels import parallel

    scenes, (w, h) = _scenes(203, 97)  # tiles cut by the viewport's edges
    order = ["terrain", "band", "big", "empty", "terrain", "band"]
    runs = []
    try:
        for n in (1, threads):
            parallel.set_threads(n)
            parallel.set_min_items(1)  # chunks as fine as the threads allow
            _fresh_pools()
            runs.append([_result(rasterize_clip(*scenes[name], w, h)) for name in order])
    finally:
        parallel.set_threads(None)
        parallel.set_min_items(None)
    for name, a, b in zip(order, *runs, strict=True):
        assert _same(a, b), name


def test_the_way_cuda_draws_gives_the_cpus_frames(monkeypatch):
    """Without the CPU's scratch tiles (as on CUDA: every tile drawn in the images themselves, by one launch index
    each, its list sorted first, every entry in 4x4 blocks), the same ids, depth, stats and counters: the SIMD rows
    and the blocks cover, test and count alike (fragments_tested counts the centres each way evaluates)."""
    from terrainwarp.kernels import parallel, raster

    scenes, (w, h) = _scenes(203, 97)
    want = {name: rasterize_clip(*scenes[name], w, h, counters=True) for name in scenes}
    monkeypatch.setattr(raster, "_SCRATCH", False)
    try:
        parallel.set_min_items(1)  # tiles drawn by every thread at once
        for name, (clip, tri) in scenes.items():
            got = rasterize_clip(clip, tri, w, h, counters=True)
            a, b = _result(got), _result(want[name])
            assert got.stats["fragments_tested"] >= got.stats["fragments_inside"]
            a[3].pop("fragments_tested"), b[3].pop("fragments_tested")
            assert _same(a, b) and got.counters == want[name].counters, name
    finally:
        parallel.set_min_items(None)


@pytest.mark.parametrize("cull_back", [False, True])
def test_the_cpus_simd_binning_gives_the_per_triangle_paths_frames(monkeypatch, cull_back):
    """Triangles in no order that meet every case of the CPU's 16-lane binning (boxes with no centre, tiny boxes
    with and without a covered centre, boxes up to 4x4 and larger, zero-area, clockwise, all beyond one clip plane,
    clipped, behind the camera, large) give the ids, depth, barycentrics, stats and counters of the per-triangle
    binning CUDA runs (the drawing way without scratch tiles, which bins one triangle at a time)."""
    from terrainwarp.kernels import raster

    w, h, n = 150, 110, 3000
    rng = np.random.default_rng(11)
    centre = rng.uniform([-25, -25], [w + 25, h + 25], (n, 1, 2))
    size = rng.choice([0.2, 0.6, 1.5, 3.0, 8.0, 40.0], (n, 1, 1))  # sub-pixel up to large
    xy = (centre + rng.normal(0.0, 1.0, (n, 3, 2)) * size).reshape(-1, 2)
    xy[1::3][::29] = xy[0::3][::29]  # zero-area: two vertices at one point
    xy[: 3 * n // 2] = np.round(xy[: 3 * n // 2] * 2.0) / 2.0  # half of them on half pixels: edges through centres
    clip = window_to_clip(xy, w, h, rng.uniform(-1.15, 1.15, len(xy)))
    clip *= rng.uniform(0.5, 2.0, (len(clip), 1))  # the same window positions at other w
    clip[2::3][::53] *= -1.0  # a vertex behind the camera
    tri = np.arange(3 * n, dtype=np.int32).reshape(-1, 3)
    simd = rasterize_clip(clip, tri, w, h, cull_back=cull_back, counters=True)
    monkeypatch.setattr(raster, "_SCRATCH", False)
    one = rasterize_clip(clip, tri, w, h, cull_back=cull_back, counters=True)
    a, b = _result(simd), _result(one)
    a[3].pop("fragments_tested"), b[3].pop("fragments_tested")  # the centres each way evaluates
    assert _same(a, b) and simd.counters == one.counters
    assert simd.stats["pixels_written"] == one.stats["pixels_written"]
    s = simd.stats  # large triangles binned, others rejected or dropped, pixels drawn over
    assert s["triangles_binned"] > 0 and s["triangles_rasterized"] < n and s["pixels_written"] > s["pixels_covered"]


@pytest.mark.parametrize("scratch", [True, False])
def test_a_frame_drawn_in_batches_is_the_frame_drawn_at_once(monkeypatch, scratch):
    """Triangles binned and drawn BATCH at a time (tiles a batch leaves alone untouched, the others going on from
    the images so far) give the frame and the counters of one batch."""
    from terrainwarp.kernels import raster

    scenes, (w, h) = _scenes(203, 97)
    monkeypatch.setattr(raster, "_SCRATCH", scratch)
    want = {name: rasterize_clip(*scenes[name], w, h, counters=True) for name in ("terrain", "big")}
    monkeypatch.setattr(raster, "BATCH", 5)
    for name, f in want.items():
        got = rasterize_clip(*scenes[name], w, h, counters=True)
        assert _same(_result(got), _result(f)) and got.counters == f.counters, name

"""terrainwarp.diff: every op against a float64 numpy reimplementation of the same function (forward and
central finite differences), antialias's coverage gradient at a moving silhouette, and deterministic
gradients (the same bits on two runs and for 1, 2 and 3 threads)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import terrainwarp as tw
from terrainwarp import diff
from terrainwarp.io.files import digest
from terrainwarp.kernels.parallel import set_min_items

# ------------------------------------------------------------------------------------------------
# float64 references (the rules of terrainwarp.kernels.antialias, written again in numpy)
# ------------------------------------------------------------------------------------------------


def ref_bary(c, i, j, h, w):
    px = (j + 0.5) / w * 2 - 1
    py = ((h - 1 - i) + 0.5) / h * 2 - 1
    a = c[:, 0] - px * c[:, 3]
    cc = c[:, 1] - py * c[:, 3]
    b = np.cross(a, cc)
    return b / b.sum()


def ref_depth(ids, clip, tri, i, j):
    t = ids[i, j]
    if t < 0:
        return np.inf
    c = clip[tri[t]]
    b = ref_bary(c, i, j, *ids.shape)
    return (b @ c[:, 2]) / (b @ c[:, 3])


def ref_facing(clip, tri, t):
    c = clip[tri[t]][:, [0, 1, 3]]
    return np.sign(np.linalg.det(c))


def cross2(a, b):
    return a[0] * b[1] - a[1] * b[0]


def ref_pair(ids, clip, tri, nbr, a, b):
    """(T, k, alpha) of the pixel pair (A, B), or None."""
    h, w = ids.shape
    ta, tb = ids[a], ids[b]
    if ta == tb:
        return None
    da, db = ref_depth(ids, clip, tri, *a), ref_depth(ids, clip, tri, *b)
    t = ta if (da < db or (da == db and 0 <= ta < tb)) else tb
    if t < 0:
        return None
    pa = np.array([a[1] + 0.5, h - 1 - a[0] + 0.5])
    pb = np.array([b[1] + 0.5, h - 1 - b[0] + 0.5])
    for k in range(3):
        n = nbr[t, k]
        sil = n < 0 or ref_facing(clip, tri, n) != ref_facing(clip, tri, t)
        c0, c1 = clip[tri[t, k]], clip[tri[t, (k + 1) % 3]]
        if not (sil and c0[3] > 0 and c1[3] > 0):
            continue
        v0 = c0[:2] / c0[3] * [w / 2, h / 2] + [w / 2, h / 2]
        v1 = c1[:2] / c1[3] * [w / 2, h / 2] + [w / 2, h / 2]
        e = v1 - v0
        fa = cross2(e, pa - v0)
        fb = cross2(e, pb - v0)
        s = pb - pa
        steep = abs(e[0]) <= abs(e[1])  # a horizontal pair takes steep edges, a vertical pair the others
        if fa * fb < 0 and cross2(s, v0 - pa) * cross2(s, v1 - pa) <= 0 and steep == (a[0] == b[0]):
            return t, k, fa / (fa - fb)
    return None


def ref_antialias(color, ids, clip, tri, nbr):
    color = np.asarray(color, np.float64)
    clip = np.asarray(clip, np.float64)
    out = color.copy()
    h, w = ids.shape
    for i in range(h):
        for j in range(w):
            for b in ((i, j + 1), (i + 1, j)):
                if b[0] >= h or b[1] >= w:
                    continue
                r = ref_pair(ids, clip, tri, nbr, (i, j), b)
                if r is None:
                    continue
                alpha = r[2]
                out[i, j] += max(0.5 - alpha, 0) * (color[b] - color[i, j])
                out[b] += max(alpha - 0.5, 0) * (color[i, j] - color[b])
    return out


def ref_displace(heights, dx, dz, uv, eye):
    hh = np.asarray(heights, np.float64)
    rows, cols = hh.shape
    u = np.clip(uv[:, 0] * (cols - 1), 0, cols - 1)
    v = np.clip(uv[:, 1] * (rows - 1), 0, rows - 1)
    j0, i0 = np.floor(u).astype(int), np.floor(v).astype(int)
    j1, i1 = np.minimum(j0 + 1, cols - 1), np.minimum(i0 + 1, rows - 1)
    fu, fv = u - j0, v - i0
    y = (hh[i0, j0] * (1 - fu) * (1 - fv) + hh[i0, j1] * fu * (1 - fv) + hh[i1, j0] * (1 - fu) * fv
         + hh[i1, j1] * fu * fv)
    return np.stack([u * dx - eye[0], y - eye[1], v * dz - eye[2]], axis=1)


def fd_grad(fun, x, eps):
    x = np.asarray(x, np.float64)
    g = np.zeros_like(x)
    for k in np.ndindex(x.shape):
        xp, xm = x.copy(), x.copy()
        xp[k] += eps
        xm[k] -= eps
        g[k] = (fun(xp) - fun(xm)) / (2 * eps)
    return g


# ------------------------------------------------------------------------------------------------
# scenes
# ------------------------------------------------------------------------------------------------


def occluder_scene():
    """A quad (two triangles) in front of a larger quad, both partly off a 24 x 18 image: silhouette edges
    over the background and over the far quad (occlusion)."""
    w, h = 24, 18
    far = [[-2.5, -1.6, -6.0], [2.2, -1.8, -6.5], [2.4, 1.7, -6.2], [-2.3, 1.5, -5.8]]
    near = [[-0.9, -0.7, -3.0], [0.8, -0.5, -3.1], [0.7, 0.75, -2.9], [-0.6, 0.6, -3.2]]
    pos = np.array(far + near, np.float32)
    tri = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]], np.int32)
    cam = tw.Camera(position=(0, 0, 0), target=(0, 0, -1), width=w, height=h, near=0.5, far=50.0)
    clip = np.asarray(diff.clip_positions(pos, cam.view_matrix(), cam.proj_matrix()), np.float32)
    ids = np.asarray(diff.rasterize(clip, tri, w, h)[0])
    color = np.random.default_rng(5).uniform(0.2, 1.0, size=(h, w, 3)).astype(np.float32)
    return clip, tri, ids, color


def terrain_scene(size=9, w=20, h=14):
    """A small fBm heightmap seen low from one side: ridges occlude the terrain behind them."""
    hm = tw.Heightmap.fbm(size, seed=3, dx=10.0, max_height=60.0, feature_size=4.0)
    heights = np.asarray(hm.heights, np.float32)
    jj, ii = np.meshgrid(np.arange(size), np.arange(size))
    uv = np.stack([jj.ravel() / (size - 1), ii.ravel() / (size - 1)], 1).astype(np.float32)
    q = np.arange(size * size).reshape(size, size)
    a, b, c, d = q[:-1, :-1].ravel(), q[:-1, 1:].ravel(), q[1:, :-1].ravel(), q[1:, 1:].ravel()
    tri = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)]).astype(np.int32)
    ext = (size - 1) * 10.0
    eye = np.array([ext * 0.5, 70.0, -25.0], np.float32)
    cam = tw.Camera(position=(0, 0, 0), target=(0, -20.0, ext * 0.6 + 25.0), width=w, height=h, near=1.0,
                    far=2000.0)
    return heights, uv, tri, eye, cam


# ------------------------------------------------------------------------------------------------
# rasterize
# ------------------------------------------------------------------------------------------------


def test_rasterize_gives_tw_rasterize_pixels_under_jit(jax_device):
    clip, tri, ids, _ = occluder_scene()
    f = tw.kernels.raster.rasterize_clip(clip, tri, 24, 18)
    jids, depth = jax.jit(lambda c: diff.rasterize(c, tri, 24, 18))(jnp.asarray(clip))
    assert np.array_equal(np.asarray(jids), f.triangle_id) and np.array_equal(np.asarray(depth), f.depth)
    assert set(np.unique(ids)) == {-1, 0, 1, 2, 3}
    with pytest.raises(ValueError, match="clip"):
        diff.rasterize(clip[:, :3], tri, 24, 18)
    with pytest.raises(ValueError, match="width"):
        diff.rasterize(clip, tri, 0, 18)


def test_topology_pairs_triangles_across_shared_edges():
    tri = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6]], np.int32)
    assert diff.topology(tri).tolist() == [[-1, -1, 1], [0, -1, -1], [-1, -1, -1]]


# ------------------------------------------------------------------------------------------------
# antialias
# ------------------------------------------------------------------------------------------------


def test_antialias_forward_matches_the_float64_reference(jax_device):
    clip, tri, ids, color = occluder_scene()
    nbr = diff.topology(tri)
    out = np.asarray(diff.antialias(color, ids, clip, tri, nbr))
    ref = ref_antialias(color, ids, clip, tri, nbr)
    np.testing.assert_allclose(out, ref, atol=2e-5)
    changed = np.abs(ref - color).max(2) > 1e-6
    assert changed.sum() > 20  # silhouettes over background and over the far quad
    # the diagonal inside the near quad is no silhouette: pixels that see only its two triangles keep
    # their colours, though their ids differ from a neighbour's
    p = np.pad(ids, 1, constant_values=2)
    hood = [p[1:-1, 1:-1], p[:-2, 1:-1], p[2:, 1:-1], p[1:-1, :-2], p[1:-1, 2:]]
    inner = np.all([np.isin(q, (2, 3)) for q in hood], 0) & np.any([q != hood[0] for q in hood[1:]], 0)
    assert inner.sum() >= 3 and np.array_equal(out[inner], color[inner])


def test_antialias_gradients_match_finite_differences(jax_device):
    clip, tri, ids, color = occluder_scene()
    nbr = diff.topology(tri)
    wts = np.random.default_rng(6).normal(size=color.shape).astype(np.float32)
    gcol, gclip = jax.grad(lambda c, k: jnp.sum(diff.antialias(c, ids, k, tri, nbr) * wts), argnums=(0, 1))(
        jnp.asarray(color), jnp.asarray(clip))
    fd_clip = fd_grad(lambda k: (ref_antialias(color, ids, k, tri, nbr) * wts).sum(), clip, 1e-5)
    scale = np.abs(fd_clip).max()
    assert scale > 1.0
    np.testing.assert_allclose(np.asarray(gclip), fd_clip, rtol=1e-3, atol=2e-3 * scale)
    # linear in the colours: the gradient is exact; check a few pixels around the silhouettes by FD
    g = np.asarray(gcol)
    ys, xs = np.nonzero(np.abs(ref_antialias(color, ids, clip, tri, nbr) - color).max(2) > 1e-6)
    for y, x in list(zip(ys, xs))[:8]:
        for yy, xx in ((y, x), (min(y + 1, 17), x), (y, min(x + 1, 23))):
            def f(v, yy=yy, xx=xx):
                c = color.astype(np.float64).copy()
                c[yy, xx, 0] = v[0]
                return (ref_antialias(c, ids, clip, tri, nbr) * wts).sum()
            fd = fd_grad(f, color[yy, xx, :1], 1e-3)[0]
            assert abs(g[yy, xx, 0] - fd) < 1e-4 * max(1.0, abs(fd))


def _coverage(clip, tri, nbr, w, h):
    """Sum of the antialiased coverage image of a white mesh on black (the full pipeline, ids included)."""
    ids, _ = diff.rasterize(clip, tri, w, h)
    one = diff.interpolate(jnp.ones((clip.shape[0], 1)), ids, clip, tri)
    return jnp.sum(diff.antialias(one, ids, clip, tri, nbr))


def test_antialias_moves_a_silhouette_across_pixel_centres(jax_device):
    """One white triangle on black: the antialiased coverage sum approximates the triangle's area in pixels,
    a continuous function of the vertices (up to jumps of about half a pixel where the ids change near a
    vertex), although the ids change whenever an edge crosses a pixel centre. Moving one vertex by 3 pixels
    each way (the ids re-rasterized at every step, the edges crossing several pixel centres), the gradients
    along the way average to the secant slope of the coverage and to the derivative of the area; each one
    is nonzero, of the right sign."""
    w, h = 32, 24
    clip = np.array([[-0.62, -0.55, 0.0, 1.0], [0.71, -0.4, 0.0, 1.0], [0.05, 0.66, 0.0, 1.0]], np.float32)
    tri = np.array([[0, 1, 2]], np.int32)
    nbr = diff.topology(tri)
    grad = jax.jit(jax.grad(_coverage), static_argnums=(3, 4))
    for v, ax in ((2, 0), (2, 1), (0, 0), (1, 1)):
        px = 2.0 / (w if ax == 0 else h)  # one pixel in NDC
        steps = np.linspace(-3, 3, 13) * px
        gs, cov = [], []
        for d in steps:
            c = clip.copy()
            c[v, ax] += d
            gs.append(float(np.asarray(grad(jnp.asarray(c), tri, nbr, w, h))[v, ax]))
            cov.append(float(_coverage(jnp.asarray(c), tri, nbr, w, h)))
        # area in pixels = |cross| / 2 of the window positions: linear in one coordinate of one vertex
        p = clip[:, :2] * [w / 2, h / 2]
        e = p[(v + 2) % 3] - p[(v + 1) % 3]
        darea = 0.5 * (-e[1] if ax == 0 else e[0]) * (w / 2 if ax == 0 else h / 2)
        secant = (cov[-1] - cov[0]) / (steps[-1] - steps[0])
        # the vertex regions are approximate (a pair whose crossing edge is filtered along the other axis
        # is not blended): a few per cent over edges 10 to 20 pixels long
        tol = 0.08 * abs(darea) + 1.5
        assert abs(np.mean(gs) - secant) < tol and abs(np.mean(gs) - darea) < tol, (v, ax, np.mean(gs), secant, darea)
        assert np.all(np.sign(gs) == np.sign(darea)) and np.all(np.abs(gs) > 0.2 * abs(darea)), (v, ax, gs)


def test_antialias_gradient_through_occlusion_on_a_terrain():
    """A terrain's skyline and ridges: the gradient of its coverage with respect to the heights comes only
    through antialias (interpolating ones gives ones, up to rounding, wherever the heights move)."""
    heights, uv, tri, eye, cam = terrain_scene()
    nbr = diff.topology(tri)
    view, proj = cam.view_matrix(), cam.proj_matrix()

    def image(hh, aa):
        pos = diff.displace(hh, 10.0, 10.0, uv, eye)
        clip = diff.clip_positions(pos, view, proj)
        ids, _ = diff.rasterize(clip, tri, cam.width, cam.height)
        col = diff.interpolate(jnp.ones((len(uv), 1)), ids, clip, tri)
        return diff.antialias(col, ids, clip, tri, nbr) if aa else col

    g_aa = np.asarray(jax.grad(lambda hh: jnp.sum(image(hh, True)))(jnp.asarray(heights)))
    g_no = np.asarray(jax.grad(lambda hh: jnp.sum(image(hh, False)))(jnp.asarray(heights)))
    assert np.abs(g_no).max() < 1e-5 and np.abs(g_aa).max() > 0.1


# ------------------------------------------------------------------------------------------------
# displace
# ------------------------------------------------------------------------------------------------


def test_displace_matches_the_reference_and_its_gradients(jax_device):
    rng = np.random.default_rng(7)
    heights = rng.uniform(0, 50, (5, 7)).astype(np.float32)
    uv = np.concatenate([rng.uniform(0, 1, (40, 2)), [[0, 0], [1, 1], [1, 0], [0.5, 1.0]]]).astype(np.float32)
    eye = np.array([30.0, 80.0, -10.0], np.float32)
    pos = np.asarray(diff.displace(heights, 10.0, 12.0, uv, eye))
    np.testing.assert_allclose(pos, ref_displace(heights, 10.0, 12.0, uv, eye), atol=2e-4)
    wts = rng.normal(size=pos.shape)
    gh, ge = jax.grad(lambda hh, e: jnp.sum(diff.displace(hh, 10.0, 12.0, uv, e) ** 2 * wts), argnums=(0, 1))(
        jnp.asarray(heights), jnp.asarray(eye))
    fd_h = fd_grad(lambda hh: (ref_displace(hh, 10.0, 12.0, uv, eye) ** 2 * wts).sum(), heights, 1e-3)
    fd_e = fd_grad(lambda e: (ref_displace(heights, 10.0, 12.0, uv, e) ** 2 * wts).sum(), eye, 1e-3)
    np.testing.assert_allclose(np.asarray(gh), fd_h, rtol=1e-3, atol=1e-2)
    np.testing.assert_allclose(np.asarray(ge), fd_e, rtol=1e-3, atol=1e-1)
    with pytest.raises(ValueError, match="uv"):
        diff.displace(heights, 10.0, 12.0, uv[:, :1], eye)


def test_displace_at_grid_uv_is_the_grid_mesh(jax_device):
    heights, uv, tri, eye, _ = terrain_scene()
    pos = np.asarray(diff.displace(heights, 10.0, 10.0, uv, eye))
    size = heights.shape[0]
    jj, ii = np.meshgrid(np.arange(size), np.arange(size))
    want = np.stack([jj.ravel() * 10.0 - eye[0], heights.ravel() - eye[1], ii.ravel() * 10.0 - eye[2]], 1)
    np.testing.assert_allclose(pos, want, atol=1e-3)


# ------------------------------------------------------------------------------------------------
# determinism
# ------------------------------------------------------------------------------------------------


def _pipeline_grads():
    heights, uv, tri, eye, cam = terrain_scene(size=17, w=48, h=32)
    nbr = diff.topology(tri)
    view, proj = cam.view_matrix(), cam.proj_matrix()
    shade = jnp.asarray(np.random.default_rng(8).uniform(0, 1, (len(uv), 3)), jnp.float32)

    def loss(hh, e, s):
        clip = diff.clip_positions(diff.displace(hh, 10.0, 10.0, uv, e), view, proj)
        ids, _ = diff.rasterize(clip, tri, cam.width, cam.height)
        img = diff.antialias(diff.interpolate(s, ids, clip, tri), ids, clip, tri, nbr)
        return jnp.sum(jnp.sin(3.0 * img))

    g = jax.grad(loss, argnums=(0, 1, 2))(jnp.asarray(heights), jnp.asarray(eye), shade)
    return digest(*[np.asarray(x) for x in g]), g


def test_gradients_are_bit_identical_across_runs_and_thread_counts(jax_device):
    base, g = _pipeline_grads()
    assert all(np.abs(np.asarray(x)).max() > 0 for x in g)
    assert _pipeline_grads()[0] == base
    set_min_items(1)  # split even these tiny launches as finely as the threads allow
    try:
        for n in (1, 2, 3):
            tw.kernels.parallel.set_threads(n)
            assert _pipeline_grads()[0] == base, n
    finally:
        tw.kernels.parallel.set_threads(None)
        set_min_items(None)

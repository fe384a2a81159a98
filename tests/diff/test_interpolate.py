"""The differentiable resolve (``terrainwarp.diff.interpolate``, kernels/gradients.py): perspective-correct
interpolation against a float64 reference and an analytic plane, and its JAX gradients against finite
differences."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import terrainwarp as tw
from terrainwarp.diff import clip_positions
from terrainwarp.diff import interpolate as jinterp
from terrainwarp.kernels.raster import rasterize, rasterize_clip


def interpolate(attr, ids, clip, tri):
    return np.asarray(jinterp(attr, ids, clip, tri))


def ref_interpolate(attr, ids, clip, tri):
    """float64 numpy reference of the same formula (barycentrics from clip coords at pixel centres)."""
    attr = np.asarray(attr, np.float64)
    clip = np.asarray(clip, np.float64)
    h, w = ids.shape
    out = np.zeros((h, w, attr.shape[1]))
    ys, xs = np.nonzero(ids >= 0)
    t = ids[ys, xs]
    nx = (xs + 0.5) / w * 2 - 1
    ny = ((h - 1 - ys) + 0.5) / h * 2 - 1
    c = clip[tri[t]]  # (k, 3, 4)
    a = c[..., 0] - nx[:, None] * c[..., 3]
    cc = c[..., 1] - ny[:, None] * c[..., 3]
    b = np.cross(a, cc)
    b /= b.sum(1, keepdims=True)
    out[ys, xs] = np.einsum("kv,kvc->kc", b, attr[tri[t]])
    return out


def small_scene():
    rng = np.random.default_rng(1)
    w, h = 20, 16
    pos = np.array([[-1.0, -0.6, -3.0], [1.2, -0.5, -4.0], [0.1, 0.9, -3.5], [1.4, 1.0, -5.0],
                    [-1.3, 0.8, -2.5]], np.float32)
    tri = np.array([[0, 1, 2], [1, 3, 2], [0, 2, 4]], np.int32)
    cam = tw.Camera(position=(0, 0, 0), target=(0, 0, -1), width=w, height=h, near=0.5, far=50.0)
    view, proj = cam.view_matrix(), cam.proj_matrix()
    clip = (np.c_[pos, np.ones(len(pos))] @ (proj @ view).T).astype(np.float32)
    ids = rasterize_clip(clip, tri, w, h).triangle_id
    attr = rng.normal(size=(len(pos), 3)).astype(np.float32)
    return pos, tri, view, proj, clip, ids, attr


def test_world_position_on_a_plane_is_interpolated_perspective_correctly():
    w, h = 48, 36
    cam = tw.Camera(position=(0, 4, 0), target=(0, 0, -20), width=w, height=h, near=0.5, far=500.0)
    view, proj = cam.view_matrix(), cam.proj_matrix()
    pos = np.array([[-40, 0, 5], [40, 0, 5], [0, 0, -200]], np.float32)
    tri = np.array([[0, 1, 2]], np.int32)
    f = rasterize(pos, tri, view, proj, w, h)
    clip = (np.c_[pos, np.ones(3)] @ (proj @ view).T).astype(np.float32)
    p = interpolate(pos, f.triangle_id, clip, tri)
    m = f.triangle_id >= 0
    assert m.sum() > 300
    # analytic: the ray through each pixel centre hits y = 0
    ys, xs = np.nonzero(m)
    nx = (xs + 0.5) / w * 2 - 1
    ny = ((h - 1 - ys) + 0.5) / h * 2 - 1
    inv = np.linalg.inv(proj @ view)
    a = np.c_[nx, ny, -np.ones_like(nx), np.ones_like(nx)] @ inv.T
    b = np.c_[nx, ny, np.ones_like(nx), np.ones_like(nx)] @ inv.T
    a, b = a[:, :3] / a[:, 3:], b[:, :3] / b[:, 3:]
    hit = a + (a[:, 1] / (a[:, 1] - b[:, 1]))[:, None] * (b - a)
    err = np.abs(p[ys, xs] - hit).max(1) / np.linalg.norm(hit - cam.position, axis=1)
    assert err.max() < 1e-5
    assert np.all(p[~m] == 0)
    # screen-affine interpolation would be far off: the far half of the plane is compressed
    assert np.ptp(p[ys, xs, 2]) > 50
    # barycentrics from the visibility pass agree with the resolve
    bary = np.c_[f.barycentrics[ys, xs], 1 - f.barycentrics[ys, xs].sum(1)]
    assert np.abs(bary @ pos - p[ys, xs]).max() < 1e-3


def test_forward_matches_the_float64_reference_and_is_deterministic():
    pos, tri, view, proj, clip, ids, attr = small_scene()
    out = interpolate(attr, ids, clip, tri)
    assert out.shape == ids.shape + (3,)
    np.testing.assert_allclose(out, ref_interpolate(attr, ids, clip, tri), atol=2e-5)
    assert np.array_equal(out, interpolate(attr, ids, clip, tri))
    one = interpolate(attr[:, 0], ids, clip, tri)
    assert one.shape == ids.shape and np.array_equal(one, out[..., 0])
    with pytest.raises(ValueError, match="attr"):
        interpolate(attr[:3], ids, clip, tri)
    with pytest.raises(ValueError, match="clip"):
        interpolate(attr, ids, clip[:, :3], tri)


def _fd_grad(fun, x, eps):
    g = np.zeros_like(x, dtype=np.float64)
    for k in np.ndindex(x.shape):
        xp = x.astype(np.float64).copy()
        xm = xp.copy()
        xp[k] += eps
        xm[k] -= eps
        g[k] = (fun(xp) - fun(xm)) / (2 * eps)
    return g


def test_jax_gradients_through_warp_jax_kernel_match_finite_differences(jax_device):
    pos, tri, view, proj, clip, ids, attr = small_scene()
    h, w = ids.shape
    wts = np.random.default_rng(3).normal(size=(h, w, 3)).astype(np.float32)

    def loss(c, a):
        return jnp.sum(jinterp(a, ids, c, tri) * wts)

    val = loss(jnp.asarray(clip), jnp.asarray(attr))
    assert abs(float(val) - float((ref_interpolate(attr, ids, clip, tri) * wts).sum())) < 1e-3
    gc, ga = jax.grad(loss, argnums=(0, 1))(jnp.asarray(clip), jnp.asarray(attr))
    fd_attr = _fd_grad(lambda a: float((ref_interpolate(a, ids, clip, tri) * wts).sum()), attr, 1e-3)
    fd_clip = _fd_grad(lambda c: float((ref_interpolate(attr, ids, c, tri) * wts).sum()), clip, 1e-4)
    np.testing.assert_allclose(np.asarray(ga), fd_attr, rtol=1e-4, atol=1e-4)
    scale = np.abs(fd_clip).max()
    np.testing.assert_allclose(np.asarray(gc), fd_clip, rtol=1e-3, atol=1e-3 * scale)
    # under jit too, and through the camera transform to world positions
    jl = jax.jit(lambda p, a: jnp.sum(jinterp(a, ids, clip_positions(p, view, proj), tri) * wts))
    gp = np.asarray(jax.grad(jl)(jnp.asarray(pos), jnp.asarray(attr)))

    def loss_pos(p):
        c = np.c_[p, np.ones(len(p))] @ (proj @ view).T
        return float((ref_interpolate(attr, ids, c, tri) * wts).sum())

    fd_pos = _fd_grad(loss_pos, pos, 1e-4)
    np.testing.assert_allclose(gp, fd_pos, rtol=2e-3, atol=2e-3 * np.abs(fd_pos).max())


def test_background_pixels_get_zero_and_no_gradient():
    pos, tri, view, proj, clip, ids, attr = small_scene()
    bg = ids < 0
    assert bg.any()
    out = np.asarray(jinterp(attr, ids, clip, tri))
    assert np.all(out[bg] == 0)
    # a loss only on background pixels has zero gradient
    g = jax.grad(lambda a: jnp.sum(jinterp(a, ids, clip, tri) * jnp.asarray(bg)[..., None]))(jnp.asarray(attr))
    assert np.all(np.asarray(g) == 0)

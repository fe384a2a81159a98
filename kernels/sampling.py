"""Heightmap sampling on the device: bilinear and bicubic filtering as ``@wp.func`` (deaconu2021,
"Increasing terrain quality"), plus one kernel that samples a batch of points.

Grid coordinates: ``u`` is the fractional column, ``v`` the fractional row (sample (i, j) at u=j, v=i).
Samples outside the grid are clamped to the edge (texture CLAMP_TO_EDGE).

* bilinear: the usual tensor-product linear filter; reproduces any plane exactly (up to float32
  rounding of the weights).
* bicubic: the tensor-product 4-point Lagrange cubic through samples at offsets -1, 0, 1, 2. Unlike
  Keys' cubic convolution (a = -0.5, "Catmull-Rom"), which reproduces only quadratics, it reproduces
  any cubic along each axis exactly, which is what the tests check. Near the border, the 4-sample
  support reaches one sample past the grid; those samples are extrapolated linearly along each axis,
  so planes are reproduced everywhere and cubics everywhere but in the outermost cell.

Heights are sampled relative to the centre sample before weighting (a local reference), so a terrain
at 8,848 m with millimetre relief keeps its relief in float32.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .checks import check_choice
from .parallel import launch, view

# ------------------------------------------------------------------------------------------------
# functions
# ------------------------------------------------------------------------------------------------


@wp.func
def fetch(h: wp.array2d(dtype=wp.float32), i: int, j: int) -> float:
    """Clamp-to-edge fetch of sample (row i, column j)."""
    ii = wp.clamp(i, 0, h.shape[0] - 1)
    jj = wp.clamp(j, 0, h.shape[1] - 1)
    return h[ii, jj]


@wp.func
def sample_bilinear(h: wp.array2d(dtype=wp.float32), u: float, v: float) -> float:
    """Bilinear sample at fractional column u, row v (clamped to the grid)."""
    uc = wp.clamp(u, 0.0, float(h.shape[1] - 1))
    vc = wp.clamp(v, 0.0, float(h.shape[0] - 1))
    j0 = int(wp.floor(uc))
    i0 = int(wp.floor(vc))
    fu = uc - float(j0)
    fv = vc - float(i0)
    ref = fetch(h, i0, j0)
    a = 0.0
    b = fetch(h, i0, j0 + 1) - ref
    c = fetch(h, i0 + 1, j0) - ref
    d = fetch(h, i0 + 1, j0 + 1) - ref
    top = a + (b - a) * fu
    bot = c + (d - c) * fu
    return ref + (top + (bot - top) * fv)


@wp.func
def _fetch_linear_ext(h: wp.array2d(dtype=wp.float32), i: int, j: int) -> float:
    """Fetch with linear extrapolation past the border (per axis), so planes stay planes."""
    n0 = h.shape[0]
    n1 = h.shape[1]
    ii = wp.clamp(i, 0, n0 - 1)
    jj = wp.clamp(j, 0, n1 - 1)
    v = h[ii, jj]
    if i != ii and n0 > 1:
        i2 = wp.clamp(ii + wp.where(i < 0, 1, -1), 0, n0 - 1)
        v += float(wp.abs(i - ii)) * (v - h[i2, jj])
    if j != jj and n1 > 1:
        j2 = wp.clamp(jj + wp.where(j < 0, 1, -1), 0, n1 - 1)
        ii2 = wp.clamp(i, 0, n0 - 1)
        a = h[ii2, jj]
        b = h[ii2, j2]
        v += float(wp.abs(j - jj)) * (a - b)
    return v


@wp.func
def _lagrange4(t: float) -> wp.vec4:
    """Weights of the cubic Lagrange interpolant through nodes -1, 0, 1, 2 at t in [0, 1]."""
    w0 = -t * (t - 1.0) * (t - 2.0) / 6.0
    w1 = (t + 1.0) * (t - 1.0) * (t - 2.0) / 2.0
    w2 = -(t + 1.0) * t * (t - 2.0) / 2.0
    w3 = (t + 1.0) * t * (t - 1.0) / 6.0
    return wp.vec4(w0, w1, w2, w3)


@wp.func
def sample_bicubic(h: wp.array2d(dtype=wp.float32), u: float, v: float) -> float:
    """Bicubic (4x4 Lagrange) sample at fractional column u, row v (clamped to the grid)."""
    uc = wp.clamp(u, 0.0, float(h.shape[1] - 1))
    vc = wp.clamp(v, 0.0, float(h.shape[0] - 1))
    j0 = int(wp.floor(uc))
    i0 = int(wp.floor(vc))
    wu = _lagrange4(uc - float(j0))
    wv = _lagrange4(vc - float(i0))
    ref = fetch(h, i0, j0)
    acc = float(0.0)
    for a in range(4):
        row = float(0.0)
        for b in range(4):
            row += wu[b] * (_fetch_linear_ext(h, i0 - 1 + a, j0 - 1 + b) - ref)
        acc += wv[a] * row
    return ref + acc


@wp.func
def sample_height(h: wp.array2d(dtype=wp.float32), u: float, v: float, method: int) -> float:
    """method 0: bilinear, 1: bicubic."""
    if method == 1:
        return sample_bicubic(h, u, v)
    return sample_bilinear(h, u, v)


# ------------------------------------------------------------------------------------------------
# kernels
# ------------------------------------------------------------------------------------------------


@wp.kernel
def _sample_kernel(
    offset: int,
    h: wp.array2d(dtype=wp.float32),
    uv: wp.array(dtype=wp.vec2),
    method: int,
    # outputs
    out_h: wp.array(dtype=wp.float32),
):
    k = wp.tid() + offset
    p = uv[k]
    out_h[k] = sample_height(h, p[0], p[1], method)


# ------------------------------------------------------------------------------------------------
# host
# ------------------------------------------------------------------------------------------------

METHODS = {"bilinear": 0, "bicubic": 1}


def sample_grid(heights: np.ndarray, u: np.ndarray, v: np.ndarray, method: str = "bilinear",
                device: str = "cpu") -> np.ndarray:
    """Sample ``heights`` (H, W) float32 at fractional grid coordinates.

    Args:
        heights: (H, W) float32 heights.
        u, v: arrays of equal shape, fractional column and row (float32 after conversion).
        method: ``"bilinear"`` or ``"bicubic"``.

    Returns:
        float32 array of the shape of ``u``.
    """
    check_choice("method", method, METHODS)
    u = np.asarray(u, dtype=np.float32)
    v = np.asarray(v, dtype=np.float32)
    if u.shape != v.shape:
        raise ValueError(f"u, v: expected equal shapes, got {u.shape} and {v.shape}")
    shape = u.shape
    n = u.size
    if n == 0:
        return np.zeros(shape, np.float32)
    uv = np.stack([u.reshape(-1), v.reshape(-1)], axis=1)
    h = view(heights, wp.float32, device)  # the heightmap: not copied per frame on the CPU
    out = wp.empty(n, dtype=wp.float32, device=device)
    launch(_sample_kernel, dim=n, inputs=[h, wp.array(uv, dtype=wp.vec2, device=device), METHODS[method]],
           outputs=[out], device=device)
    return out.numpy().reshape(shape)

"""Analytic height fields with exact derivatives, shared by the normal/curvature tests and
benchmarks/bench_normals_curvature.py (float64 references; the heights handed to the kernels are the
float32 rounding of h)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

DIRS = ((0, 1), (1, 0), (1, 1), (-1, 1))  # (di, dj): x, z, diagonal (+x,+z), diagonal (+x,-z)


@dataclass(frozen=True)
class Surface:
    """h(x, z) with gradient (hx, hz) and Hessian (hxx, hxz, hzz), all float64 callables."""

    name: str
    h: Callable
    hx: Callable
    hz: Callable
    hxx: Callable
    hxz: Callable
    hzz: Callable


def plane(a: float = 0.3, b: float = -0.7, c: float = 0.0) -> Surface:
    z0 = lambda x, z: 0.0 * x  # noqa: E731
    return Surface("plane", lambda x, z: a * x + b * z + c, lambda x, z: a + 0 * x, lambda x, z: b + 0 * x,
                   z0, z0, z0)


def paraboloid(a: float = 0.05, b: float = -0.03, c: float = 0.02, e: float = 0.1) -> Surface:
    return Surface("paraboloid", lambda x, z: a * x * x + b * z * z + c * x * z + e * x,
                   lambda x, z: 2 * a * x + c * z + e, lambda x, z: 2 * b * z + c * x,
                   lambda x, z: 2 * a + 0 * x, lambda x, z: c + 0 * x, lambda x, z: 2 * b + 0 * x)


def sphere_cap(r: float = 40.0) -> Surface:
    def w(x, z):
        return np.sqrt(r * r - x * x - z * z)
    return Surface("sphere_cap", lambda x, z: w(x, z) - r, lambda x, z: -x / w(x, z), lambda x, z: -z / w(x, z),
                   lambda x, z: -(r * r - z * z) / w(x, z) ** 3, lambda x, z: -x * z / w(x, z) ** 3,
                   lambda x, z: -(r * r - x * x) / w(x, z) ** 3)


def cylinder_ridge(r: float = 30.0) -> Surface:
    """A cylinder of radius r with its axis along x: a ridge running along x, curved along z."""
    def w(z):
        return np.sqrt(r * r - z * z)
    z0 = lambda x, z: 0.0 * x  # noqa: E731
    return Surface("cylinder_ridge", lambda x, z: w(z) - r + 0 * x, z0, lambda x, z: -z / w(z) + 0 * x,
                   z0, z0, lambda x, z: -r * r / w(z) ** 3 + 0 * x)


def sinusoid(amp: float = 2.0, kx: float = 0.21, kz: float = 0.13) -> Surface:
    return Surface("sinusoid", lambda x, z: amp * np.sin(kx * x) * np.cos(kz * z),
                   lambda x, z: amp * kx * np.cos(kx * x) * np.cos(kz * z),
                   lambda x, z: -amp * kz * np.sin(kx * x) * np.sin(kz * z),
                   lambda x, z: -amp * kx * kx * np.sin(kx * x) * np.cos(kz * z),
                   lambda x, z: -amp * kx * kz * np.cos(kx * x) * np.sin(kz * z),
                   lambda x, z: -amp * kz * kz * np.sin(kx * x) * np.cos(kz * z))


SURFACES = {"plane": plane, "paraboloid": paraboloid, "sphere_cap": sphere_cap,
            "cylinder_ridge": cylinder_ridge, "sinusoid": sinusoid}


def grid(surf: Surface, extent_x: float, extent_z: float, dx: float, dz: float, offset: float = 0.0):
    """Sample ``surf`` centred on (0, 0): returns (float32 heights (H, W), X, Z float64 coordinates)."""
    nx = int(round(extent_x / dx)) + 1
    nz = int(round(extent_z / dz)) + 1
    x = (np.arange(nx) - (nx - 1) / 2) * dx
    z = (np.arange(nz) - (nz - 1) / 2) * dz
    xx, zz = np.meshgrid(x, z)
    return (surf.h(xx, zz) + offset).astype(np.float32), xx, zz


def exact_normals(surf: Surface, xx, zz) -> np.ndarray:
    n = np.stack([-surf.hx(xx, zz), np.ones_like(xx), -surf.hz(xx, zz)], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def exact_directional(surf: Surface, xx, zz, dx: float, dz: float) -> np.ndarray:
    """(H, W, 4) exact curvature |h_uu| / (1 + h_u^2)^(3/2) of the vertical sections in the four directions."""
    out = []
    for di, dj in DIRS:
        ln = np.hypot(dj * dx, di * dz)
        ux, uz = dj * dx / ln, di * dz / ln
        hu = surf.hx(xx, zz) * ux + surf.hz(xx, zz) * uz
        huu = surf.hxx(xx, zz) * ux * ux + 2 * surf.hxz(xx, zz) * ux * uz + surf.hzz(xx, zz) * uz * uz
        out.append(np.abs(huu) / (1 + hu * hu) ** 1.5)
    return np.stack(out, axis=-1)


def exact_edge_angle(surf: Surface, xx, zz, dx: float, dz: float) -> np.ndarray:
    """(H, W, 4) edge-angle curvature 1 - cos(turn of the chords) from exact heights (float64)."""
    out = []
    for di, dj in DIRS:
        ln = np.hypot(dj * dx, di * dz)
        hc = surf.h(xx, zz)
        hp = surf.h(xx - dj * dx, zz - di * dz)
        hn = surf.h(xx + dj * dx, zz + di * dz)
        s1, s2 = (hc - hp) / ln, (hn - hc) / ln
        c = (1 + s1 * s2) / np.sqrt((1 + s1 * s1) * (1 + s2 * s2))
        out.append(np.clip(1 - c, 0, 1))
    return np.stack(out, axis=-1)


def exact_surface(surf: Surface, xx, zz) -> np.ndarray:
    """(H, W, 4) exact mean, Gaussian, profile and plan curvature (positive on convex ground)."""
    p, q = surf.hx(xx, zz), surf.hz(xx, zz)
    r, s, t = surf.hxx(xx, zz), surf.hxz(xx, zz), surf.hzz(xx, zz)
    w = 1 + p * p + q * q
    g2 = p * p + q * q
    mean = -((1 + q * q) * r - 2 * p * q * s + (1 + p * p) * t) / (2 * w ** 1.5)
    gauss = (r * t - s * s) / w ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        prof = np.where(g2 > 0, -(p * p * r + 2 * p * q * s + q * q * t) / (g2 * w ** 1.5), 0.0)
        plan = np.where(g2 > 0, -(q * q * r - 2 * p * q * s + p * p * t) / g2 ** 1.5, 0.0)
    return np.stack([mean, gauss, prof, plan], axis=-1)


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between unit vectors, stable near 0."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1)))

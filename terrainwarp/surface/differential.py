"""Normals and curvature of a heightmap: the host API over ``terrainwarp.kernels.normals`` and
``terrainwarp.kernels.curvature``.

::

    hm = Heightmap.example()
    n = compute_normals(hm, "quad")                       # (H, W, 3) float32 unit normals
    k = compute_curvature(hm, "three_normal", scale=6.0, distance=2)   # (H, W, 4) float32
    kmax, kdir = max_curvature(k)                          # (H, W) float32, (H, W) int32 in 0..3
    gis = surface_curvature(hm)                            # dict of (H, W) mean/gaussian/profile/plan
    rgb = normal_map_image(n)                              # (H, W, 3) uint8, deaconu2021 figure 8

Every method runs as one Warp kernel over the whole grid, uses the heightmap's spacing (dx along x /
columns, dz along z / rows) and returns world units. NaN heights (``Heightmap.from_array(...,
allow_nan=True)``) are no-data holes: normals stay finite everywhere; curvature is NaN exactly at the
holes and finite everywhere else (see the kernels' module docstrings for the rules).

Measured on the real DEM ``Heightmap.example()`` (SRTM, 344 x 403, heights 236..1076 m, dx 74.6 m,
dz 92.5 m; tests/surface/test_normals.py re-measures it): Sobel normals with the paper's constant-0 border and
with clamp-to-edge are bit-identical inside and differ on every sample of the border ring, by 47.9 to
91.0 degrees (median 69.8): a 0 m outside sample beside 500 m of terrain is a 500 m cliff. Clamp itself
halves the edge-normal slope (clamp vs one-sided ``"skip"``: up to 16.5 degrees, median 3.6). Use
``border="skip"`` (exact on planes) or ``"clamp"`` on real terrain.
"""

from __future__ import annotations

import numpy as np

from ..heightmap import Heightmap
from ..kernels.checks import check_device
from ..kernels.curvature import (
    CURVATURE_METHODS,
    DIRECTIONS,
    SURFACE_FIELDS,
    SURFACE_SCHEMES,
    directional_curvature,
    surface_curvature_planes,
)
from ..kernels.curvature import max_curvature as _max_curvature
from ..kernels.normals import METHODS as NORMAL_METHODS
from ..kernels.normals import decode_normal_map, encode_normal_map, vertex_normals

__all__ = ["compute_normals", "compute_curvature", "surface_curvature", "max_curvature", "normal_map_image",
           "decode_normal_map", "NORMAL_METHODS", "CURVATURE_METHODS", "DIRECTIONS", "SURFACE_SCHEMES",
           "SURFACE_FIELDS"]


def _unpack(heightmap: Heightmap | np.ndarray, dx: float | None,
            dz: float | None) -> tuple[np.ndarray, float, float]:
    if isinstance(heightmap, Heightmap):
        if dx is not None or dz is not None:
            raise ValueError("dx, dz: give them only with a plain array (a Heightmap has its own spacing)")
        return heightmap.heights, heightmap.dx, heightmap.dz
    if isinstance(heightmap, np.ndarray):
        if heightmap.ndim != 2 or heightmap.size == 0:
            raise ValueError(f"heightmap: expected a non-empty (H, W) array, got shape {heightmap.shape}")
        if not (np.issubdtype(heightmap.dtype, np.floating) or np.issubdtype(heightmap.dtype, np.integer)):
            raise TypeError(f"heightmap: expected a float or integer array, got dtype {heightmap.dtype}")
        d = 1.0 if dx is None else dx
        return heightmap, d, d if dz is None else dz
    raise TypeError(f"heightmap: expected a Heightmap or a 2D numpy array, got {type(heightmap).__name__}")


def compute_normals(heightmap: Heightmap | np.ndarray, method: str = "sobel", *, border: str = "constant",
                    constant: float = 0.0, dx: float | None = None, dz: float | None = None,
                    device: str = "cpu") -> np.ndarray:
    """Per-vertex unit normals.

    Args:
        heightmap: a :class:`Heightmap`, or an (H, W) array with ``dx``/``dz`` (default 1 m).
        method: ``"sobel"`` (deaconu2021), ``"edge"``, ``"triangle"`` or ``"quad"`` (curtis2004).
        border: for ``"sobel"``: ``"constant"`` (outside samples = ``constant``, 0 by default, as the
            paper says; tilts border normals on high terrain), ``"clamp"`` (repeat the edge sample) or
            ``"skip"`` (one-sided differences). The other methods always skip outside samples.
        constant: outside height for ``border="constant"`` (metres).

    Returns:
        (H, W, 3) float32 unit normals (x, y, z), y up, finite everywhere (also at NaN holes).
        Not differentiable (discrete kernel).
    """
    h, dx_, dz_ = _unpack(heightmap, dx, dz)
    check_device("device", device)
    return vertex_normals(h, dx_, dz_, method=method, border=border, constant=constant, device=device)


def compute_curvature(heightmap: Heightmap | np.ndarray, method: str = "three_normal", *, scale: float = 1.0,
                      distance: int = 1, normals: str = "quad", dx: float | None = None,
                      dz: float | None = None, device: str = "cpu") -> np.ndarray:
    """Directional curvature of curtis2004 in the four directions x, z, diagonal (+x,+z), diagonal (+x,-z).

    Args:
        heightmap: a :class:`Heightmap`, or an (H, W) array with ``dx``/``dz``.
        method: ``"two_normal"``, ``"three_normal"``, ``"three_vertex"`` or ``"edge_angle"``.
        scale: curtis2004's curvature scale (multiplies every value).
        distance: ``three_normal`` reinforcement distance (1 = none).
        normals: vertex normals used by the normal-based methods (``"quad"``, as the paper).

    Returns:
        (H, W, 4) float32 >= 0 (NaN at NaN heights): Equation 1, ``|y''| / (1 + y'^2)^(3/2)``, in 1/m times
        ``scale`` (1/m^2 when reinforced), or 1 - cos(angle) in [0, 1] times ``scale`` for
        ``edge_angle``. Not differentiable.
    """
    h, dx_, dz_ = _unpack(heightmap, dx, dz)
    check_device("device", device)
    return directional_curvature(h, dx_, dz_, method=method, scale=scale, distance=distance, normals=normals,
                                 device=device)


def surface_curvature(heightmap: Heightmap | np.ndarray, scheme: str = "zevenbergen_thorne", *,
                      dx: float | None = None, dz: float | None = None,
                      device: str = "cpu") -> dict[str, np.ndarray]:
    """GIS surface curvatures (Zevenbergen-Thorne or Evans-Young 3x3 fits).

    Returns:
        dict with (H, W) float32 arrays ``mean`` (1/m), ``gaussian`` (1/m^2), ``profile`` (1/m, normal
        curvature along the gradient) and ``plan`` (1/m, curvature of the contour line); positive on
        convex ground; NaN at NaN heights.
    """
    h, dx_, dz_ = _unpack(heightmap, dx, dz)
    k = surface_curvature_planes(h, dx_, dz_, scheme=scheme, device=device)
    return dict(zip(SURFACE_FIELDS, k, strict=True))  # each plane contiguous, no copy


def max_curvature(curvature: np.ndarray, device: str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """((H, W) float32 max over the four directions, (H, W) int32 its direction index into
    ``DIRECTIONS``; -1 at NaN holes)."""
    return _max_curvature(curvature, device=device)


def normal_map_image(normals: np.ndarray, layout: str = "xzy", device: str = "cpu") -> np.ndarray:
    """(H, W, 3) uint8 RGB normal map (deaconu2021 figure 8): ``round((n * 0.5 + 0.5) * 255)``, with
    R = n.x, G = n.z, B = n.y (up) for ``layout="xzy"``; write it with ``terrainwarp.io.files.write_image``."""
    return encode_normal_map(normals, layout=layout, device=device)

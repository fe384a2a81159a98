"""LOD policies: the policy objects the quadtree selects with, the one map from a :class:`LodConfig` to
its policy object, and the continuous policy's per-edge factor rule.

What a policy *is* (its name, the ``LodConfig`` field that holds its parameter, the fit's range, which
way is coarser, how its numbers are validated) is the table ``terrainwarp.scene.POLICY_TABLE``; this module
maps each row to a class. The continuous factor rule (:func:`edge_pixels`, :func:`continuous_factors`)
is the one used by :func:`terrainwarp.lod.select`, the fit's relaxed model and the differentiable path
(which evaluate the same function with ``jax.numpy``). Beside it, :func:`dx11_edge_pixels`: the NVIDIA DX11
terrain sample's per-edge screen size, and how it maps onto ``edge_pixels`` (not the same rule); and Cesium's
heightmap-terrain rule (:func:`cesium_level_error`, :func:`cesium_sse`, :func:`cesium_refines`), which the
``cesium`` scheme (:mod:`terrainwarp.lod.cesium`, a ``LodConfig.policy`` like the others) selects with.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, fields
from types import ModuleType

import numpy as np

from ..camera import Camera
from ..heightmap import Heightmap
from ..scene import MAX_LOG_SCALE, MAX_TESS, POLICY_TABLE, LodConfig, check_policy_numbers

__all__ = ["DistancePolicy", "ScreenErrorPolicy", "ContinuousPolicy", "Policy", "POLICY_CLASSES", "make_policy",
           "check_policy", "edge_pixels", "dx11_edge_pixels", "continuous_factors", "MAX_TESS", "EDGE_PX_MAX", "EDGES",
           "cesium_level_error", "cesium_sse", "cesium_refines", "CESIUM_TILE_SAMPLES", "CESIUM_HEIGHTMAP_QUALITY",
           "CESIUM_DEFAULT_SSE"]

# the projected length given to an edge whose midpoint is the eye (distance 0): any target gives MAX_TESS,
# and it stays finite so that float32 derivatives through the rule stay finite (zero where clamped)
EDGE_PX_MAX = 1e20
# a patch's edges in OpenGL order as pairs of corners (du, dv): u=0 (west), v=0 (north), u=1 (east), v=1 (south)
EDGES = (((0, 0), (0, 1)), ((0, 0), (1, 0)), ((1, 0), (1, 1)), ((0, 1), (1, 1)))


# ------------------------------------------------------------------------------------------------
# policy objects
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DistancePolicy:
    """Split while the distance from the eye to the node's box is below the level's threshold
    (deaconu2021 "Rendering"). ``thresholds[L]`` in metres; default ``k * node_size(L) * exp(level_scale[L])``
    (``level_scale``: :attr:`terrainwarp.LodConfig.level_log_scale`; levels past its end: 0)."""

    k: float = 2.0
    thresholds: tuple[float, ...] | None = None
    hysteresis: float = 0.0
    code: int = 0
    level_scale: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        check_policy_numbers("distance", self.k, self.hysteresis)
        if self.thresholds is not None and not all(np.isfinite(t) and t >= 0 for t in self.thresholds):
            raise ValueError("thresholds: expected finite distances >= 0 in metres")
        _check_scales(self.level_scale)

    def threshold(self, level: int, node_size_m: float) -> float:
        """The split threshold (m) at ``level``, whose nodes are ``node_size_m`` metres wide."""
        if self.thresholds is not None:
            if level >= len(self.thresholds):
                return 0.0
            return float(self.thresholds[level])
        return self.k * node_size_m * _scale(self.level_scale, level)


@dataclass(frozen=True)
class ScreenErrorPolicy:
    """Split while the projected geometric error exceeds ``tolerance_px * exp(level_scale[L])`` pixels at level L
    (malafeev2014; Cesium's maximumScreenSpaceError): ``sse = geometric_error * focal_px / dist``
    (``level_scale``: :attr:`terrainwarp.LodConfig.level_log_scale`; levels past its end: 0)."""

    tolerance_px: float = 1.0
    hysteresis: float = 0.0
    code: int = 1
    level_scale: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        check_policy_numbers("sse", self.tolerance_px, self.hysteresis)
        _check_scales(self.level_scale)

    def threshold(self, level: int, node_size_m: float) -> float:
        return float(self.tolerance_px) * _scale(self.level_scale, level)


@dataclass(frozen=True)
class ContinuousPolicy:
    """Every node of one ``level`` (a uniform patch grid), frustum-culled, with continuous per-edge
    factors for fractional spacing (:func:`continuous_factors` of :func:`edge_pixels`: one factor per
    edge, computed from the edge's own endpoints)."""

    target_px: float = 8.0
    level: int = 0
    hysteresis: float = 0.0
    code: int = 2

    def __post_init__(self) -> None:
        check_policy_numbers("continuous", self.target_px, self.hysteresis, self.level)

    def threshold(self, level: int, node_size_m: float) -> float:
        return 0.0


def _check_scales(scales: tuple[float, ...]) -> None:
    if not all(np.isfinite(m) and abs(m) <= MAX_LOG_SCALE for m in scales):
        raise ValueError(f"level_scale: expected finite log multipliers in [-{MAX_LOG_SCALE:g}, {MAX_LOG_SCALE:g}], "
                         f"got {scales!r}")


def _scale(scales: tuple[float, ...], level: int) -> float:
    """``exp(scales[level])``, 1 past the end (the same rule as :meth:`LodConfig.level_threshold_scale`)."""
    return math.exp(scales[level]) if level < len(scales) else 1.0


Policy = DistancePolicy | ScreenErrorPolicy | ContinuousPolicy
POLICY_CLASSES: dict[str, type] = {"sse": ScreenErrorPolicy, "distance": DistancePolicy,
                                   "continuous": ContinuousPolicy}


def make_policy(config: LodConfig) -> Policy:
    """The policy object of a :class:`terrainwarp.LodConfig`: the class of its ``POLICY_TABLE`` row,
    given the row's parameter field, the hysteresis and the fields the row ``reads``. Both are frozen: the object
    made for an equal configuration is returned again (the last 256 kept; a render asks once per frame)."""
    if not isinstance(config, LodConfig):
        raise TypeError(f"config: expected a LodConfig, got {type(config).__name__}")
    try:
        hash(config)
    except TypeError:  # a field holding something unhashable: made afresh
        return _make_policy(config)
    return _kept_policy(config)


@functools.lru_cache(maxsize=256)
def _kept_policy(config: LodConfig) -> Policy:
    return _make_policy(config)


def _make_policy(config: LodConfig) -> Policy:
    if config.is_scheme:
        raise ValueError(f"config: the scheme {config.policy!r} is drawn by its mesh source "
                         f"(terrainwarp.rendering.sources.scene_source), not by a quadtree policy object")
    spec = POLICY_TABLE[config.policy]
    kw = {spec.field: float(config.value), "hysteresis": float(config.hysteresis)}
    kw.update({f: int(getattr(config, f)) for f in spec.reads})
    if config.level_log_scale and "level_scale" in {f.name for f in fields(POLICY_CLASSES[config.policy])}:
        kw["level_scale"] = tuple(config.level_log_scale)
    return POLICY_CLASSES[config.policy](**kw)


def check_policy(policy: object) -> None:
    """TypeError unless ``policy`` is one of the policy objects (their numbers are checked when made)."""
    if not isinstance(policy, DistancePolicy | ScreenErrorPolicy | ContinuousPolicy):
        raise TypeError(f"policy: expected DistancePolicy, ScreenErrorPolicy or ContinuousPolicy, got "
                        f"{type(policy).__name__}")


# ------------------------------------------------------------------------------------------------
# the continuous per-edge factor rule
# ------------------------------------------------------------------------------------------------
def edge_pixels(heightmap: Heightmap, eye: tuple[float, float, float], focal_px: float, origin: np.ndarray,
                size: np.ndarray) -> np.ndarray:
    """(P, 4) float64 projected length in pixels of each patch edge (``EDGES`` order): ``L * focal_px / d``,
    L the edge's 3-D length between its endpoints (heights sampled from the heightmap), d the distance from
    the eye to the edge's midpoint; ``EDGE_PX_MAX`` where d = 0. Symmetric in the endpoints, so the two
    patches sharing an edge get the same value bit for bit.

    Args:
        origin: (P, 2) float64 world (x, z) of each patch's (u, v) = (0, 0) corner; size: (P, 2) its extent.
    """
    e = np.asarray(eye, dtype=np.float64)
    x0, z0 = origin[:, 0], origin[:, 1]
    xz = {(du, dv): (x0 + du * size[:, 0] if du else x0, z0 + dv * size[:, 1] if dv else z0)
          for du in (0, 1) for dv in (0, 1)}
    pts = {c: np.stack([x, heightmap.sample(x, z).astype(np.float64), z], axis=1) for c, (x, z) in xz.items()}
    out = []
    for a, b in EDGES:
        pa, pb = pts[a], pts[b]
        length = np.linalg.norm(pb - pa, axis=1)
        d = np.linalg.norm(0.5 * (pa + pb) - e, axis=1)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            px = np.where(d > 0, length * focal_px / np.where(d > 0, d, 1.0), EDGE_PX_MAX)
        out.append(np.minimum(px, EDGE_PX_MAX))
    return np.stack(out, axis=1)


def dx11_edge_pixels(heightmap: Heightmap, camera: Camera, origin: np.ndarray, size: np.ndarray) -> np.ndarray:
    """(P, 4) float64 the NVIDIA DX11 terrain tessellation sample's per-edge screen size, in the same units
    and edge order as :func:`terrainwarp.lod.policies.edge_pixels` (so both divide by a target in pixels).

    The sample (``SphereToScreenSpaceTessellation``, hull shader) projects a sphere around each edge: the
    view-space edge midpoint ``c`` and ``c + (D, 0, 0)`` (``D`` the tile's side, the sphere's diameter) are
    projected, their NDC x difference is scaled by the screen size (skipping the NDC-to-pixel halving), and
    the factor is ``clamp(that / g_tessellatedTriWidth, 0, 64)``. In pixels::

        dx11 = 2 * D * focal_px / z_view        (z_view: the midpoint's depth along the view axis)
        ours = L * focal_px / d                 (edge_pixels: L the 3-D edge length, d the eye distance)

    so ``dx11 = ours * 2 * (D / L) * (d / z_view)``. **Not the same rule**: it equals ours exactly with
    ``target_px = tri_width / 2`` only for a level edge (``L = D``) whose midpoint lies on the view axis
    (``d = z_view``). Off axis it asks for more triangles by ``d / z_view = 1 / cos(angle off the view
    axis)`` (up to 1.25 in the corners of a 60-degree 16:9 view), and on a slope fewer by ``D / L`` (the
    sample's diameter is horizontal); both rules are symmetric in the edge's endpoints, so both are
    crack-free. The sample then rounds factors at LOD neighbours up to powers of two, which ours does not
    need (fractional spacing with matching edge factors).

    Args:
        origin: (P, 2) float64 world (x, z) of each patch's (u, v) = (0, 0) corner; size: (P, 2) its extent.
    """
    view = camera.view_matrix()
    x0, z0 = origin[:, 0], origin[:, 1]
    out = []
    for (ua, va), (ub, vb) in EDGES:
        xa, za = x0 + ua * size[:, 0], z0 + va * size[:, 1]
        xb, zb = x0 + ub * size[:, 0], z0 + vb * size[:, 1]
        ya, yb = heightmap.sample(xa, za).astype(np.float64), heightmap.sample(xb, zb).astype(np.float64)
        mid = np.stack([0.5 * (xa + xb), 0.5 * (ya + yb), 0.5 * (za + zb), np.ones_like(xa)], 1)
        z_view = -(mid @ view.T)[:, 2]
        diam = np.hypot(xb - xa, zb - za)
        out.append(np.where(z_view > 0, 2.0 * diam * camera.focal_px / np.where(z_view > 0, z_view, 1.0), np.inf))
    return np.stack(out, 1)


def continuous_factors(edge_px, target_px, xp: ModuleType = np, clamp: Callable | None = None):
    """The continuous policy's tessellation factors: ``outer = clamp(edge_px / target_px, 1, MAX_TESS)`` per
    edge, ``inner`` = (mean of the v=0 and v=1 edges, mean of the u=0 and u=1 edges).

    One rule for every caller: :func:`terrainwarp.lod.select` evaluates it in numpy float64 (then rounds
    to float32), the fit's relaxed model and :mod:`terrainwarp.fit.diffpath` in ``jax.numpy`` float32
    (``xp=jax.numpy``; the fit passes a soft ``clamp(x, lo, hi)``).

    Args:
        edge_px: (P, 4) projected edge lengths (:func:`edge_pixels`).
        target_px: pixels per triangle edge (> 0), a number or a scalar array of ``xp``.

    Returns:
        (outer (P, 4), inner (P, 2)) arrays of ``xp`` in the inputs' precision.
    """
    f = edge_px / target_px
    outer = xp.clip(f, 1.0, float(MAX_TESS)) if clamp is None else clamp(f, 1.0, float(MAX_TESS))
    inner = xp.stack([0.5 * (outer[:, 1] + outer[:, 3]), 0.5 * (outer[:, 0] + outer[:, 2])], axis=1)
    return outer, inner


# ------------------------------------------------------------------------------------------------
# Cesium's heightmap-terrain rule (CesiumJS: TerrainProvider, QuadtreePrimitive, HeightmapTerrainData)
# ------------------------------------------------------------------------------------------------
CESIUM_TILE_SAMPLES = 65  # a heightmap tile's samples per side (TerrainProvider's tileImageWidth)
CESIUM_HEIGHTMAP_QUALITY = 0.25  # TerrainProvider.heightmapTerrainQuality
CESIUM_DEFAULT_SSE = 2.0  # Globe.maximumScreenSpaceError's default


def cesium_level_error(level: int | np.ndarray, level0_tile_width_m: float) -> float | np.ndarray:
    """Cesium's geometric error (metres) of a heightmap tile at ``level`` (0: the root tiles):
    ``heightmapTerrainQuality * level0_tile_width / (tileImageWidth * 2**level)``, i.e.
    ``0.25 * W0 / (65 * 2**L)``.

    CesiumJS estimates level 0 as ``ellipsoid.maximumRadius * 2 pi * 0.25 / (65 * tiles at level 0)``
    (``TerrainProvider.getEstimatedLevelZeroGeometricErrorForAHeightmap``; the equator's length over the level-0
    tiles across it is a level-0 tile's width) and halves it per level (``getLevelMaximumGeometricError``). On a
    planar heightmap the level-0 tile's width ``W0`` is its extent along x in metres. A tile spans 64 sample
    spacings, so this is 0.25 * 64/65 of the tile's sample spacing."""
    return CESIUM_HEIGHTMAP_QUALITY * float(level0_tile_width_m) / (CESIUM_TILE_SAMPLES * np.exp2(level))


def cesium_sse(geometric_error_m: float | np.ndarray, distance_m: float | np.ndarray, viewport_height: int,
               fov_y_deg: float) -> float | np.ndarray:
    """Cesium's screen-space error of a tile (QuadtreePrimitive ``screenSpaceError``, perspective, fog off,
    pixelRatio 1): ``geometricError * viewportHeight / (distance * 2 tan(fovy / 2))``, ``distance`` from the eye
    to the tile's bounding volume (infinite at distance 0)."""
    den = np.asarray(distance_m, np.float64) * 2.0 * math.tan(math.radians(fov_y_deg) / 2.0)
    with np.errstate(divide="ignore"):
        out = np.where(den > 0, np.asarray(geometric_error_m, np.float64) * viewport_height / np.where(den > 0, den, 1),
                       np.inf)
    return out if out.ndim else float(out)


def cesium_refines(sse: float | np.ndarray, maximum_screen_space_error: float) -> bool | np.ndarray:
    """Whether Cesium refines a tile (draws its children instead): unless ``sse < maximumScreenSpaceError``
    (QuadtreePrimitive ``visitTile``: a tile meets the SSE only strictly below it), and only where it has
    children."""
    out = np.asarray(sse) >= float(maximum_screen_space_error)
    return out if out.ndim else bool(out)

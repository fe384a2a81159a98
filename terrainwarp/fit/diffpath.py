"""The differentiable path of the continuous LOD policy: per-pixel screen error as a JAX function of
``log(target_px)``, with gradients through the fractional_odd point placement, the displacement and the
Warp resolve kernel.

The policy (:class:`terrainwarp.lod.ContinuousPolicy`, ``fractional_odd`` spacing): a uniform grid of
patches at one quadtree level, per-edge factors ``f = clamp(L * focal / (d * target_px), 1, 64)`` from each
edge's endpoints (L the edge's 3-D length, d the eye's distance to its midpoint), inner factors the mean of
opposite edges. The chain, and what is differentiable in it::

    log t ──► factors f(t)  (6 per patch: outer 0..3, inner u, v; the tessellator's clamp to [1, 63])
          ──► domain points uv(f)   JAX, fractional_odd placement of the D3D11 reference tessellator
          ──► positions p(uv)       JAX, bilinear height sampling, camera-relative float32
          ──► clip = MVP p          JAX
          ──► P = interpolate(p, triangle_id, clip, triangles)
                  Warp kernels through ``warp.jax_callable`` with a deterministic backward
                  (:func:`terrainwarp.diff.interpolate`)
          ──► e = |proj(P) - proj(R)| px, R the full-resolution surface point below/above P (JAX)
          ──► soft maximum / mean / mean above the p99 over pixels

Held fixed (the non-differentiable, discrete part, frozen at the current factors by :func:`prepare`):
the topology of every patch (the number of points per edge and ring, the ruler-function split point, the
triangles), the visibility pass (``rasterize``: triangle id per pixel, from the exact mesh) and the
factor clamps' active sets (a clamped factor has zero derivative).

Point placement (D3D11 reference ``PlacePointIn1D``, :mod:`terrainwarp.rendering.reference_tessellator` rule 7),
fractional_odd:
with the level f, ``half = (f + 1) / 2``, ``fl = floor(half)``, ``frac = half - fl``, a point of index
``point`` on the first half of an edge sits at ``idx_f * R(2 fl - 1) * (1 - frac) + point * R(2 ceil(half) - 1)
* frac`` (``R(n) = round(2^16 / n) / 2^16``, ``idx_f = point - 1`` beyond the ruler-function split, else
``point``); the second half mirrors it (``1 - x``). The hardware evaluates it in 16.16 fixed point (the
level rounded to 2^-16, the result rounded to 2^-16); we evaluate the same formula in float32 with the
topology (fl, ceil(half), split, the flip) held fixed, so ``d uv / d f = (point R_c - idx_f R_f) / 2``
exists. Within a topology (f between two odd integers) the formula is linear in f. When f rises
through an odd integer 2k+1 the point count grows: at f = 2k+1 both partitions coincide (the new pair
of points is born on an existing point), so positions are continuous in f but have a kink there; the
derivative we give is that of the piece the current factor lies in (one-sided at the kink, towards the
current topology). At exactly an odd level (in practice only the clamps 1 and 63, where the derivative is
zero anyway) the frozen formula does not move the points: zero derivative, neither side's.

Forward values: at the current factors the frame is the exact pipeline's, bit for bit (domain points from
the Warp tessellator, positions from its displacement kernel); the JAX model contributes the motion away
from them, ``x(t) = x_warp + (x_model(t) - x_model(t0))``, so derivatives are the model's. The model's
domain points differ from the hardware's by at most 2^-16 (its two roundings), checked by the tests.

Relaxed (not the exact pipeline): (1) the rounding of levels and points to 16.16 fixed point and of
lattice coordinates to 2^-16 cells is dropped in the derivative; (2) the topology and the triangle id
image are those of the current factors (no gradient through coverage: silhouettes and the pixels whose
visible triangle would change are extrapolated on the frozen triangle); (3) the maximum is a soft maximum
(log-mean-exp with a temperature in pixels) or the mean above the 99th percentile (its pixel set frozen
at the current value). Bilinear height filtering only (``filter="bilinear"``).

Reverse mode only, one scalar at a time (``jax.grad``, ``jax.vjp``): ``jax.jacfwd`` is refused by the
``jax_kernel`` custom VJP, and ``jax.jacrev`` (which vmaps the cotangents through the Warp kernel's
backward) returns wrong numbers without an error; :func:`loss_and_grads` calls one VJP per output.

Precision: float32 like the pipeline; the reference height and the error are float32 too (the exact
:mod:`terrainwarp.measure.error` runs in float64), so absolute errors below ~1e-4 px are noise; the error is
written as ``|dy| * |d proj / dy|`` (no difference of two nearby projections).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import logsumexp

from ..camera import Camera
from ..diff import clip_positions, interpolate
from ..heightmap import Heightmap
from ..kernels.checks import check_number
from ..kernels.raster import rasterize
from ..kernels.tessellator import tessellate_patches
from ..lod.policies import EDGE_PX_MAX, ContinuousPolicy, continuous_factors, edge_pixels
from ..lod.quadtree import PatchList, Terrain, select

__all__ = ["DiffFrame", "prepare", "levels", "domain_points", "positions", "pixel_error", "soft_max_px",
           "frame_loss", "loss_and_grads", "log_slope", "place_fixed"]

FXP_ONE = 65536
_RECIP = np.array([0] + [int(65536.0 / n + 0.5) for n in range(1, 130)], np.int64)  # round(2^16 / n)
_RMSB = np.array([0] + [v - (1 << (v.bit_length() - 1)) for v in range(1, 130)], np.int64)  # RemoveMSB
_HI = np.float32(63.0)  # fractional_odd clamps levels to [1, 63]
_LO_IN = np.float32(1.0 + 2.0**-16)  # picture frame: inner lower bound when any level exceeds 1 + 2^-17
_ONE_PLUS_HALF_EPS = np.float32(1.0 + 2.0**-17)


# ------------------------------------------------------------------------------------------------
# topology: which level places each coordinate of each point, with which partition index
# ------------------------------------------------------------------------------------------------
def _fixed_levels(outer: np.ndarray, inner: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """fractional_odd level processing (tessellate.py rules 3-6) for P patches, vectorised.

    Returns (fx (P, 6) int64 16.16 levels, frame (P,) bool picture-frame flag, minimal (P,) bool)."""
    o = np.minimum(_HI, np.maximum(np.float32(1.0), outer.astype(np.float32)))
    i = inner.astype(np.float32)
    frame = (o > _ONE_PLUS_HALF_EPS).any(1) | (i > _ONE_PLUS_HALF_EPS).any(1)
    lo_in = np.where(frame, _LO_IN, np.float32(1.0)).astype(np.float32)[:, None]
    i = np.minimum(_HI, np.maximum(lo_in, i))
    fx = np.rint(np.concatenate([o, i], 1).astype(np.float64) * FXP_ONE).astype(np.int64)
    return fx, frame, (fx == FXP_ONE).all(1)


def _num_points(fx: np.ndarray) -> np.ndarray:
    half = FXP_ONE // 2 + (fx + 1) // 2
    ce = np.where(half & 0xFFFF, (half & 0x7FFF0000) + FXP_ONE, half)
    return (ce * 2) >> 16


def _layout(fx: np.ndarray) -> np.ndarray:
    g = _num_points(fx)
    g[:, 4:] = np.maximum(4, g[:, 4:])
    return g


def _descriptors(g: tuple[int, ...]) -> np.ndarray:
    """(n, 4) int64 rows (slot_u, q_u, slot_v, q_v) of one patch layout, in the tessellator's point order.

    slot 0..5 is the level that places the coordinate (outer 0..3, inner u, inner v) and q the partition
    point; slot -1 is a constant coordinate, q then its value (0 or 1)."""
    rows = []
    for e in range(4):  # outer ring: from (0,1) down u=0, along v=0, up u=1, back along v=1
        end = g[e] - 1
        for p in range(end):
            q = p if e in (1, 2) else end - p
            rows.append(((-1, 0, e, q), (e, q, -1, 0), (-1, 1, e, q), (e, q, -1, 1))[e])
    nu, nv = g[4], g[5]
    for ring in range(1, min(nu, nv) >> 1):  # inner rings, spiralling inwards
        end = (nu - 1 - ring, nv - 1 - ring)
        for e in range(4):
            along, perp = (e + 1) & 1, e & 1
            tq = ring if e < 2 else end[perp]
            for p in range(ring, end[along]):
                q = p if e in (1, 2) else end[along] - (p - ring)
                rows.append((4 + perp, tq, 4 + along, q) if along else (4 + along, q, 4 + perp, tq))
    return np.asarray(rows, np.int64).reshape(-1, 4)


_MINIMAL = np.array([[-1, 0, -1, 0], [-1, 1, -1, 0], [-1, 1, -1, 1], [-1, 0, -1, 1]], np.int64)


class _Context(dict):
    """Per-coordinate placement context at the frozen topology (numpy arrays of one length)."""


def _context(fx: np.ndarray, q: np.ndarray) -> _Context:
    """Fixed-point placement context of partition point ``q`` on edges of 16.16 level ``fx`` (odd parity)."""
    half = (fx + 1) // 2 + FXP_ONE // 2
    fl = half & 0x7FFF0000
    ce = np.where(half & 0xFFFF, fl + FXP_ONE, half)
    nhalf = ce >> 16
    split = np.where(ce == fl, nhalf + 1, np.where(fl == FXP_ONE, 0, (_RMSB[np.maximum((fl >> 16) - 1, 0)] << 1) + 1))
    nfs = ((fl * 2) >> 16) - 1
    ncs = ((ce * 2) >> 16) - 1
    flip = q >= nhalf
    point = np.where(flip, 2 * nhalf - q - 1, q)
    idx_f = np.where(point > split, point - 1, point)
    return _Context(half=half, fl=fl, frac=half - fl, flip=flip, point=point, idx_f=idx_f,
                    rf=_RECIP[np.maximum(nfs, 1)], rc=_RECIP[np.maximum(ncs, 1)])


def place_fixed(fx: np.ndarray, q: np.ndarray) -> np.ndarray:
    """The hardware's 16.16 position of partition point ``q`` on fractional_odd edges of level ``fx``
    (vectorised ``terrainwarp.rendering.reference_tessellator.place``), int64."""
    c = _context(np.asarray(fx, np.int64), np.asarray(q, np.int64))
    loc = (c["idx_f"] * c["rf"] * (FXP_ONE - c["frac"]) + c["point"] * c["rc"] * c["frac"] + FXP_ONE // 2) >> 16
    return np.where(c["flip"], FXP_ONE - loc, loc)


@dataclass(frozen=True, eq=False)
class _Coords:
    """Per point and axis (u, v): the frozen placement of each domain coordinate."""

    patch: np.ndarray  # (n,) int32
    slot: np.ndarray  # (n, 2) int32, -1 constant
    const: np.ndarray  # (n, 2) float32
    fl: np.ndarray  # (n, 2) float32, floor(half) in levels
    a: np.ndarray  # (n, 2) float32: idx_f * R_f
    b: np.ndarray  # (n, 2) float32: point * R_c
    flip: np.ndarray  # (n, 2) bool


def _coords(fx: np.ndarray, minimal: np.ndarray) -> tuple[_Coords, np.ndarray]:
    """Descriptors for every point of every patch (points concatenated in patch order) and the fixed
    16.16 domain coordinates they give (n, 2) int64."""
    g = _layout(fx)
    cache: dict[tuple[int, ...], np.ndarray] = {}
    parts, pids = [], []
    for p in range(len(fx)):  # host-side, once per frame; layouts repeat, so the enumeration is cached
        key = (0,) if minimal[p] else tuple(int(x) for x in g[p])
        if key not in cache:
            cache[key] = _MINIMAL if minimal[p] else _descriptors(key)
        parts.append(cache[key])
        pids.append(np.full(len(cache[key]), p, np.int32))
    d = np.concatenate(parts) if parts else np.zeros((0, 4), np.int64)
    pid = np.concatenate(pids) if pids else np.zeros(0, np.int32)
    slot = d[:, [0, 2]]
    q = d[:, [1, 3]]
    lv = fx[pid[:, None], np.maximum(slot, 0)]
    c = _context(lv, q)
    loc = (c["idx_f"] * c["rf"] * (FXP_ONE - c["frac"]) + c["point"] * c["rc"] * c["frac"] + FXP_ONE // 2) >> 16
    fixed = np.where(slot < 0, q * FXP_ONE, np.where(c["flip"], FXP_ONE - loc, loc))
    co = _Coords(patch=pid, slot=slot.astype(np.int32), const=q.astype(np.float32),
                 fl=(c["fl"] / FXP_ONE).astype(np.float32),
                 a=(c["idx_f"] * c["rf"] / FXP_ONE).astype(np.float32),
                 b=(c["point"] * c["rc"] / FXP_ONE).astype(np.float32), flip=c["flip"])
    return co, fixed


def _topology(outer, inner):
    """Frozen fractional_odd topology of P patches: (coords, levels (P, 6) float32 as the tessellator
    clamps them, fixed 16.16 domain points (n, 2) int64, picture-frame flag (P,) bool)."""
    o = np.asarray(outer, np.float32).reshape(-1, 4)
    i = np.asarray(inner, np.float32).reshape(-1, 2)
    fx, frame_flag, minimal = _fixed_levels(o, i)
    co, fixed = _coords(fx, minimal)
    lo_in = np.where(frame_flag, _LO_IN, np.float32(1.0)).astype(np.float32)[:, None]
    lv = np.concatenate([np.minimum(_HI, np.maximum(np.float32(1.0), o)), np.minimum(_HI, np.maximum(lo_in, i))], 1)
    return co, lv.astype(np.float32), fixed, frame_flag


# ------------------------------------------------------------------------------------------------
# the frozen frame
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class DiffFrame:
    """Everything :func:`frame_loss` holds fixed, built at the current ``target_px`` by :func:`prepare`.

    Attributes:
        log_target0: the log(target_px) the frame was built at.
        raw: (P, 4) float32 projected edge lengths in pixels (:func:`terrainwarp.lod.edge_pixels`: the
            per-edge factors at target 1 px, unclamped); ``const`` (P, 4) bool marks edges whose factor does
            not depend on the target (eye on the midpoint: ``EDGE_PX_MAX``, whose factor is 64 for any target).
        frame_flag: (P,) bool, the picture-frame rule's inner lower bound (1 + 2^-16) applies.
        coords: the frozen placement of every domain point.
        domain: (n, 2) float32 the Warp tessellator's domain points (exact multiples of 2^-16).
        positions: (n, 3) float32 the Warp displacement kernel's camera-relative positions.
        triangles: (m, 3) int32 (as :class:`terrainwarp.kernels.tessellator.Tessellation` stores them).
        triangle_id: (H, W) int32 the visibility pass (``rasterize``) of that mesh, -1 background.
        box: (P, 4) float64 patch extents in cells (x0, z0, x1, z1); off: (P, 3) float64 camera-relative
            position of each patch's (u, v) = (0, 0) corner at height 0.
        heights: (H, W) float32 heightmap; eye, origin, dx, dz, mvp (4, 4), width, height: the camera.
        patches: the :class:`terrainwarp.lod.PatchList`.
    """

    log_target0: float
    raw: np.ndarray
    const: np.ndarray
    frame_flag: np.ndarray
    coords: _Coords
    domain: np.ndarray
    positions: np.ndarray
    triangles: np.ndarray
    triangle_id: np.ndarray
    box: np.ndarray
    off: np.ndarray
    heights: np.ndarray
    eye: tuple[float, float, float]
    origin: tuple[float, float]
    dx: float
    dz: float
    mvp: np.ndarray
    width: int
    height: int
    patches: PatchList
    _jit: dict = field(default_factory=dict, repr=False)


def prepare(heightmap: Heightmap, camera: Camera, target_px: float, level: int = 3, *, roots=16,
            terrain: Terrain | None = None, cull_back: bool = False, device: str = "cpu") -> DiffFrame:
    """Run the exact pipeline once at ``target_px`` (select, tessellate + displace, rasterize) and freeze
    what the differentiable path holds fixed.

    Args:
        heightmap, camera: the scene.
        target_px: pixels per triangle edge (> 0), the continuous policy's parameter.
        level: the level of the uniform patch grid (clamped to the terrain's depth).
        roots: root nodes when ``terrain`` is None (as ``LodConfig.roots``).
        terrain: a prepared :class:`Terrain` (its ``tess`` is unused by this policy).
        cull_back: cull back faces in the visibility pass (as ``Scene.cull_back``).

    Returns:
        A :class:`DiffFrame`.
    """
    if not isinstance(heightmap, Heightmap):
        raise TypeError(f"heightmap: expected a Heightmap, got {type(heightmap).__name__}")
    if not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a Camera, got {type(camera).__name__}")
    check_number("target_px", target_px, 0.0, lo_open=True)
    if terrain is None:
        terrain = Terrain.prepare(heightmap, roots=roots, tess=8, device=device)
    elif terrain.heightmap is not heightmap:
        raise ValueError("terrain: prepared for another heightmap")
    pl = select(terrain, camera, ContinuousPolicy(float(target_px), level=min(int(level), terrain.depth)),
                device=device)
    hm = heightmap
    t = tessellate_patches({"origin_xz": pl.origin, "size": pl.size, "outer": pl.outer, "inner": pl.inner,
                            "level": pl.level}, hm.heights, hm.dx, hm.dz, camera.position,
                           spacing="fractional_odd", filter="bilinear", origin=hm.origin, device=device)
    view = camera.view_matrix(relative=True)
    proj = camera.proj_matrix()
    frags = rasterize(t.positions, t.triangles, view, proj, camera.width, camera.height, cull_back=cull_back,
                      device=device)
    if len(pl) == 0 or len(t.triangles) == 0:
        raise ValueError("camera: sees no terrain patch, nothing to differentiate")
    co, _, fixed, frame_flag = _topology(pl.outer, pl.inner)
    if len(fixed) != len(t.domain) or not np.array_equal(fixed.astype(np.float32) / FXP_ONE, t.domain):
        raise RuntimeError("diffpath: the frozen topology does not reproduce the tessellator's points")
    edge_px = edge_pixels(hm, camera.position, camera.focal_px, pl.origin, pl.size)
    raw, const = edge_px.astype(np.float32), edge_px >= EDGE_PX_MAX
    # patch extents on the 2^-16-cell lattice, as tessellate_patches rounds them, in cells
    sc = np.array([FXP_ONE / hm.dx, FXP_ONE / hm.dz])
    lo = np.rint((pl.origin - hm.origin) * sc) / FXP_ONE
    hi = np.rint((pl.origin + pl.size - hm.origin) * sc) / FXP_ONE
    box = np.concatenate([lo, hi], 1)
    eye = np.asarray(camera.position, np.float64)
    off = np.stack([hm.origin[0] + lo[:, 0] * hm.dx - eye[0], np.full(len(lo), -eye[1]),
                    hm.origin[1] + lo[:, 1] * hm.dz - eye[2]], 1)
    return DiffFrame(log_target0=math.log(float(target_px)), raw=raw, const=const, frame_flag=frame_flag,
                     coords=co, domain=t.domain, positions=t.positions, triangles=t.triangles,
                     triangle_id=frags.triangle_id, box=box, off=off, heights=hm.heights.astype(np.float32),
                     eye=(float(eye[0]), float(eye[1]), float(eye[2])),
                     origin=(float(hm.origin[0]), float(hm.origin[1])), dx=float(hm.dx), dz=float(hm.dz),
                     mvp=(proj @ view).astype(np.float32), width=camera.width, height=camera.height, patches=pl)


# ------------------------------------------------------------------------------------------------
# the differentiable chain (JAX)
# ------------------------------------------------------------------------------------------------
def levels(frame: DiffFrame, log_target):
    """(P, 6) float32 tessellation levels (outer 0..3, inner u, inner v) as the tessellator uses them:
    the policy's rule (:func:`terrainwarp.lod.continuous_factors`, here in float32 JAX: ``clamp(raw / t, 1,
    64)``, inner = mean of opposite edges), then the fractional_odd clamp to [1, 63] (inner: [1 + 2^-16, 63]
    under the picture-frame rule). Zero derivative where clamped. Within one float32 rounding of the factors
    :func:`terrainwarp.lod.select` gives (float64 rule, rounded once), checked by the tests."""
    t = jnp.exp(jnp.asarray(log_target, jnp.float32))
    f, inner = continuous_factors(jnp.asarray(frame.raw), t, xp=jnp)
    lo_in = jnp.where(jnp.asarray(frame.frame_flag), _LO_IN, jnp.float32(1.0))[:, None]
    return jnp.concatenate([jnp.clip(f, 1.0, float(_HI)), jnp.clip(inner, lo_in, float(_HI))], 1)


def domain_points(frame, lv):
    """(n, 2) float32 domain coordinates of every point, the model's continuous placement at levels
    ``lv`` (P, 6) with the frozen topology (not snapped to 2^-16; within 2^-16 of the hardware at the
    frame's own levels). Differentiable in ``lv``. ``frame`` may also be the frozen coordinates alone."""
    c = frame.coords if isinstance(frame, DiffFrame) else frame
    slot = jnp.asarray(c.slot)
    f = lv[jnp.asarray(c.patch)[:, None], jnp.maximum(slot, 0)]  # (n, 2)
    frac = 0.5 * (f + 1.0) - jnp.asarray(c.fl)
    loc = jnp.asarray(c.a) * (1.0 - frac) + jnp.asarray(c.b) * frac
    loc = jnp.where(jnp.asarray(c.flip), 1.0 - loc, loc)
    return jnp.where(slot < 0, jnp.asarray(c.const), loc)


def _bilinear(h, gx, gz):
    """``terrainwarp.kernels.sampling.sample_bilinear`` in JAX (clamped), differentiable in gx, gz."""
    rows, cols = h.shape
    uc = jnp.clip(gx, 0.0, float(cols - 1))
    vc = jnp.clip(gz, 0.0, float(rows - 1))
    j0 = jax.lax.stop_gradient(jnp.floor(uc)).astype(jnp.int32)
    i0 = jax.lax.stop_gradient(jnp.floor(vc)).astype(jnp.int32)
    fu = uc - j0
    fv = vc - i0
    j1 = jnp.minimum(j0 + 1, cols - 1)
    i1 = jnp.minimum(i0 + 1, rows - 1)
    ref = h[i0, j0]
    b = h[i0, j1] - ref
    c = h[i1, j0] - ref
    d = h[i1, j1] - ref
    top = b * fu
    bot = c + (d - c) * fu
    return ref + (top + (bot - top) * fv)


def positions(frame: DiffFrame, uv):
    """(n, 3) float32 camera-relative positions of domain points ``uv`` (n, 2): the patch's extent on the
    heightmap (clamped to the grid, as the displacement kernel clamps past-the-grid points), heights
    by bilinear sampling. Differentiable in ``uv``."""
    h = jnp.asarray(frame.heights)
    p = jnp.asarray(frame.coords.patch)
    box = frame.box
    x0, z0 = jnp.asarray(box[:, 0], jnp.float32)[p], jnp.asarray(box[:, 1], jnp.float32)[p]
    sx = jnp.asarray(box[:, 2] - box[:, 0], jnp.float32)[p]
    sz = jnp.asarray(box[:, 3] - box[:, 1], jnp.float32)[p]
    rows, cols = frame.heights.shape
    gx = jnp.clip(x0 + sx * uv[:, 0], 0.0, float(cols - 1))
    gz = jnp.clip(z0 + sz * uv[:, 1], 0.0, float(rows - 1))
    hgt = _bilinear(h, gx, gz)
    off = jnp.asarray(frame.off, jnp.float32)[p]
    # camera-relative: (grid coordinate - patch corner) * spacing + the corner's camera-relative offset
    px = (gx - x0) * frame.dx + off[:, 0]
    pz = (gz - z0) * frame.dz + off[:, 2]
    return jnp.stack([px, hgt + off[:, 1], pz], 1)


def _reference_height(frame: DiffFrame, x, z):
    """Height of the full-resolution triangulated grid at world (x, z) (``metrics.reference_height``),
    JAX float32, differentiable in x, z (piecewise linear)."""
    h = jnp.asarray(frame.heights)
    rows, cols = frame.heights.shape
    u = jnp.clip((x - frame.origin[0]) / frame.dx, 0.0, float(cols - 1))
    v = jnp.clip((z - frame.origin[1]) / frame.dz, 0.0, float(rows - 1))
    j = jnp.minimum(jax.lax.stop_gradient(jnp.floor(u)).astype(jnp.int32), max(cols - 2, 0))
    i = jnp.minimum(jax.lax.stop_gradient(jnp.floor(v)).astype(jnp.int32), max(rows - 2, 0))
    fx = u - j
    fz = v - i
    j1 = jnp.minimum(j + 1, cols - 1)
    i1 = jnp.minimum(i + 1, rows - 1)
    h00, h01, h10, h11 = h[i, j], h[i, j1], h[i1, j], h[i1, j1]
    lower = jax.lax.stop_gradient(fx + fz) <= 1.0
    a = h00 + fx * (h01 - h00) + fz * (h10 - h00)
    b = h11 + (1.0 - fx) * (h10 - h11) + (1.0 - fz) * (h01 - h11)
    return jnp.where(lower, a, b)


def pixel_error(frame: DiffFrame, log_target):
    """Per-pixel screen error (px) of the frame at ``log_target``, differentiable.

    Returns:
        (err (H, W) float32, valid (H, W) bool), jax arrays. ``err`` is ``|proj(P) - proj(R)|``
        in pixels, P the visible surface point of the pixel (the Warp resolve kernel), R the
        full-resolution surface point with P's x and z (as :func:`terrainwarp.measure.error.frame_error`); 0
        where not ``valid`` (background, or R behind the camera).
    """


    lv = levels(frame, log_target)
    lv0 = jax.lax.stop_gradient(levels(frame, frame.log_target0))
    uv = domain_points(frame, lv)
    uv0 = domain_points(frame, lv0)
    # forward: the Warp tessellator's exact points and positions; motion and derivatives: the model's
    pos = jnp.asarray(frame.positions) + (positions(frame, uv) - jax.lax.stop_gradient(positions(frame, uv0)))
    clip = clip_positions(pos, np.eye(4, dtype=np.float32), frame.mvp)
    P = interpolate(pos, frame.triangle_id, clip, frame.triangles)  # (H, W, 3): Warp kernel via jax_kernel
    cov = jnp.asarray(frame.triangle_id >= 0)
    m = jnp.asarray(frame.mvp)
    qx = P @ m[0, :3] + m[0, 3]
    qy = P @ m[1, :3] + m[1, 3]
    qw = P @ m[3, :3] + m[3, 3]
    ry = _reference_height(frame, P[..., 0] + frame.eye[0], P[..., 2] + frame.eye[2]) - frame.eye[1]
    dy = ry - P[..., 1]
    qwr = qw + m[3, 1] * dy
    ok = cov & (qw > 0) & (qwr > 0)
    den = jnp.where(ok, qw * qwr, 1.0)
    # proj(R) - proj(P) = dy * (q m[k,1] ... ) / (qw qwr): exact algebra, no cancellation
    cx = (m[0, 1] * qw - qx * m[3, 1]) / den * (0.5 * frame.width)
    cy = (m[1, 1] * qw - qy * m[3, 1]) / den * (0.5 * frame.height)
    scale = jnp.sqrt(jnp.maximum(cx * cx + cy * cy, 1e-30))
    err = jnp.where(ok, jnp.abs(dy) * scale, 0.0)
    return err, ok


def soft_max_px(err, valid, temperature_px: float = 0.25):
    """Smooth maximum of ``err`` over the ``valid`` pixels: ``T log(mean exp(err / T))`` (log-mean-exp,
    between the mean and the maximum; the maximum as T -> 0, within T log(N) of it)."""
    v = jnp.asarray(valid)
    n = jnp.sum(v)
    z = jnp.where(v, err / temperature_px, -1e30)  # not -inf: finite gradients even with no valid pixel
    return jnp.where(n > 0, temperature_px * (logsumexp(z) - jnp.log(jnp.maximum(n, 1))), 0.0)


def tail_mean_px(err, valid, q: float = 0.99):
    """Mean of the largest ``ceil((1 - q) N)`` errors over the ``valid`` pixels (the expected shortfall
    above the q-quantile, >= the q-quantile). Differentiable almost everywhere: the set of tail pixels is
    chosen at the current value (its derivative is that of the tail's values)."""
    flat = jnp.where(jnp.asarray(valid), err, -1.0).reshape(-1)
    n = flat.shape[0]
    k = max(int(math.ceil((1.0 - q) * n)), 1)  # static: of all pixels, then of the valid ones below
    top, _ = jax.lax.top_k(flat, k)
    nv = jnp.sum(jnp.asarray(valid))
    kv = jnp.maximum(jnp.ceil((1.0 - q) * nv), 1.0)
    w = (jnp.arange(k) < kv) & (top >= 0)
    return jnp.sum(jnp.where(w, top, 0.0)) / jnp.maximum(jnp.sum(w), 1)


def frame_loss(frame: DiffFrame, log_target, temperature_px: float = 0.25, q: float = 0.99):
    """(soft maximum px, mean px, tail mean above the q-quantile px) of the per-pixel error at
    ``log_target``; all differentiable."""
    err, valid = pixel_error(frame, log_target)
    n = jnp.maximum(jnp.sum(valid), 1)
    return soft_max_px(err, valid, temperature_px), jnp.sum(err) / n, tail_mean_px(err, valid, q)


def loss_and_grads(frame: DiffFrame, log_target, temperature_px: float = 0.25):
    """Values and derivatives of :func:`frame_loss` (soft maximum px, mean px, tail mean px) with respect
    to ``log_target``, one compiled function per frame (cached on it): ``(values (3,), d values /
    d log_target (3,))`` numpy float64.

    One forward pass and three reverse passes through the same VJP (``jax.jacrev`` would vmap the
    cotangents through the Warp kernel's backward, which ``warp.jax_kernel`` does not support)."""
    key = ("loss_and_grads", float(temperature_px))
    fn = frame._jit.get(key)
    if fn is None:
        def run(lt):
            out, vjp = jax.vjp(lambda x: jnp.stack(frame_loss(frame, x, temperature_px)), lt)
            gs = [vjp(jnp.eye(3, dtype=jnp.float32)[k])[0] for k in range(3)]
            return out, jnp.stack(gs)

        fn = frame._jit[key] = jax.jit(run)
    v, g = fn(jnp.asarray(log_target, jnp.float32))
    return np.asarray(v, np.float64), np.asarray(g, np.float64)


def log_slope(heightmap: Heightmap, camera: Camera, target_px: float, level: int, terrain: Terrain, *,
              cull_back: bool = False, temperature_px: float = 0.25, device: str = "cpu") -> tuple[float, float]:
    """(tail mean above the 99th percentile px, its d log / d log(target_px)) of one frame at ``target_px``:
    the exact pipeline once, then the differentiable path (the slope a Newton step on log p99 needs; the
    tail mean tracks the p99's slope more closely than the soft maximum, which follows a few pixels)."""
    fr = prepare(heightmap, camera, target_px, level, terrain=terrain, cull_back=cull_back, device=device)
    v, g = loss_and_grads(fr, fr.log_target0, temperature_px)
    return float(v[2]), float(g[2]) / max(float(v[2]), 1e-12)

"""The stability suite: every extreme case of :mod:`terrainwarp.experiments.extreme` through every pipeline stage.

For each (case, stage) the suite records whether the outputs are finite, whether the mesh is watertight
(where a mesh exists), the error of the float32 product against a float64 reference of the same
computation (computed here, on the host, in numpy float64), or the clear error raised instead. Where
float32 loses precision it also measures the same computation *without* the GPU remedy the product
uses, so the benefit is a number, not a claim:

* sampling: the device's bilinear filter (weights applied to heights relative to the cell's first sample)
  vs naive float32 ``sum(w_k h_k)``.
* normals: the Sobel kernel (every difference taken between two samples before any sum) vs a naive
  float32 convolution accumulating signed weighted heights in row-major order.
* curvature: three-vertex curvature (chord slopes first) vs naive ``(h[+1] + h[-1] - 2 h[0]) / L^2``.
* raster: camera-relative float32 positions (world - eye in float64 on the host, then cast) vs naive
  absolute float32 positions minus a float32 eye; in metres, in pixels, and as the number of pixels
  whose visible triangle changes when the naive positions are rasterized.

Stages: ``sampling``, ``select`` (:func:`terrainwarp.lod.select`), ``tessellate``
(:func:`terrainwarp.rendering.reference_tessellator.reference_tessellate_patch` against the frame kernel
``terrainwarp.kernels.tessellator.tessellate_domains``; cases without a factor: a LOD frame, watertight by
:func:`terrainwarp.rendering.watertight.check_watertight`), ``normals``, ``curvature``
(:mod:`terrainwarp.surface.differential`), ``raster`` (:func:`terrainwarp.render`, grid mesh), ``error``
(``render``'s error stage: the primary error at the heightmap's samples, :mod:`terrainwarp.measure.sample_error`,
with the grid-image error of :mod:`terrainwarp.measure.error` beside it), ``fit`` (the relaxed JAX model of
:mod:`terrainwarp.fit`: finite cost, error and gradients, gradient against a finite difference).

Outcomes: ``pass``; ``raised``, a clear error (ValueError/TypeError whose message names the argument,
"name: expected X, got Y"); ``FAIL``, a check that failed, or any other exception, recorded with its type
and where it was raised (function, file:line of the innermost frame), never as a pass.

::

    rows = run_suite()                      # small grids (33 x 33), about a minute
    write_stability_md(rows, "out/stab")    # stability.md
"""

from __future__ import annotations

import math
import re
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..fit.families import relaxed_model
from ..io.files import digest, write_text
from ..kernels.raster import rasterize
from ..kernels.sampling import sample_grid
from ..kernels.tessellator import tessellate_domains
from ..lod.policies import ScreenErrorPolicy
from ..lod.quadtree import Terrain, select
from ..rendering.pipeline import render
from ..rendering.reference_tessellator import SPACINGS, reference_tessellate_patch
from ..rendering.watertight import check_watertight, check_watertight_domain, lod_boundary
from ..scene import LodConfig, Scene
from ..surface.differential import compute_curvature, compute_normals
from .extreme import CASES, ExtremeCase

__all__ = ["Row", "STAGES", "run_suite", "run_case", "write_stability_md", "stage_hashes"]

STAGES = ("sampling", "select", "tessellate", "normals", "curvature", "raster", "error", "fit")
PASS, RAISED, FAIL, NA = "pass", "raised", "FAIL", "n/a"
_F32 = np.float32


@dataclass
class Row:
    """One (case, stage) outcome.

    Attributes:
        case, stage: what ran.
        status: ``pass``, ``raised`` (a clear ValueError/TypeError naming the argument), ``FAIL`` or ``n/a``.
        error: the float32 product's error against the float64 reference (with the GPU remedy), as text.
        naive: the same error without the remedy ("" when no remedy applies).
        note: what was checked, or the message raised.
        hash: :func:`terrainwarp.io.files.digest` of the stage's output arrays ("" when none).
    """

    case: str
    stage: str
    status: str
    error: str = ""
    naive: str = ""
    note: str = ""
    hash: str = ""


def _g(x: float) -> str:
    return f"{x:.3g}"


class _Fail(Exception):
    """A check failed: the stage gave a wrong or non-finite answer without raising."""


def _check(ok: bool, msg: str) -> None:
    if not ok:
        raise _Fail(msg)


# ------------------------------------------------------------------------------------------------
# float64 references (host numpy; the product stays float32)
# ------------------------------------------------------------------------------------------------
def _bilinear64(h: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    rows, cols = h.shape
    uc = np.clip(u.astype(np.float64), 0, cols - 1)
    vc = np.clip(v.astype(np.float64), 0, rows - 1)
    j0 = np.floor(uc).astype(np.int64)
    i0 = np.floor(vc).astype(np.int64)
    j1, i1 = np.minimum(j0 + 1, cols - 1), np.minimum(i0 + 1, rows - 1)
    fu, fv = uc - j0, vc - i0
    h = h.astype(np.float64)
    top = h[i0, j0] + (h[i0, j1] - h[i0, j0]) * fu
    bot = h[i1, j0] + (h[i1, j1] - h[i1, j0]) * fu
    return top + (bot - top) * fv, (i0, j0, i1, j1, fu, fv)


def _sobel_grad(h: np.ndarray, dx: float, dz: float, naive: bool) -> tuple[np.ndarray, np.ndarray]:
    """Interior Sobel gradient (H-2, W-2): float64 differences, or naive float32 row-major convolution."""
    kx = np.array([[-1, 0, 1], [-2, 0, 2], [-1, 0, 1]], np.float64)
    kz = kx.T
    rows, cols = h.shape
    dt = _F32 if naive else np.float64
    a = h.astype(dt)
    if naive:
        sx = np.zeros((rows - 2, cols - 2), _F32)
        sz = np.zeros((rows - 2, cols - 2), _F32)
        for r in range(3):
            for c in range(3):
                win = a[r:r + rows - 2, c:c + cols - 2]
                if kx[r, c]:
                    sx = (sx + _F32(kx[r, c]) * win).astype(_F32)
                if kz[r, c]:
                    sz = (sz + _F32(kz[r, c]) * win).astype(_F32)
        return sx.astype(np.float64) / (8.0 * dx), sz.astype(np.float64) / (8.0 * dz)
    sx = sum(kx[r, c] * (a[r:r + rows - 2, c:c + cols - 2]) for r in range(3) for c in range(3) if kx[r, c])
    sz = sum(kz[r, c] * (a[r:r + rows - 2, c:c + cols - 2]) for r in range(3) for c in range(3) if kz[r, c])
    return sx / (8.0 * dx), sz / (8.0 * dz)


def _normal(gx: np.ndarray, gz: np.ndarray) -> np.ndarray:
    n = np.stack([-gx, np.ones_like(gx), -gz], -1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between unit vectors, accurate for tiny angles (atan2 of |a x b| and a.b)."""
    a = a.astype(np.float64)
    b = b.astype(np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, -1)))


def _three_vertex64(h: np.ndarray, step: float, axis: int, naive: bool) -> np.ndarray:
    """Interior three-vertex curvature along an axis (0: x / columns, 1: z / rows)."""
    a = h if axis == 0 else h.T
    if naive:
        f = a.astype(_F32)
        ypp = ((f[:, 2:] + f[:, :-2] - _F32(2.0) * f[:, 1:-1]) / _F32(step * step)).astype(np.float64)
        yp = ((f[:, 2:] - f[:, :-2]) / _F32(2.0 * step)).astype(np.float64)
    else:
        f = a.astype(np.float64)
        s1 = (f[:, 1:-1] - f[:, :-2]) / step
        s2 = (f[:, 2:] - f[:, 1:-1]) / step
        ypp = (s2 - s1) / step
        yp = 0.5 * (s1 + s2)
    k = np.abs(ypp) / (1.0 + yp * yp) ** 1.5
    return k if axis == 0 else k.T


# ------------------------------------------------------------------------------------------------
# stages
# ------------------------------------------------------------------------------------------------
def _stage_sampling(case: ExtremeCase, scene) -> Row:
    hm = scene.heightmap
    h = hm.heights
    rows, cols = h.shape
    rng = np.random.default_rng(0)
    u = np.concatenate([rng.uniform(0, cols - 1, 512), [0.0, cols - 1, 0.5 * (cols - 1)]]).astype(_F32)
    v = np.concatenate([rng.uniform(0, rows - 1, 512), [0.0, rows - 1, 0.5 * (rows - 1)]]).astype(_F32)
    out = sample_grid(h, u, v, "bilinear")
    ref, (i0, j0, i1, j1, fu, fv) = _bilinear64(h, u, v)
    f = h.astype(_F32)
    fu32, fv32 = fu.astype(_F32), fv.astype(_F32)
    one = _F32(1.0)
    naive = (f[i0, j0] * (one - fu32) * (one - fv32) + f[i0, j1] * fu32 * (one - fv32)
             + f[i1, j0] * (one - fu32) * fv32 + f[i1, j1] * fu32 * fv32).astype(_F32)
    fin = np.isfinite(ref)
    _check(np.array_equal(np.isfinite(out), fin), "non-finite samples where the float64 reference is finite "
           "(or finite where it is NaN)")
    err = float(np.max(np.abs(out[fin] - ref[fin]))) if fin.any() else 0.0
    nerr = float(np.max(np.abs(naive[fin] - ref[fin]))) if fin.any() else 0.0
    scale = float(np.nanmax(np.abs(h))) if np.isfinite(h).any() else 0.0
    bound = 4.0 * float(np.spacing(_F32(max(scale, 1e-30))))
    _check(err <= bound, f"bilinear error {err:.3g} m exceeds 4 ulp of max|h| ({bound:.3g} m)")
    nan_note = f"; {int((~fin).sum())} samples NaN next to holes, as the reference" if (~fin).any() else ""
    return Row(case.name, "sampling", PASS, f"{_g(err)} m", f"{_g(nerr)} m",
               f"bilinear at 515 points; bound 4 ulp(max|h|) = {bound:.2g} m{nan_note}", digest(out))


def _stage_select(case: ExtremeCase, scene) -> Row:
    hm = scene.heightmap
    terrain = Terrain.prepare(hm, roots=4, tess=8)
    p = select(terrain, scene.camera, ScreenErrorPolicy(1.0))
    for nm in ("outer", "inner", "distance", "metric", "geometric_error", "origin", "size"):
        a = getattr(p, nm)
        _check(bool(np.all(np.isfinite(a))), f"{nm}: non-finite values in the PatchList")
    _check(bool(np.all(p.outer >= 1) and np.all(p.outer <= 64)), "outer: factors outside [1, 64]")
    lv = f"levels {int(p.level.min())}..{int(p.level.max())}" if len(p) else "no patch visible"
    return Row(case.name, "select", PASS, "", "", f"{len(p)} patches, {lv}, {p.stats.get('culled', 0)} culled; "
               "factors finite in [1, 64]",
               digest(p.level, p.key, p.outer, p.inner, p.origin_cells))


def _stage_tessellate(case: ExtremeCase, scene) -> Row:
    if case.factor is None:
        return _stage_lod_mesh(case, scene)
    f = case.factor
    notes, hashes = [], []
    for sp in SPACINGS:
        uv, tri = reference_tessellate_patch([f] * 4, [f] * 2, sp)
        _check(bool(np.all(np.isfinite(uv))) and bool(np.all((uv >= 0) & (uv <= 1))), f"{sp}: uv outside [0, 1]")
        culled = not (f > 0)  # <= 0 or NaN: the GPU discards the patch
        if culled:
            _check(len(tri) == 0, f"{sp}: factor {f} must cull the patch, got {len(tri)} triangles")
        else:
            w = check_watertight_domain(uv, tri)
            _check(w.n_open_edges == 0 and w.n_nonmanifold_edges == 0, f"{sp}: not watertight "
                   f"({w.n_open_edges} open, {w.n_nonmanifold_edges} non-manifold edges)")
            a = uv[tri]
            area = 0.5 * ((a[:, 1, 0] - a[:, 0, 0]) * (a[:, 2, 1] - a[:, 0, 1])
                          - (a[:, 2, 0] - a[:, 0, 0]) * (a[:, 1, 1] - a[:, 0, 1])).astype(np.float64)
            _check(bool(np.all(area > 0)), f"{sp}: {int((area <= 0).sum())} triangles not counter-clockwise")
            _check(abs(float(area.sum()) - 1.0) < 1e-6, f"{sp}: triangles cover area {area.sum()}, not 1")
            _check(len(tri) <= 2 * 64 * 64 + 4 * 64, f"{sp}: {len(tri)} triangles exceed the level-64 maximum")
        d = tessellate_domains(np.full((1, 4), f, _F32), np.full((1, 2), f, _F32), sp)
        _check(np.array_equal(d["uv"], uv) and np.array_equal(d["triangles"], tri),
               f"{sp}: frame kernel differs from reference_tessellate_patch")
        notes.append(f"{sp} {len(tri)}")
        hashes += [uv, tri]
    return Row(case.name, "tessellate", PASS, "", "",
               "triangles " + ", ".join(notes) + ("; culled" if not (f > 0) else "; watertight, ccw, area 1")
               + "; frame kernel identical", digest(*hashes))


def _lod_scene(scene: Scene, outputs: tuple[str, ...]) -> Scene:
    """The case's LOD frame: screen-error 1 px, 4 roots of tessellation level 8."""
    return scene.with_(mesh="lod", outputs=outputs, lod=LodConfig(roots=4, tess=8))


def _stage_lod_mesh(case: ExtremeCase, scene: Scene) -> Row:
    fr = render(_lod_scene(scene, ("mesh",)))
    m = fr.mesh
    _check(bool(np.all(np.isfinite(m.positions))), f"mesh: {int((~np.isfinite(m.positions)).any(1).sum())} "
           "vertices with non-finite positions")
    if m.n_triangles == 0:
        return Row(case.name, "tessellate", PASS, "", "", "no visible patch (empty mesh)", digest(m.triangles))
    w = check_watertight(m, allowed=lod_boundary(fr.patches, scene.heightmap, m.eye))
    status = PASS if w.n_open_edges == 0 and w.n_nonmanifold_edges == 0 else FAIL
    return Row(case.name, "tessellate", status, "", "",
               f"LOD mesh {m.n_vertices} vertices, {m.n_triangles} triangles, {len(fr.patches)} patches; "
               f"{w.n_open_edges} open interior edges (cracks), {w.n_nonmanifold_edges} non-manifold",
               digest(m.positions, m.triangles))


def _stage_normals(case: ExtremeCase, scene) -> Row:
    hm = scene.heightmap
    n = compute_normals(hm, "sobel", border="skip")
    _check(bool(np.all(np.isfinite(n))), "normals: non-finite values")
    _check(float(np.max(np.abs(np.linalg.norm(n.astype(np.float64), axis=-1) - 1.0))) < 1e-5, "normals: not unit")
    h = hm.heights
    if min(h.shape) < 3:
        return Row(case.name, "normals", PASS, "", "", "finite unit normals (no interior sample to compare)",
                   digest(n))
    win_ok = np.ones((h.shape[0] - 2, h.shape[1] - 2), bool)
    for r in range(3):
        for c in range(3):
            win_ok &= np.isfinite(h[r:r + h.shape[0] - 2, c:c + h.shape[1] - 2])
    ref = _normal(*_sobel_grad(h, hm.dx, hm.dz, naive=False))
    nai = _normal(*_sobel_grad(h, hm.dx, hm.dz, naive=True))
    inner = n[1:-1, 1:-1]
    err = float(np.max(_angle_deg(inner, ref)[win_ok])) if win_ok.any() else 0.0
    nerr = float(np.max(_angle_deg(nai, ref)[win_ok])) if win_ok.any() else 0.0
    return Row(case.name, "normals", PASS, f"{_g(err)} deg", f"{_g(nerr)} deg",
               f"Sobel, {int(win_ok.sum())} interior samples vs float64; finite unit everywhere", digest(n))


def _stage_curvature(case: ExtremeCase, scene) -> Row:
    hm = scene.heightmap
    h = hm.heights
    k = compute_curvature(hm, "three_vertex")
    nan_h = np.isnan(h)
    _check(bool(np.all(np.isfinite(k[~nan_h]))), "curvature: non-finite values away from holes")
    _check(bool(np.all(k[~nan_h] >= 0)), "curvature: negative values")
    if case.name == "flat":
        _check(bool(np.all(k == 0)), "flat plane: curvature not exactly 0")
    errs, nerrs, kmax = [], [], 0.0
    for axis, step in ((0, hm.dx), (1, hm.dz)):
        if h.shape[1 - axis] < 3:
            continue
        ref = _three_vertex64(h, step, axis, False)
        nai = _three_vertex64(h, step, axis, True)
        got = (k[:, 1:-1, 0] if axis == 0 else k[1:-1, :, 1]).astype(np.float64)
        ok = np.isfinite(ref)
        if ok.any():
            kmax = max(kmax, float(np.max(ref[ok])))
            errs.append(float(np.max(np.abs(got[ok] - ref[ok]))))
            nerrs.append(float(np.max(np.abs(nai[ok] - ref[ok]))))
    if not errs:
        return Row(case.name, "curvature", PASS, "", "", "finite, >= 0 (no interior sample)", digest(k))
    err, nerr = max(errs), max(nerrs)
    rel = err / kmax if kmax > 0 else err
    nrel = nerr / kmax if kmax > 0 else nerr
    unit = "(relative to max)" if kmax > 0 else "1/m (reference is 0)"
    return Row(case.name, "curvature", PASS, f"{_g(rel)} {unit}", f"{_g(nrel)} {unit}",
               f"three-vertex x and z, interior vs float64; max k = {kmax:.3g} 1/m", digest(k))


def _grid_world64(hm) -> np.ndarray:
    rows, cols = hm.shape
    jj, ii = np.meshgrid(np.arange(cols, dtype=np.float64), np.arange(rows, dtype=np.float64))
    y = np.where(np.isnan(hm.heights), 0.0, hm.heights.astype(np.float64))
    return np.stack([hm.origin[0] + jj * hm.dx, y, hm.origin[1] + ii * hm.dz], -1).reshape(-1, 3)


def _stage_raster(case: ExtremeCase, scene) -> Row:
    fr = render(scene.with_(outputs=("image", "depth", "normals", "mesh")))
    d = fr.depth
    _check(bool(np.all(np.isfinite(d))) and float(d.min()) >= 0.0 and float(d.max()) <= 1.0,
           "depth: outside [0, 1] or non-finite")
    _check(bool(np.all(np.isfinite(fr.normals))), "normals image: non-finite")
    m = fr.mesh
    hm = scene.heightmap
    cam = scene.camera
    if np.isnan(hm.heights).any():
        bad = np.isnan(hm.heights.reshape(-1))[m.triangles].any(axis=1)
        _check(not bad.any(), f"{int(bad.sum())} triangles touch a NaN hole")
    world = _grid_world64(hm)
    eye = np.asarray(cam.position, np.float64)
    exact = world - eye
    err_m = float(np.max(np.abs(m.positions.astype(np.float64) - exact)))
    naive = (world.astype(_F32) - eye.astype(_F32)).astype(_F32)
    nerr_m = float(np.max(np.abs(naive.astype(np.float64) - exact)))
    mvp = cam.proj_matrix() @ cam.view_matrix(relative=True)

    def proj(p):
        q = p @ mvp[:, :3].T + mvp[:, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.stack([q[:, 0] / q[:, 3] * 0.5 * cam.width, q[:, 1] / q[:, 3] * 0.5 * cam.height], 1), q

    pe, q = proj(exact)
    vis = (q[:, 3] > cam.near) & np.all(np.abs(q[:, :3]) <= q[:, 3:4], axis=1)
    err_px = float(np.max(np.linalg.norm(proj(m.positions.astype(np.float64))[0] - pe, axis=1)[vis])) \
        if vis.any() else 0.0
    nerr_px = float(np.max(np.linalg.norm(proj(naive.astype(np.float64))[0] - pe, axis=1)[vis])) \
        if vis.any() else 0.0
    changed = 0
    if len(m.triangles):
        fn = rasterize(naive, m.triangles, cam.view_matrix(relative=True), cam.proj_matrix(), cam.width, cam.height)
        changed = int(np.sum(fn.triangle_id != fr.triangle_id))
    covm = fr.triangle_id >= 0
    cov = float(np.mean(covm))
    dv = d[covm]
    depth_note = (f"; depth of covered px in [{float(dv.min()):.7g}, {float(dv.max()):.7g}], "
                  f"{len(np.unique(dv))} distinct values") if dv.size else ""
    return Row(case.name, "raster", PASS, f"{_g(err_m)} m, {_g(err_px)} px", f"{_g(nerr_m)} m, {_g(nerr_px)} px, "
               f"{changed} px changed", f"grid mesh {m.n_triangles} triangles, coverage {cov:.1%}; depth in [0, 1]"
               + depth_note,
               digest(fr.triangle_id, fr.depth, fr.barycentrics))


def _stage_error(case: ExtremeCase, scene) -> Row:
    fr = render(scene.with_(outputs=("error",)))
    e = fr.error
    vals = (e.max_px, e.p99_px, e.mean_px)
    _check(all(math.isfinite(x) and x >= 0 for x in vals), f"error: non-finite or negative {vals}")
    if case.name == "flat":
        # Exactly 0 needs camera-relative heights that float32 represents exactly (tests/experiments/test_stability.py
        # checks that with an eye at y = 32 m); with this eye (y = 27.47... m) every height rounds by up
        # to ulp/2 = 9.5e-7 m, which is all the reprojection error may be.
        _check(e.max_px <= 1e-4, f"flat plane: grid error {e.max_px} px, expected float32 rounding only")
    note = (f"grid vs its reference: max {e.max_px:.3g} px over {e.samples_visible} samples (image error max "
            f"{e.image_err_max_px:.3g} px over {e.covered} px)")
    el = render(_lod_scene(scene, ("error",))).error
    _check(all(math.isfinite(x) and x >= 0 for x in (el.max_px, el.p99_px)), "LOD error: non-finite or < 0")
    note += f"; LOD (sse 1 px) max {el.max_px:.3g} px, p99 {el.p99_px:.3g} px, {el.see_through_px} see-through px"
    return Row(case.name, "error", PASS, f"{_g(e.max_px)} px", "", note,
               digest(fr.error.error_map if fr.error.error_map is not None else np.zeros(0)))


def _stage_fit(case: ExtremeCase, scene) -> Row:
    """The JAX relaxed LOD model of :mod:`terrainwarp.fit` (the sse policy's, on its error probes): finite cost,
    error and gradients, and the gradient against a central finite difference of the same float32 model (one
    jitted program per model spec and padded size: the small cases share it, and JAX's cache keeps it)."""
    import jax.numpy as jnp  # lazy: heavy optional dependency

    sc = scene.with_(lod=LodConfig(roots=4, tess=8))
    model = relaxed_model(sc, [scene.camera], "sse")
    u = jnp.asarray([model.knobs[0].to_unit(1.0)], jnp.float32)
    (c, gc), (e, ge) = _fit_grads()(model.spec, model.data, u)
    vals = [float(c), float(gc[0]), float(e), float(ge[0])]
    _check(all(math.isfinite(v) for v in vals), f"relaxed model: non-finite cost/error/gradients {vals}")
    h = 1e-2
    fd = (float(_fit_grads()(model.spec, model.data, u + h)[0][0])
          - float(_fit_grads()(model.spec, model.data, u - h)[0][0])) / (2 * h)
    noise = 4.0 * float(np.spacing(_F32(abs(float(c))))) / (2 * h)  # what a float32 FD can resolve
    diff = abs(float(gc[0]) - fd)
    if diff <= noise:
        txt = f"{_g(diff)} (grad vs FD, within FD resolution {noise:.2g})"
    else:
        txt = f"{_g(diff / max(abs(fd), abs(float(gc[0]))))} (grad vs FD, relative)"
    return Row(case.name, "fit", PASS, txt, "",
               f"relaxed sse model at tolerance 1 px, temperature 0.5: log cost {float(c):.4g}, "
               f"d/du = {float(gc[0]):.4g}, log p99 {float(e):.3g}; finite", "")


_FIT_JIT: dict = {}


def _fit_grads():
    """jitted (spec static): ((log cost, its gradient), (log p99, its gradient)) of the first camera at
    temperature 0.5."""
    if "grads" not in _FIT_JIT:
        import jax  # lazy: heavy optional dependency
        import jax.numpy as jnp

        def cost(spec, data, u):
            return jnp.log(spec.relaxed(data, u, jnp.float32(0.5))[0][0])

        def err(spec, data, u):
            return spec.relaxed(data, u, jnp.float32(0.5))[1][0]

        _FIT_JIT["grads"] = jax.jit(lambda spec, data, u: (jax.value_and_grad(cost, argnums=2)(spec, data, u),
                                                           jax.value_and_grad(err, argnums=2)(spec, data, u)),
                                    static_argnums=0)
    return _FIT_JIT["grads"]


_STAGE_FUNCS = {"sampling": _stage_sampling, "select": _stage_select, "tessellate": _stage_tessellate,
                "normals": _stage_normals, "curvature": _stage_curvature, "raster": _stage_raster,
                "error": _stage_error, "fit": _stage_fit}


def run_case(case: ExtremeCase, n: int = 33, stages: tuple[str, ...] = STAGES) -> list[Row]:
    """Run one case through the given stages (see the module docstring)."""
    try:
        scene = case.build(n)
    except (ValueError, TypeError) as e:
        return [Row(case.name, "build", RAISED, note=str(e).splitlines()[0])]
    rows = []
    for st in stages:
        if case.group == "tess" and st != "tessellate":
            continue  # factor cases only differ in the tessellator
        try:
            rows.append(_STAGE_FUNCS[st](case, scene))
        except _Fail as e:
            rows.append(Row(case.name, st, FAIL, note=str(e)))
        except Exception as e:  # noqa: BLE001 - every exception is a row: a clear error, or a failure
            rows.append(_exception_row(case.name, st, e))
    return rows


# a clear error names its argument first: "name: expected X, got Y" (the public boundary's convention)
_CLEAR = re.compile(r"^[A-Za-z_][\w.\[\]]*: ")


def _exception_row(case: str, stage: str, e: Exception) -> Row:
    """``raised`` for a clear ValueError/TypeError naming its argument; otherwise a FAIL naming the exception
    type and where it was raised (function, file:line of the innermost frame)."""
    msg = str(e).splitlines()[0] if str(e) else ""
    if isinstance(e, ValueError | TypeError) and _CLEAR.match(msg):
        return Row(case, stage, RAISED, note=msg)
    tb = traceback.extract_tb(e.__traceback__)[-1]
    where = "/".join(Path(tb.filename).parts[-2:])
    return Row(case, stage, FAIL, note=f"unexpected {type(e).__name__} in stage {stage}: {msg[:100]} "
                                       f"(in {tb.name}, {where}:{tb.lineno})")


def run_suite(n: int = 33, cases: list[str] | None = None, stages: tuple[str, ...] = STAGES,
              progress: bool = False) -> list[Row]:
    """Every case (or the named ones) through every stage; grids of about ``n`` x ``n`` samples."""
    names = list(CASES) if cases is None else list(cases)
    bad = [c for c in names if c not in CASES]
    if bad:
        raise ValueError(f"cases: unknown {bad}; expected some of {list(CASES)}")
    bad = [s for s in stages if s not in STAGES]
    if bad:
        raise ValueError(f"stages: unknown {bad}; expected some of {list(STAGES)}")
    rows: list[Row] = []
    for name in names:
        t0 = time.perf_counter()
        rows += run_case(CASES[name], n, stages)
        if progress:
            print(f"  {name}: {time.perf_counter() - t0:.1f} s", flush=True)
    return rows


def stage_hashes(rows: list[Row]) -> dict[str, str]:
    """{"case/stage": hash} of every row with an output."""
    return {f"{r.case}/{r.stage}": r.hash for r in rows if r.hash}


# Why a FAIL is a known open problem, by a phrase of its note (none today: every FAIL is unexplained).
EXPLANATIONS: dict[str, str] = {}


def _esc(s: str) -> str:
    return s.replace("|", "\\|")


def write_stability_md(rows: list[Row], out_dir: str | Path, *, title: str = "Stability suite",
                       command: str = "terrainwarp stability --out DIR", n: int = 33) -> Path:
    """Write ``stability.md`` (atomically) under ``out_dir``: a case x stage summary and one row per
    (case, stage) with the error with and without the float32 remedies."""
    out = Path(out_dir)
    cases = list(dict.fromkeys(r.case for r in rows))
    stages = [s for s in ("build", *STAGES) if any(r.stage == s for r in rows)]
    by = {(r.case, r.stage): r for r in rows}
    counts = {s: sum(r.status == s for r in rows) for s in (PASS, RAISED, FAIL)}
    lines = [f"# {title}", "", f"Command: `{command}`; grids of {n} x {n} samples (fixed-shape cases keep "
             "theirs). float32 product against a float64 reference computed in numpy.", "",
             f"Outcomes: {counts[PASS]} pass, {counts[RAISED]} clear errors raised, {counts[FAIL]} FAIL.", "",
             "Remedies measured (\"with\" = the product, \"without\" = the naive float32 computation): sampling "
             "weights heights relative to the cell's first sample; normals difference samples pairwise before "
             "summing; curvature takes chord slopes before the second difference; the rasterizer gets "
             "camera-relative positions (world - eye in float64, then float32) instead of absolute float32 "
             "positions minus a float32 eye (\"px changed\": pixels whose visible triangle changes).", "",
             "## Summary (case x stage)", "",
             "| case | catches | " + " | ".join(stages) + " |", "|---|---|" + "---|" * len(stages)]
    for c in cases:
        cells = []
        for s in stages:
            r = by.get((c, s))
            cells.append("" if r is None else r.status)
        lines.append(f"| {c} | {_esc(CASES[c].catches) if c in CASES else ''} | " + " | ".join(cells) + " |")
    lines += ["", "## Details", "", "| case | stage | status | error (with remedy) | error without remedy | note |",
              "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r.case} | {r.stage} | {r.status} | {_esc(r.error)} | {_esc(r.naive)} | {_esc(r.note)} |")
    fails = [r for r in rows if r.status == FAIL]
    if fails:
        lines += ["", "## Failures", ""]
        seen: dict[str, list[str]] = {}
        for r in fails:
            key = next((k for k in EXPLANATIONS if k in r.note), r.note)
            seen.setdefault(key, []).append(f"{r.case}/{r.stage}")
        for key, where in seen.items():
            why = EXPLANATIONS.get(key, "UNEXPLAINED")
            lines.append(f"- {_esc(key)} ({len(where)}: {', '.join(where[:6])}{' ...' if len(where) > 6 else ''}): "
                         f"{why}")
        lines.append("")
    raised = [r for r in rows if r.status == RAISED]
    if raised:
        lines += ["## Clear errors raised", ""] + [f"- {r.case} / {r.stage}: {_esc(r.note)}" for r in raised] + [""]
    return write_text(out / "stability.md", "\n".join(lines))

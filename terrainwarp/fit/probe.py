"""Error probes: what each visible heightmap sample's error would be, per camera, if the surface above it were
drawn at each resolution a family can draw it at; measured once, before a fit tries any setting.

This is Martini's shape (the error map is computed once, independent of the threshold, so selecting for a new
threshold is cheap) carried to the screen: for a quadtree with patches of T segments, resolution L is the surface
every level-L patch draws (:func:`terrainwarp.lod.quadtree.uniform_patches`); for CDLOD, a LOD's unmorphed grid;
for the continuous policy, the level's patches at one uniform fractional factor. The surface of each resolution
is made once per heightmap (``render`` of that uniform selection, then
:func:`terrainwarp.measure.sample_error.surface_heights`); each camera then measures it with the primary error's
own kernel (:func:`terrainwarp.kernels.sample_error.sample_displacement`: the same projection and the same
visibility against the camera's full-detail depth). A setting's frame draws each sample at one resolution (its
leaf's), so its error map is read off the probes; edge factors toward finer neighbours, CDLOD's morph and the
2:1 balance are what the models leave out (:mod:`terrainwarp.fit.relaxed`), and the fit's exact tries calibrate.

Measured on the bundled DEM (8 cameras of the ground path, 960x540, sse, T = 16): the probes' p99 per camera is
within 1% of the exact frame's at tolerances 0.5-4 px; at T = 1 (two triangles a patch, where doubled edges touch
every sample) 5-20% above it.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..camera import Camera, relative_origin
from ..heightmap import Heightmap
from ..kernels import sample_error as _k
from ..measure.sample_error import surface_heights
from ..mesh import Mesh
from ..rendering.pipeline import Frame

__all__ = ["CameraProbe", "probe_cameras", "surfaces_of", "pop_pairs", "FLOOR_PX"]

FLOOR_PX = 1e-4  # errors below this (a sample on a vertex: exactly 0) are taken as this, so their log is finite


@dataclass(frozen=True)
class CameraProbe:
    """One camera's probe.

    Attributes:
        rows, cols: (V,) int32 the kept visible samples (every visible sample, or a deterministic subset of
            ``max_samples``).
        err: (R, V) float32 each kept sample's projected error (px) at each resolution (at least ``FLOOR_PX``).
        visible: visible samples in all (kept or not).
        eye: the camera's position.
        dist: (V,) float32 eye-to-sample distance (m).
    """

    rows: np.ndarray
    cols: np.ndarray
    err: np.ndarray
    visible: int
    eye: tuple[float, float, float]
    dist: np.ndarray

    def subset(self, n: int) -> CameraProbe:
        """At most ``n`` of the kept samples (a deterministic subset)."""
        if len(self.rows) <= n:
            return self
        keep = _choose(len(self.rows), n)
        return CameraProbe(self.rows[keep], self.cols[keep], self.err[:, keep], self.visible, self.eye,
                           self.dist[keep])


def _choose(total: int, n: int) -> np.ndarray:
    """``n`` of ``total`` indices, sorted: the same for the same sizes on every run."""
    return np.sort(np.random.default_rng(0x7E55).choice(total, size=n, replace=False))


def surfaces_of(heightmap: Heightmap, meshes: list[Mesh | None]) -> list[np.ndarray | None]:
    """Each mesh's surface height (world m, float64 (rows, cols)) at every sample; None stays None (the samples
    themselves: the full-detail surface)."""
    return [None if m is None else surface_heights(heightmap, m) for m in meshes]


def probe_cameras(heightmap: Heightmap, cameras: list[Camera], refs: list[Frame], surfaces: list[np.ndarray | None],
                  *, max_samples: int = 1 << 20, on_camera: Callable[[], None] | None = None) -> list[CameraProbe]:
    """Each camera's probe of the given resolutions' surfaces (None: the samples themselves, error 0).

    A sample is kept where it is visible (in view and passing the full-detail depth test) and every resolution
    draws a surface above it."""
    hm = heightmap
    out = []
    for cam, ref in zip(cameras, refs, strict=True):
        if ref.depth is None:
            raise ValueError("refs: expected the full-detail frames with depth")
        rel = relative_origin(hm.origin, cam.position)
        mvp = cam.proj_matrix() @ cam.view_matrix(relative=True)
        errs, ok = [], None
        for y in surfaces:
            yb = np.asarray(hm.heights, np.float64) if y is None else y
            e, st, _ = _k.sample_displacement(hm.heights, None, yb - float(cam.position[1]), ref.depth, rel,
                                              (hm.dx, hm.dz), mvp, cam.near, cam.far)
            vis = st == _k.VISIBLE
            ok = vis if ok is None else ok & vis
            errs.append(np.where(vis, e, np.nan))
        rows, cols = np.nonzero(ok)
        visible = len(rows)
        if visible > max_samples:
            keep = _choose(visible, max_samples)
            rows, cols = rows[keep], cols[keep]
        err = np.stack([np.clip(e[rows, cols], FLOOR_PX, 1e6) for e in errs]).astype(np.float32)
        x = hm.origin[0] + cols * hm.dx - cam.position[0]
        z = hm.origin[1] + rows * hm.dz - cam.position[2]
        h = hm.heights[rows, cols].astype(np.float64) - cam.position[1]
        dist = np.sqrt(x * x + z * z + h * h).astype(np.float32)
        out.append(CameraProbe(rows.astype(np.int32), cols.astype(np.int32), err, visible,
                               tuple(float(v) for v in cam.position), dist))
        if on_camera is not None:
            on_camera()
    return out


def pop_pairs(heightmap: Heightmap, cameras: list[Camera], refs: list[Frame], surfaces: list[np.ndarray | None],
              probes: list[CameraProbe]) -> list[np.ndarray]:
    """For each camera after the first: how far each of its probe's kept samples moves on its screen (px) when
    the surface above it changes from one resolution to another, for every pair ``(a, b)``, ``a < b``
    (:func:`itertools.combinations` order): (pairs, V) float32, at least ``FLOOR_PX`` (the pop between two
    consecutive selections, :func:`terrainwarp.measure.sample_error.popping`, read per sample)."""
    hm = heightmap
    out = []
    ys = [np.asarray(hm.heights, np.float64) if y is None else y for y in surfaces]
    for cam, ref, probe in zip(cameras[1:], refs[1:], probes[1:], strict=True):
        rel = relative_origin(hm.origin, cam.position)
        mvp = cam.proj_matrix() @ cam.view_matrix(relative=True)
        eye = float(cam.position[1])
        rows = []
        for a, b in itertools.combinations(range(len(ys)), 2):
            e, _, _ = _k.sample_displacement(hm.heights, ys[a] - eye, ys[b] - eye, ref.depth, rel, (hm.dx, hm.dz),
                                             mvp, cam.near, cam.far)
            rows.append(np.clip(np.nan_to_num(e[probe.rows, probe.cols], nan=FLOOR_PX), FLOOR_PX, 1e6))
        out.append(np.stack(rows).astype(np.float32) if rows else np.zeros((0, len(probe.rows)), np.float32))
    return out

"""Error probes: what each visible heightmap sample's error would be, per camera, if the surface above it were
drawn at each resolution a family can draw it at; measured once, before a fit tries any setting.

This is Martini's shape (the error map is computed once, independent of the threshold, so selecting for a new
threshold is cheap) carried to the screen: for a quadtree with patches of T segments, resolution L is the surface
every level-L patch draws (:func:`terrainwarp.lod.quadtree.uniform_patches`); for CDLOD, a LOD's unmorphed grid;
for the continuous policy, the level's patches at one uniform fractional factor. A setting's frame draws each
sample at one resolution (its leaf's), so its error map is read off the probes; edge factors toward finer
neighbours, CDLOD's morph and the 2:1 balance are what the models leave out (:mod:`terrainwarp.fit.relaxed`), and
the fit's exact tries calibrate.

Work in proportion to what the cameras see: one pass a camera over the heightmap finds the samples it sees
(:func:`sight`: in view, passing its full-detail depth test); a resolution's surface is drawn only from the
patches (quadrants) that may hold one of them (``render`` of that part of the uniform selection) and evaluated at
those samples alone (:func:`terrainwarp.kernels.sample_error.surface_at`); each camera measures it at its own
samples with the primary error's kernel (:func:`terrainwarp.kernels.sample_error.displacement_at`: the same
projection and the same visibility against the camera's full-detail depth as
:func:`terrainwarp.kernels.sample_error.sample_displacement`). The probes are those of drawing and measuring the
whole grid, bit for bit: a sample takes the lowest-numbered triangle that holds it, and the patches left out hold
none of the samples measured. The continuous policy's rungs are placed at the samples without tessellating every
patch (:mod:`terrainwarp.fit.ladder`), to the same bits.

Measured on the bundled DEM (8 cameras of the ground path, 960x540, sse, T = 16): the probes' p99 per camera is
within 1% of the exact frame's at tolerances 0.5-4 px; at T = 1 (two triangles a patch, where doubled edges touch
every sample) 5-20% above it.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from ..camera import Camera, relative_origin
from ..heightmap import Heightmap
from ..kernels import sample_error as _k
from ..mesh import Mesh
from ..rendering.pipeline import Frame

__all__ = ["CameraProbe", "Sight", "sight", "probe_cameras", "surfaces_of", "pop_pairs", "FLOOR_PX"]

FLOOR_PX = 1e-4  # errors below this (a sample on a vertex: exactly 0) are taken as this, so their log is finite
LAUNCH_SAMPLES = 1 << 22  # samples x surfaces measured in one launch (a camera's surfaces batched up to this)


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


@dataclass(frozen=True)
class Sight:
    """The samples a camera path sees: what the probes measure, and all they need the drawn surfaces at.

    Attributes:
        rows, cols: (U,) int32 every sample visible from at least one camera (in view, passing its full-detail
            depth test), row-major.
        seen: per camera, (n,) int64 the indices (into ``rows``/``cols``) of the samples it sees, ascending.
        shape: the heightmap's (rows, cols).
    """

    rows: np.ndarray
    cols: np.ndarray
    seen: list[np.ndarray]
    shape: tuple[int, int]

    @cached_property
    def _counts(self) -> np.ndarray:
        """(rows + 1, cols + 1) int64: the visible samples in each top-left rectangle (an integral image)."""
        h, w = self.shape
        out = np.zeros((h + 1, w + 1), np.int64)
        np.add.at(out, (self.rows.astype(np.int64) + 1, self.cols.astype(np.int64) + 1), 1)
        return out.cumsum(0).cumsum(1)

    def touching(self, x0: np.ndarray, y0: np.ndarray, size: np.ndarray) -> np.ndarray:
        """(P,) bool: which squares (corner column ``x0``, row ``y0``, side ``size``, in cells) hold a visible sample
        on them or within a cell of them (a patch whose triangles may hold one)."""
        h, w = self.shape
        x0, y0 = np.asarray(x0, np.float64), np.asarray(y0, np.float64)
        x1, y1 = x0 + np.asarray(size, np.float64), y0 + np.asarray(size, np.float64)
        c0 = np.clip(np.floor(x0) - 1, 0, w).astype(np.int64)
        c1 = np.clip(np.ceil(x1) + 2, 0, w).astype(np.int64)  # exclusive
        r0 = np.clip(np.floor(y0) - 1, 0, h).astype(np.int64)
        r1 = np.clip(np.ceil(y1) + 2, 0, h).astype(np.int64)
        n = self._counts
        return (n[r1, c1] - n[r0, c1] - n[r1, c0] + n[r0, c0]) > 0


def sight(heightmap: Heightmap, cameras: list[Camera], refs: list[Frame], device: str = "cpu") -> Sight:
    """The samples each camera sees (one pass over the heightmap per camera): the probes measure no other, so a
    surface needs drawing only where it lies above one (:meth:`Sight.touching`)."""
    hm = heightmap
    h64 = np.asarray(hm.heights, np.float64)
    lins = []
    for cam, ref in zip(cameras, refs, strict=True):
        if ref.depth is None:
            raise ValueError("refs: expected the full-detail frames with depth")
        rel = relative_origin(hm.origin, cam.position)
        mvp = cam.proj_matrix() @ cam.view_matrix(relative=True)
        _, st, _ = _k.sample_displacement(hm.heights, None, h64 - float(cam.position[1]), ref.depth, rel,
                                          (hm.dx, hm.dz), mvp, cam.near, cam.far, device=device)
        lins.append(np.flatnonzero(st == _k.VISIBLE))
    union = np.unique(np.concatenate(lins)) if lins else np.zeros(0, np.int64)
    rows, cols = np.divmod(union, hm.shape[1])
    return Sight(rows.astype(np.int32), cols.astype(np.int32), [np.searchsorted(union, lin) for lin in lins],
                 (int(hm.shape[0]), int(hm.shape[1])))


def surfaces_of(heightmap: Heightmap, meshes: list[Mesh | None], at: Sight,
                device: str = "cpu") -> list[np.ndarray | None]:
    """Each mesh's surface height (world m, float64) above every sample of ``at`` ((U,), in its order; NaN where
    the mesh holds none: :func:`terrainwarp.measure.sample_error.surface_heights` at those samples, bit for
    bit); None stays None (the samples themselves: the full-detail surface)."""
    out: list[np.ndarray | None] = []
    for m in meshes:
        if m is None:
            out.append(None)
            continue
        y, _ = _k.surface_at(m.positions, m.triangles, (0.0, 0.0, 0.0), relative_origin(heightmap.origin, m.eye),
                             (heightmap.dx, heightmap.dz), heightmap.shape, at.rows, at.cols, device=device)
        out.append(y + float(m.eye[1]))
    return out


def probe_cameras(heightmap: Heightmap, cameras: list[Camera], refs: list[Frame], surfaces: list[np.ndarray | None],
                  at: Sight, *, max_samples: int = 1 << 20, on_camera: Callable[[], None] | None = None,
                  device: str = "cpu") -> list[CameraProbe]:
    """Each camera's probe of the given resolutions' surfaces (:func:`surfaces_of` at ``at``'s samples; None: the
    samples themselves, error 0).

    A sample is kept where it is visible (in view and passing the full-detail depth test) and every resolution
    draws a surface above it. Only the samples the camera sees are measured (``at.seen``), a camera's surfaces in
    one launch (up to :data:`LAUNCH_SAMPLES` samples)."""
    hm = heightmap
    hu = np.asarray(hm.heights, np.float64)[at.rows, at.cols]
    out = []
    for cam, ref, idx in zip(cameras, refs, at.seen, strict=True):
        rel = relative_origin(hm.origin, cam.position)
        mvp = cam.proj_matrix() @ cam.view_matrix(relative=True)
        r, c = at.rows[idx], at.cols[idx]
        errs, ok = [], np.ones(len(idx), bool)
        per = max(1, LAUNCH_SAMPLES // max(len(idx), 1))  # surfaces measured in one launch
        for k in range(0, len(surfaces), per):
            group = surfaces[k:k + per]
            yb = np.concatenate([(hu if y is None else y)[idx] for y in group]) - float(cam.position[1])
            e, st = _k.displacement_at(hm.heights, np.tile(r, len(group)), np.tile(c, len(group)), None, yb,
                                       ref.depth, rel, (hm.dx, hm.dz), mvp, cam.near, cam.far, device=device)
            for e_s, st_s in zip(np.split(e, len(group)), np.split(st, len(group)), strict=True):
                ok &= st_s == _k.VISIBLE
                errs.append(e_s)
        keep = np.flatnonzero(ok)
        visible = len(keep)
        if visible > max_samples:
            keep = keep[_choose(visible, max_samples)]
        rows, cols = r[keep].astype(np.int64), c[keep].astype(np.int64)
        err = np.stack([np.clip(e[keep], FLOOR_PX, 1e6) for e in errs]).astype(np.float32)
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
              probes: list[CameraProbe], at: Sight, device: str = "cpu") -> list[np.ndarray]:
    """For each camera after the first: how far each of its probe's kept samples moves on its screen (px) when
    the surface above it changes from one resolution to another, for every pair ``(a, b)``, ``a < b``
    (:func:`itertools.combinations` order): (pairs, V) float32, at least ``FLOOR_PX`` (the pop between two
    consecutive selections, :func:`terrainwarp.measure.sample_error.popping`, read per sample)."""
    hm = heightmap
    hu = np.asarray(hm.heights, np.float64)[at.rows, at.cols]
    ys = [hu if y is None else y for y in surfaces]
    union = at.rows.astype(np.int64) * hm.shape[1] + at.cols
    out = []
    for cam, ref, probe in zip(cameras[1:], refs[1:], probes[1:], strict=True):
        rel = relative_origin(hm.origin, cam.position)
        mvp = cam.proj_matrix() @ cam.view_matrix(relative=True)
        eye = float(cam.position[1])
        u = np.searchsorted(union, probe.rows.astype(np.int64) * hm.shape[1] + probe.cols)
        rows = []
        pairs = list(itertools.combinations(range(len(ys)), 2))
        per = max(1, LAUNCH_SAMPLES // max(len(u), 1))  # pairs measured in one launch
        for k in range(0, len(pairs), per):
            group = pairs[k:k + per]
            ya = np.concatenate([ys[a][u] for a, _ in group]) - eye
            yb = np.concatenate([ys[b][u] for _, b in group]) - eye
            e, _ = _k.displacement_at(hm.heights, np.tile(probe.rows, len(group)), np.tile(probe.cols, len(group)),
                                      ya, yb, ref.depth, rel, (hm.dx, hm.dz), mvp, cam.near, cam.far, device=device)
            rows += [np.clip(np.nan_to_num(x, nan=FLOOR_PX), FLOOR_PX, 1e6) for x in np.split(e, len(group))]
        out.append(np.stack(rows).astype(np.float32) if rows else np.zeros((0, len(probe.rows)), np.float32))
    return out

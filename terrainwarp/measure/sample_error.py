"""Screen-space error measured at the heightmap's samples (the primary error), and popping.

**The definition.** For every visible heightmap sample P = (x, h, z), the error is the distance in pixels
between the projections of P and of P' = (x, h_lod, z), the point of the drawn LOD surface at the same
(x, z), both projected exactly (float64) with the frame's camera. This is how Cesium, CDLOD, Chunked LOD,
Martini and Delatin define geometric error (the vertical distance between a sample and the simplified
surface above it), carried to the screen.

**Why this and not a per-pixel comparison.** Every family's full-detail mesh passes through every sample,
so under this definition it scores 0 whatever its diagonals: the quadtree tessellator at its deepest level
(which mirrors its diagonals about each patch's centre lines), Martini and Delatin at error 0, the polytree
at tolerance 0, and the full grid. A per-pixel comparison against the fixed-diagonal grid
(:func:`terrainwarp.measure.error.frame_error`) instead carries a triangulation floor (p99 about 1 px at 10%
clearance and 2.4 to 3.5 px at 2% on the bundled DEM at 1080p), which makes the budgets engines use (Nanite
1 px, Cesium 2 px) unreachable near the ground; a per-pixel comparison against each family's own
full-detail mesh would need one reference per family and still could not compare families with each other.
(The bintree's finest level is 0 only where its vertex grid falls on the samples: its vertices sit on a
grid of side / 2^k, with heights from the three nearest samples.)

**How, per frame (three launches; no Python loop over samples or pixels).**

1. h_lod at every sample (:func:`terrainwarp.kernels.sample_error.surface_at_samples`): a top-down raster
   whose pixels are the samples, done as a scatter over the drawn triangles (each claims the samples inside
   its (x, z) footprint, inclusive, float64; the lowest triangle id wins where footprints touch or overlap),
   then the claiming triangle's plane evaluated in float64 at the sample's (x, z). The samples'
   camera-relative (x, z) and h are float32, rounded exactly as the pipeline's grid vertices are, so a
   sample that is a mesh vertex scores exactly 0. (The pipeline's rasterizer with an orthographic camera
   would give the samples on a mesh's outer boundary to no triangle, by its fill rule, and would miss
   triangles smaller than a cell that hold a sample but no pixel centre.)
2. Visibility: P lies in the viewport and between the near and far planes, and passes the depth test
   against the full-detail frame's depth buffer (``ref_depth``: the grid frame of the same camera, window
   depth in [0, 1], 1.0 on background) at the pixel P falls in. Background there means nothing is in front
   of P. Otherwise both depths are linearised to view depth (clip w) and P is visible when
   ``w_P <= w_ref + tol`` with

   ``tol = 1e-4 * w_ref + 8 * 2**-24 * w_ref**2 * (far - near) / (far * near) + |g_x| + |g_y|``

   * ``1e-4 * w_ref``: the float32 rounding of camera-relative positions and of the rasterizer's depth plane
     (relative error a few 1e-7; 1e-4 leaves a wide margin and is still 10 cm at 1 km);
   * the second term: 8 float32 ulps of window depth (2^-24 near 1) turned into view depth with
     d(w)/d(depth) = w^2 (far - near) / (far near): what a depth buffer can resolve at that distance;
   * ``|g_x| + |g_y|``: the change of view depth across one pixel at that pixel, each the smaller of its two
     one-sided differences (so an occluding edge on one side does not widen it; background neighbours are
     skipped). P lies within half a pixel of the pixel centre each way, so a locally planar surface changes
     by at most half of this between P and the centre: a factor two of margin.

   A sample behind a hill is farther than the hill by far more than this; the tolerance only decides
   samples on the visible surface itself.
3. Excluded and counted: ``no_data`` (NaN heights), ``outside`` (viewport, near, far), ``hidden`` (depth
   test), ``beside_hole`` and ``missing``: visible samples with no drawn surface above or below them (culled
   patches, holes a setting made larger). Where P' lies behind the eye the error is +inf.

**Beside a no-data hole.** A finite sample within one cell of a NaN sample (a corner of a cell that touches
the hole: :func:`beside_hole`) is measured by no family: whether a mesh draws it depends on its diagonals
(no triangle may touch the hole, so a cell with one NaN corner keeps one triangle or none) and on its
vertices' filter (a bilinear fetch at or beside the sample reads the hole, so a tessellated vertex there is a
hole too). Every family's full-detail mesh draws every sample farther from the hole (a fully finite cell
around it), so counting only those as missing holds every family to the same terrain; the ones beside the
hole are counted apart (``beside_hole``) and are neither measured nor missing.

**Popping.** For cameras t -> t+1, the LOD selected at t (held) and the LOD selected at t+1, both drawn for
camera t+1: per visible sample (visibility as above, from camera t+1's full-detail depth buffer), the pixel
distance between the two surfaces' points above it. :func:`popping` reports p99, max and mean, the samples
that move by more than ``threshold_px`` (0.5 px) and the image pixels those samples fall in.

Measurement, not pipeline: the per-sample work runs in float64. Deterministic: identical on every run.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..camera import Camera, relative_origin
from ..heightmap import Heightmap
from ..kernels import sample_error as _k
from ..kernels.pool import pooled
from ..mesh import Mesh

__all__ = ["SampleError", "PopStats", "surface_heights", "sample_error", "popping", "STATES", "percentile",
           "beside_hole"]

BESIDE_HOLE = 5  # a sample next to a no-data hole: measured by no family (set on the host after the kernel)
STATES = {"visible": _k.VISIBLE, "no_data": _k.NO_DATA, "outside": _k.OUTSIDE, "hidden": _k.HIDDEN,
          "missing": _k.MISSING, "beside_hole": BESIDE_HOLE}


@dataclass(frozen=True)
class SampleError:
    """The primary error of one frame (pixels), over its visible samples.

    Attributes:
        p99_px, max_px, mean_px: 99th percentile (numpy's linear interpolation), maximum and mean of the
            per-sample error over the ``visible`` samples (0.0 when there are none; +inf where a surface
            point lies behind the eye).
        visible: samples measured (in view, passing the depth test, with a drawn surface).
        outside: samples outside the viewport or the near/far planes.
        hidden: samples in view that fail the depth test against the full-detail frame.
        missing: samples that would be visible but have no drawn surface above or below them.
        no_data: samples whose height is NaN.
        beside_hole: samples in view within one cell of a no-data sample (:func:`beside_hole`): measured by no
            family, neither visible nor missing.
        error_map: (rows, cols) float32 per-sample error, NaN where not measured; only with ``keep_map``.
    """

    p99_px: float
    max_px: float
    mean_px: float
    visible: int
    outside: int
    hidden: int
    missing: int
    no_data: int
    beside_hole: int = 0
    error_map: np.ndarray | None = field(default=None, repr=False, compare=False)

    def row(self) -> dict[str, float | int]:
        """The numbers (no map), for tables."""
        return {k: getattr(self, k) for k in ("p99_px", "max_px", "mean_px", "visible", "outside", "hidden",
                                              "missing", "no_data", "beside_hole")}


@dataclass(frozen=True)
class PopStats:
    """The pop between two drawn surfaces seen from one camera (pixels), over the visible samples.

    Attributes:
        p99_px, max_px, mean_px: of the per-sample displacement between the two surfaces.
        popped: visible samples that move by more than ``threshold_px``.
        popped_pixels: distinct image pixels those samples fall in (the pixel of the sample itself).
        threshold_px: the threshold used.
        visible, outside, hidden, missing, no_data, beside_hole: as :class:`SampleError` (``missing``: either
            surface).
        pop_map: (rows, cols) float32 per-sample displacement, NaN where not measured; only with ``keep_map``.
    """

    p99_px: float
    max_px: float
    mean_px: float
    popped: int
    popped_pixels: int
    threshold_px: float
    visible: int
    outside: int
    hidden: int
    missing: int
    no_data: int
    beside_hole: int = 0
    pop_map: np.ndarray | None = field(default=None, repr=False, compare=False)

    def row(self) -> dict[str, float | int]:
        """The numbers (no map), for tables."""
        return {k: getattr(self, k) for k in ("p99_px", "max_px", "mean_px", "popped", "popped_pixels",
                                              "threshold_px", "visible", "outside", "hidden", "missing",
                                              "no_data", "beside_hole")}


# ------------------------------------------------------------------------------------------------
# validation
# ------------------------------------------------------------------------------------------------
def _check(heightmap: object, camera: object, meshes: dict[str, object], ref_depth: object | None) -> np.ndarray | None:
    if not isinstance(heightmap, Heightmap):
        raise TypeError(f"heightmap: expected a Heightmap, got {type(heightmap).__name__}")
    if camera is not None and not isinstance(camera, Camera):
        raise TypeError(f"camera: expected a Camera, got {type(camera).__name__}")
    for name, m in meshes.items():
        if not isinstance(m, Mesh):
            raise TypeError(f"{name}: expected a Mesh, got {type(m).__name__}")
    if ref_depth is None:
        return None
    d = np.asarray(ref_depth)
    if d.shape != (camera.height, camera.width):
        raise ValueError(f"ref_depth: expected shape ({camera.height}, {camera.width}) (the camera's viewport), "
                         f"got {d.shape}")
    if not np.issubdtype(d.dtype, np.floating):
        raise TypeError(f"ref_depth: expected a float array of window depths, got {d.dtype}")
    return np.ascontiguousarray(d, np.float32)


# ------------------------------------------------------------------------------------------------
# the drawn surface at the samples
# ------------------------------------------------------------------------------------------------
def _relative_surface(heightmap: Heightmap, mesh: Mesh, eye: tuple[float, float, float],
                      device: str) -> np.ndarray:
    """(rows, cols) float64 height of the drawn surface above each sample, relative to ``eye``'s height."""
    offset = tuple(float(a) - float(b) for a, b in zip(mesh.eye, eye, strict=True))
    return _k.surface_at_samples(mesh.positions, mesh.triangles, offset, relative_origin(heightmap.origin, eye),
                                 (heightmap.dx, heightmap.dz), heightmap.shape, device=device)


def surface_heights(heightmap: Heightmap, mesh: Mesh, *, device: str = "cpu") -> np.ndarray:
    """The drawn surface's world height at every heightmap sample (x, z).

    Args:
        heightmap: the grid whose samples are measured.
        mesh: any drawn terrain :class:`Mesh` (positions relative to ``mesh.eye``).

    Returns:
        (rows, cols) float64 world heights, NaN where no triangle lies above or below the sample (culled
        patches, holes, beyond the mesh). Where two surfaces overlap, the higher.
    """
    _check(heightmap, None, {"mesh": mesh}, None)
    return _relative_surface(heightmap, mesh, mesh.eye, device) + float(mesh.eye[1])


# ------------------------------------------------------------------------------------------------
# the measures
# ------------------------------------------------------------------------------------------------
def beside_hole(heightmap: Heightmap) -> np.ndarray | None:
    """(rows, cols) bool: the finite samples within one cell of a no-data (NaN) sample (a corner of a cell that
    touches the hole), which no family is held to draw (the module docstring); None for a heightmap without
    holes. Worked out once per heightmap (kept in ``heightmap.held``)."""
    if not heightmap.has_nodata:
        return None
    got = heightmap.held.beside_hole
    if got is None:
        nan = np.isnan(heightmap.heights)
        near = np.zeros((nan.shape[0] + 2, nan.shape[1] + 2), bool)
        for a in range(3):  # the 3 x 3 neighbourhood: every corner of the four cells around a sample
            for b in range(3):
                near[a:a + nan.shape[0], b:b + nan.shape[1]] |= nan
        got = heightmap.held.beside_hole = near[1:-1, 1:-1] & ~nan
    return got


def _measure(heightmap: Heightmap, camera: Camera, ya: np.ndarray | None, yb: np.ndarray, depth: np.ndarray,
             device: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    mvp = camera.proj_matrix() @ camera.view_matrix(relative=True)
    err, state, pix = _k.sample_displacement(heightmap.heights, ya, yb, depth,
                                             relative_origin(heightmap.origin, camera.position),
                                             (heightmap.dx, heightmap.dz), mvp, camera.near, camera.far, device=device)
    beside = beside_hole(heightmap)
    if beside is not None:  # in view and not hidden, beside a hole: measured by no family
        m = beside & ((state == _k.VISIBLE) | (state == _k.MISSING))
        state[m] = BESIDE_HOLE
        err[m] = np.nan
    return err, state, pix


def percentile(a: np.ndarray, q: float) -> float:
    """``np.percentile(a, q)`` where ``a`` may hold +inf (a point behind the eye is infinitely far on screen):
    numpy's interpolation gives NaN (inf - inf, with a RuntimeWarning) when a neighbour is infinite; the
    percentile is +inf then."""
    with np.errstate(invalid="ignore"):
        v = float(np.percentile(a, q))
    return math.inf if math.isnan(v) and np.isposinf(a).any() else v


def _summary(err: np.ndarray, state: np.ndarray) -> dict[str, float | int]:
    vis = state == _k.VISIBLE
    e = err[vis]
    counts = {k: int(np.count_nonzero(state == v)) for k, v in STATES.items()}
    if not e.size:
        return {"p99_px": 0.0, "max_px": 0.0, "mean_px": 0.0, **counts}
    return {"p99_px": percentile(e, 99), "max_px": float(e.max()), "mean_px": float(e.mean()), **counts}


def _as_map(err: np.ndarray) -> np.ndarray:
    """The per-sample map: the kernel leaves every sample but the visible ones NaN already. Float32, in a
    buffer of the frame-buffer pool (two kept: a path's previous frame may still hold its map)."""
    out = pooled(err.shape, np.float32, keep=2, max_bytes=1 << 30)
    np.copyto(out, err, casting="same_kind")
    return out


def sample_error(heightmap: Heightmap, camera: Camera, mesh: Mesh, ref_depth: np.ndarray, *,
                 keep_map: bool = False, device: str = "cpu") -> SampleError:
    """The primary screen-space error of a drawn mesh (see the module docstring).

    Args:
        heightmap: the full-resolution terrain whose samples are measured.
        camera: the frame's camera.
        mesh: the drawn LOD :class:`Mesh` (any family; positions relative to ``mesh.eye``, normally the
            camera's position).
        ref_depth: (camera.height, camera.width) float32 window depth of the full-detail (grid) frame of the
            same camera, 1.0 on background, row 0 at the top (``render(scene.with_(mesh="grid"))``'s ``depth``).
        keep_map: also return the per-sample error map.

    Returns:
        :class:`SampleError`. Deterministic. Not differentiable.
    """
    depth = _check(heightmap, camera, {"mesh": mesh}, ref_depth)
    y = _relative_surface(heightmap, mesh, camera.position, device)
    err, state, _ = _measure(heightmap, camera, None, y, depth, device)
    return SampleError(**_summary(err, state), error_map=_as_map(err) if keep_map else None)


def popping(heightmap: Heightmap, camera: Camera, held: Mesh, current: Mesh, ref_depth: np.ndarray, *,
            threshold_px: float = 0.5, keep_map: bool = False, device: str = "cpu") -> PopStats:
    """The pop between two consecutive selections, seen from the later camera.

    Args:
        heightmap: the full-resolution terrain.
        camera: camera t+1.
        held: the LOD selected at t, drawn for camera t+1; current: the LOD selected at t+1, drawn for
            camera t+1.
        ref_depth: (camera.height, camera.width) float32 full-detail window depth of camera t+1 (as for
            :func:`sample_error`).
        threshold_px: a sample pops when it moves by more than this many pixels.
        keep_map: also return the per-sample displacement map.

    Returns:
        :class:`PopStats`. 0 everywhere when both meshes are the same surface. Deterministic.
    """
    depth = _check(heightmap, camera, {"held": held, "current": current}, ref_depth)
    if not (np.isfinite(threshold_px) and threshold_px >= 0):
        raise ValueError(f"threshold_px: expected a finite number >= 0, got {threshold_px}")
    ya = _relative_surface(heightmap, held, camera.position, device)
    yb = _relative_surface(heightmap, current, camera.position, device)
    err, state, pix = _measure(heightmap, camera, ya, yb, depth, device)
    s = _summary(err, state)
    moved = (state == _k.VISIBLE) & (err > threshold_px)
    return PopStats(p99_px=s["p99_px"], max_px=s["max_px"], mean_px=s["mean_px"], popped=int(moved.sum()),
                    popped_pixels=int(np.unique(pix[moved]).size), threshold_px=float(threshold_px),
                    visible=s["visible"], outside=s["outside"], hidden=s["hidden"], missing=s["missing"],
                    no_data=s["no_data"], beside_hole=s["beside_hole"], pop_map=_as_map(err) if keep_map else None)

"""Screen-space error of a frame against the full-resolution reference, in pixels.

For each pixel the LOD frame covers, P is its world position on the LOD surface (the visible
triangle's vertices interpolated with the perspective-correct barycentrics of the visibility pass)
and R the reference surface point directly above or below it: same x and z, the height of the
full-resolution mesh (two triangles per heightmap cell, split along the (i, j+1)-(i+1, j) diagonal
as :func:`terrainwarp.kernels.displacement.grid_mesh` builds it). The error is the distance between
the projections of P and R in pixels, exact (the full projection, not an approximation). Beside it we
report the classic estimate ``|P.y - R.y| * focal_px / dist(eye, P)`` (the formula screen-space-error
LOD policies use), to show how far it is from the truth.

Coverage: pixels covered by one frame and not the other are *mismatched*; a *see-through* pixel
(``see_through_px``) is one where the LOD frame shows background although the reference is covered there
and the LOD terrain covers both neighbours across it (above and below, or left and right): background seen
through the terrain, where a crack would show it. It is a pixel heuristic, not the crack count: cracks are
open edges of the mesh, :func:`terrainwarp.check_watertight`'s ``n_cracks``. Requiring all four neighbours
would miss every see-through line longer than one pixel (along a line the neighbours along it are
see-through too). Other mismatches are *silhouette* pixels.

It runs in float64 (one Warp launch over pixels, :mod:`terrainwarp.kernels.metrics`): it measures the
float32 pipeline, it is not part of it. :func:`pixel_positions` and :func:`reference_height` are the
same maths in numpy, for tests and for users.

**This is the secondary error.** The fixed-diagonal grid is not every family's full-detail surface: the GPU
tessellator mirrors its diagonals about each patch's centre lines, and Martini, Delatin, the bintree and
the polytree triangulate their own way, so even a family's finest mesh differs from the grid per pixel.
On the bundled DEM at 1920x1080 that floor is a p99 of 0.69-0.94 px (max 2.7-2.8 px) at 10% clearance
and 2.4-5.7 px at 2% (``benchmarks/results/yardstick.md``). The primary error,
:func:`terrainwarp.measure.sample_error.sample_error`, is measured at the heightmap's samples and has no
such floor; :class:`FrameError` (``Frame.error``) carries both, this one as the ``image_err_*`` fields.
"""


from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..camera import Camera
from ..heightmap import Heightmap
from ..io.display import html_table
from ..kernels.metrics import pixel_error
from .sample_error import SampleError, percentile

__all__ = ["ErrorStats", "FrameError", "pixel_positions", "reference_height", "frame_error"]


def pixel_positions(positions: np.ndarray, triangles: np.ndarray, triangle_id: np.ndarray,
                    barycentrics: np.ndarray) -> np.ndarray:
    """(H, W, 3) float64 camera-relative positions of the visible surface (NaN on background)."""
    hh, ww = triangle_id.shape
    out = np.full((hh, ww, 3), np.nan)
    m = triangle_id >= 0
    if not m.any():
        return out
    t = triangles[triangle_id[m]]
    b = barycentrics[m].astype(np.float64)
    b2 = 1.0 - b[:, 0] - b[:, 1]
    p = positions.astype(np.float64)
    out[m] = b[:, :1] * p[t[:, 0]] + b[:, 1:2] * p[t[:, 1]] + b2[:, None] * p[t[:, 2]]
    return out


def reference_height(heightmap: Heightmap, x: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Height of the full-resolution triangulated grid at world (x, z), float64 (clamped to the grid)."""
    h = heightmap.heights.astype(np.float64)
    rows, cols = h.shape
    u = np.clip((np.asarray(x, np.float64) - heightmap.origin[0]) / heightmap.dx, 0.0, cols - 1)
    v = np.clip((np.asarray(z, np.float64) - heightmap.origin[1]) / heightmap.dz, 0.0, rows - 1)
    j = np.minimum(np.floor(u).astype(np.int64), max(cols - 2, 0))
    i = np.minimum(np.floor(v).astype(np.int64), max(rows - 2, 0))
    fx = u - j
    fz = v - i
    j1 = np.minimum(j + 1, cols - 1)
    i1 = np.minimum(i + 1, rows - 1)
    h00, h01, h10, h11 = h[i, j], h[i, j1], h[i1, j], h[i1, j1]
    lower = fx + fz <= 1.0
    a = h00 + fx * (h01 - h00) + fz * (h10 - h00)
    b = h11 + (1.0 - fx) * (h10 - h11) + (1.0 - fz) * (h01 - h11)
    return np.where(lower, a, b)


@dataclass
class ErrorStats:
    """Per-frame error summary (pixels unless named otherwise)."""

    max_px: float
    p99_px: float
    mean_px: float
    approx_max_px: float
    approx_p99_px: float
    covered: int
    mismatched: int
    silhouette: int
    see_through_px: int
    max_depth_diff: float
    psnr_db: float | None = None
    ssim: float | None = None
    error_map: np.ndarray | None = field(default=None, repr=False)
    see_through_mask: np.ndarray | None = field(default=None, repr=False)

    def row(self) -> dict[str, float | int | None]:
        return {k: v for k, v in self.__dict__.items() if k not in ("error_map", "see_through_mask")}


@dataclass
class FrameError:
    """A frame's error (``Frame.error``): the primary error at the heightmap's samples, and the per-pixel
    grid-image error beside it as secondary, named fields.

    Attributes:
        p99_px, max_px, mean_px: the primary error (:func:`terrainwarp.measure.sample_error.sample_error`):
            per visible heightmap sample, the pixel distance between the sample and the drawn surface at
            its (x, z); every family's full-detail mesh scores 0.
        samples_visible, samples_outside, samples_hidden, samples_missing, samples_no_data,
            samples_beside_hole: what the primary error counted
            (:class:`terrainwarp.measure.sample_error.SampleError`; beside a no-data hole: measured by no family).
        image_err_p99_px, image_err_max_px, image_err_mean_px: the per-pixel reprojection error against
            the fixed-diagonal full-resolution grid (:func:`frame_error`). Secondary: it carries a
            triangulation floor (p99 0.69-0.94 px at 10% clearance, 2.4-5.7 px at 2%, on the bundled DEM
            at 1080p, for the finest quadtree frame).
        approx_max_px, approx_p99_px: the classic ``|dy| * focal / distance`` estimate of the image error.
        covered, mismatched, silhouette, see_through_px, max_depth_diff: coverage against the grid frame
            (pixels; window depth); ``see_through_px``: background pixels seen through the terrain (the
            module docstring; not the crack count, which is ``check_watertight``'s).
        psnr_db, ssim: of the hillshaded image against the grid's (None when not shaded).
        error_map: (rows, cols) float32 per-sample primary error, NaN where not measured.
        image_error_map: (H, W) float32 per-pixel image error, NaN on background.
        see_through_mask: (H, W) bool see-through pixels.
    """

    p99_px: float
    max_px: float
    mean_px: float
    samples_visible: int
    samples_outside: int
    samples_hidden: int
    samples_missing: int
    samples_no_data: int
    image_err_p99_px: float
    image_err_max_px: float
    image_err_mean_px: float
    approx_max_px: float
    approx_p99_px: float
    covered: int
    mismatched: int
    silhouette: int
    see_through_px: int
    max_depth_diff: float
    psnr_db: float | None = None
    ssim: float | None = None
    samples_beside_hole: int = 0
    error_map: np.ndarray | None = field(default=None, repr=False)
    image_error_map: np.ndarray | None = field(default=None, repr=False)
    see_through_mask: np.ndarray | None = field(default=None, repr=False)

    @classmethod
    def combine(cls, samples: SampleError, image: ErrorStats) -> FrameError:
        """The primary error ``samples`` and the image error ``image`` of one frame, as one record."""
        return cls(p99_px=samples.p99_px, max_px=samples.max_px, mean_px=samples.mean_px,
                   samples_visible=samples.visible, samples_outside=samples.outside, samples_hidden=samples.hidden,
                   samples_missing=samples.missing, samples_no_data=samples.no_data,
                   samples_beside_hole=samples.beside_hole,
                   image_err_p99_px=image.p99_px, image_err_max_px=image.max_px, image_err_mean_px=image.mean_px,
                   approx_max_px=image.approx_max_px, approx_p99_px=image.approx_p99_px, covered=image.covered,
                   mismatched=image.mismatched, silhouette=image.silhouette, see_through_px=image.see_through_px,
                   max_depth_diff=image.max_depth_diff, psnr_db=image.psnr_db, ssim=image.ssim,
                   error_map=samples.error_map, image_error_map=image.error_map,
                   see_through_mask=image.see_through_mask)

    def _repr_html_(self) -> str:
        """The primary error, the secondary image error and the coverage as an HTML table (Jupyter)."""
        rows = [("primary (at the samples)", self.p99_px, self.max_px, self.mean_px,
                 f"{self.samples_visible} samples visible, {self.samples_hidden} hidden"),
                ("image (against the grid; floor)", self.image_err_p99_px, self.image_err_max_px,
                 self.image_err_mean_px, f"{self.see_through_px} see-through pixels, {self.covered} covered"
                 + ("" if self.psnr_db is None else f", PSNR {self.psnr_db:.1f} dB, SSIM {self.ssim:.3f}"))]
        return html_table(("error", "p99_px", "max_px", "mean_px", "counted"), rows)

    def row(self) -> dict[str, float | int | None]:
        """The numbers (no maps), for tables and report.json."""
        return {k: v for k, v in self.__dict__.items() if k not in ("error_map", "image_error_map", "see_through_mask")}


def frame_error(heightmap: Heightmap, camera: Camera, positions: np.ndarray, eye: tuple[float, float, float],
                triangles: np.ndarray, triangle_id: np.ndarray, barycentrics: np.ndarray,
                depth: np.ndarray | None = None, ref_triangle_id: np.ndarray | None = None,
                ref_depth: np.ndarray | None = None, image: np.ndarray | None = None,
                ref_image: np.ndarray | None = None, keep_maps: bool = False, device: str = "cpu") -> ErrorStats:
    """Measure one LOD frame (the per-pixel error pass runs on ``device``).

    Args:
        heightmap: the full-resolution terrain (the reference surface).
        camera: the frame's camera.
        positions: (n, 3) float32 camera-relative vertex positions of the drawn mesh, relative to ``eye``.
        triangles: (m, 3) int32; triangle_id: (H, W) int32; barycentrics: (H, W, 2) float32 (the
            visibility pass of the LOD frame).
        depth, ref_triangle_id, ref_depth: the LOD frame's depth and the reference frame's coverage and
            depth (for the coverage and depth comparisons; optional).
        image, ref_image: hillshaded images for PSNR and SSIM (optional).
    """
    hh, ww = triangle_id.shape
    cov = triangle_id >= 0
    m = camera.proj_matrix() @ camera.view_matrix(relative=True)
    emap, amap = pixel_error(triangle_id, barycentrics, positions, triangles, heightmap.heights, eye,
                             heightmap.origin, (heightmap.dx, heightmap.dz), m, camera.focal_px, device=device)
    err = emap[cov]
    err = np.where(err >= 1e300, np.inf, err)
    approx = amap[cov]
    approx = np.where(approx >= 1e300, np.inf, approx)
    n = int(cov.sum())

    def q(a: np.ndarray, f) -> float:
        return float(f(a)) if len(a) else 0.0

    stats = ErrorStats(
        max_px=q(err, np.max), p99_px=q(err, lambda a: percentile(a, 99)), mean_px=q(err, np.mean),
        approx_max_px=q(approx, np.max), approx_p99_px=q(approx, lambda a: percentile(a, 99)),
        covered=n, mismatched=0, silhouette=0, see_through_px=0, max_depth_diff=0.0)
    if ref_triangle_id is not None:
        rc = ref_triangle_id >= 0
        mism = rc ^ cov
        pad = np.pad(cov, 1, constant_values=False)
        enclosed = (pad[:-2, 1:-1] & pad[2:, 1:-1]) | (pad[1:-1, :-2] & pad[1:-1, 2:])
        crack = ~cov & rc & enclosed
        stats.mismatched = int(mism.sum())
        stats.see_through_px = int(crack.sum())
        stats.silhouette = stats.mismatched - stats.see_through_px
        if keep_maps:
            stats.see_through_mask = crack
        if depth is not None and ref_depth is not None:
            both = rc & cov
            stats.max_depth_diff = float(np.abs(depth[both].astype(np.float64) - ref_depth[both]).max()) \
                if both.any() else 0.0
    if image is not None and ref_image is not None:
        from skimage.metrics import peak_signal_noise_ratio, structural_similarity  # lazy: heavy optional

        a = image.astype(np.float64) / 255.0
        b = ref_image.astype(np.float64) / 255.0
        same = np.array_equal(a, b)
        stats.psnr_db = float("inf") if same else float(peak_signal_noise_ratio(b, a, data_range=1.0))
        if min(a.shape[0], a.shape[1]) >= 7:  # SSIM's 7x7 window needs at least that many pixels
            stats.ssim = float(structural_similarity(b, a, channel_axis=-1, data_range=1.0))
    if keep_maps:
        emap = np.full((hh, ww), np.nan, np.float32)
        emap[cov] = err
        stats.error_map = emap
    return stats

"""Line and hatch shading of curtis2004 ("Utilizing curvature"): view-independent strokes drawn from the
directional curvature of :func:`terrainwarp.compute_curvature`.

* :func:`line_strokes`: every vertex whose maximum curvature (over the four directions) reaches
  ``threshold`` links to its two neighbours in the direction perpendicular to its direction of maximum
  curvature (x <-> z, diagonal (+x,+z) <-> diagonal (+x,-z); with dx != dz the diagonals are the
  nearest-to-perpendicular grid direction) when they reach the threshold too. The union of those links
  is the paper's set of traced paths (paths that meet merge, each link is drawn once); a connected path
  with fewer than ``min_length`` vertices is dropped. Each segment is black with alpha = the curvature
  of its vertices (mean of the two, clipped to [0, 1]).
* :func:`hatch_strokes`: at every vertex above ``threshold`` a stroke of ``length`` sample spacings
  on the tangent plane, centred on the vertex, along the curvature-weighted direction of the four
  directions projected onto the tangent plane (``direction="with"``) or perpendicular to it on the
  tangent plane (``"perp"``); alpha = maximum curvature clipped to [0, 1]. The paper sums the four
  unit vectors weighted by curvature; a curvature direction has no sign, so here they are averaged as
  axes (doubled angles, sum_d k_d (cos 2a_d, sin 2a_d), then half the angle): on a ridge along x the
  plain sum would tilt the hatches by 35 degrees because the two diagonals' vectors do not cancel.
  Where the weights cancel (equal curvature every way, e.g. a sphere) the direction of the maximum is
  used.

Both return :class:`Strokes` (segment arrays a rasterizer can draw) and draw themselves top-down with
matplotlib (:meth:`Strokes.picture`), so the parameter tables of curtis2004 figures 3 and 4 can be
reproduced: curvature style = ``method``, curv dist = ``distance``, curv scale = ``scale``, has
contours = ``contours``, min len = ``min_length``, hatch len = ``length``, line width = ``line_width``,
hatch dir = ``direction``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..heightmap import Heightmap
from ..io.files import save_figure
from ..kernels.checks import check_int

if TYPE_CHECKING:
    from matplotlib.figure import Figure
from .differential import compute_curvature, compute_normals, max_curvature

__all__ = ["Strokes", "line_strokes", "hatch_strokes"]

_OFFSETS = np.array([(0, 1), (1, 0), (1, 1), (-1, 1)], dtype=np.int64)  # (di, dj) per direction
_PERP = np.array([1, 0, 3, 2], dtype=np.int64)


@dataclass(frozen=True, eq=False)
class Strokes:
    """Strokes to draw over a heightmap.

    Attributes:
        segments: (n, 2, 3) float32 endpoints (x, y, z) in metres relative to the heightmap origin
            (x = j*dx, y = height, z = i*dz); add ``origin`` (x, z) for world coordinates.
        alpha: (n,) float32 opacity in [0, 1] (black strokes).
        path_id: (n,) int32: the traced path of each segment (line shading) or its vertex index
            i*W + j (hatch shading).
        kind: ``"line"`` or ``"hatch"``.
        shape: (H, W) of the heightmap; dx, dz: its spacing; origin: its world (x, z) origin.
        params: the parameters that made the strokes.
    """

    segments: np.ndarray
    alpha: np.ndarray
    path_id: np.ndarray
    kind: str
    shape: tuple[int, int]
    dx: float
    dz: float
    origin: tuple[float, float]
    params: dict

    def __len__(self) -> int:
        return int(self.segments.shape[0])

    @property
    def n_paths(self) -> int:
        return int(np.unique(self.path_id).size)

    def picture(self, path: str | Path | None = None, *, heightmap: Heightmap | None = None,
                contours: bool = False, line_width: float = 1.0, size_px: int = 800,
                title: str | None = None) -> Figure:
        """Draw the strokes top-down (x to the right, z down: row 0 at the top) on white.

        Args:
            path: image file to write (PNG, PDF, SVG: any matplotlib format), written atomically.
            heightmap: the terrain, needed for ``contours``.
            contours: add 12 grey contour lines of the heightmap (the papers' "has contours").
            line_width: stroke width in points.
            size_px: width of the picture in pixels at 100 dpi.

        Returns:
            the matplotlib ``Figure``.
        """
        # lazy: heavy optional dependency
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.collections import LineCollection
        from matplotlib.figure import Figure

        hh, ww = self.shape
        ext_x = max((ww - 1) * self.dx, self.dx)
        ext_z = max((hh - 1) * self.dz, self.dz)
        wi = size_px / 100.0
        fig = Figure(figsize=(wi, max(wi * ext_z / ext_x, 1.0)), dpi=100)
        FigureCanvasAgg(fig)
        ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
        if contours:
            if heightmap is None:
                raise ValueError("heightmap: needed to draw contours")
            hgt = np.asarray(heightmap.heights, dtype=np.float64)
            if hgt.shape[0] >= 2 and hgt.shape[1] >= 2 and np.nanmax(hgt) > np.nanmin(hgt):
                xs = np.arange(ww) * self.dx
                zs = np.arange(hh) * self.dz
                ax.contour(xs, zs, hgt, levels=12, colors="0.55", linewidths=0.5 * line_width)
        if len(self):
            xz = self.segments[:, :, [0, 2]].astype(np.float64)
            rgba = np.zeros((len(self), 4))
            rgba[:, 3] = np.clip(self.alpha, 0.0, 1.0)
            ax.add_collection(LineCollection(xz, colors=rgba, linewidths=line_width, capstyle="round"))
        pad_x = 0.01 * ext_x
        pad_z = 0.01 * ext_z
        ax.set_xlim(-pad_x, ext_x + pad_x)
        ax.set_ylim(ext_z + pad_z, -pad_z)
        ax.set_axis_off()
        if title:
            ax.text(0.01, 0.99, title, transform=ax.transAxes, va="top", ha="left", fontsize=9,
                    bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "none"})
        if path is not None:
            save_figure(fig, path, dpi=100, facecolor="white")
        return fig


def _check_heightmap(heightmap: object) -> Heightmap:
    if not isinstance(heightmap, Heightmap):
        raise TypeError(f"heightmap: expected a Heightmap, got {type(heightmap).__name__}")
    return heightmap


def _curvature_for(hm: Heightmap, curvature: np.ndarray | None, method: str, scale: float,
                   distance: int) -> np.ndarray:
    if curvature is None:
        return compute_curvature(hm, method, scale=scale, distance=distance)
    k = np.asarray(curvature, dtype=np.float32)
    if k.shape != (*hm.shape, 4):
        raise ValueError(f"curvature: expected shape {(*hm.shape, 4)}, got {k.shape}")
    return k


def _positions(hm: Heightmap, flat_idx: np.ndarray) -> np.ndarray:
    ww = hm.shape[1]
    i = flat_idx // ww
    j = flat_idx % ww
    return np.stack([j * hm.dx, hm.heights.reshape(-1)[flat_idx], i * hm.dz], axis=-1).astype(np.float32)


def line_strokes(heightmap: Heightmap, *, method: str = "three_normal", scale: float = 1.0, distance: int = 1,
                 threshold: float = 0.5, min_length: int = 5, curvature: np.ndarray | None = None) -> Strokes:
    """Line shading: paths through high-curvature vertices, perpendicular to the maximum curvature.

    Args:
        heightmap: the terrain.
        method, scale, distance: passed to :func:`terrainwarp.compute_curvature` (ignored when
            ``curvature`` is given).
        threshold: a vertex takes part when its maximum (scaled) curvature is >= threshold.
        min_length: paths with fewer vertices are dropped (>= 2).
        curvature: (H, W, 4) float32 precomputed directional curvature (already scaled).

    Returns:
        :class:`Strokes` of kind ``"line"``; ``path_id`` numbers the kept paths 0..n_paths-1.
    """
    from scipy.sparse import coo_matrix  # lazy: heavy optional dependency
    from scipy.sparse.csgraph import connected_components

    hm = _check_heightmap(heightmap)
    check_int("min_length", min_length, 2)
    thr = float(threshold)
    if not np.isfinite(thr):
        raise ValueError(f"threshold: expected a finite number, got {threshold!r}")
    k = _curvature_for(hm, curvature, method, scale, distance)
    kmax, kdir = max_curvature(k)
    hh, ww = hm.shape
    strong = np.isfinite(kmax) & (kmax >= thr)
    vi, vj = np.nonzero(strong)
    src_list, dst_list = [], []
    for side in (1, -1):
        off = _OFFSETS[_PERP[kdir[vi, vj]]] * side
        ni, nj = vi + off[:, 0], vj + off[:, 1]
        ok = (ni >= 0) & (ni < hh) & (nj >= 0) & (nj < ww)
        ok[ok] &= strong[ni[ok], nj[ok]]
        src_list.append(vi[ok] * ww + vj[ok])
        dst_list.append(ni[ok] * ww + nj[ok])
    a = np.concatenate(src_list)
    b = np.concatenate(dst_list)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    key = np.unique(lo * (hh * ww) + hi)
    lo, hi = key // (hh * ww), key % (hh * ww)
    n = hh * ww
    g = coo_matrix((np.ones(lo.size, np.int8), (lo, hi)), shape=(n, n))
    _, label = connected_components(g, directed=False)
    sizes = np.bincount(label[strong.reshape(-1)], minlength=label.max() + 1) if lo.size else np.zeros(1, int)
    keep = sizes[label[lo]] >= min_length if lo.size else np.zeros(0, bool)
    lo, hi = lo[keep], hi[keep]
    _, path_id = np.unique(label[lo], return_inverse=True)
    seg = np.stack([_positions(hm, lo), _positions(hm, hi)], axis=1)
    kf = np.clip(np.nan_to_num(kmax.reshape(-1)), 0.0, 1.0)
    alpha = (0.5 * (kf[lo] + kf[hi])).astype(np.float32)
    return Strokes(segments=seg.reshape(-1, 2, 3), alpha=alpha, path_id=path_id.astype(np.int32).reshape(-1),
                   kind="line", shape=(hh, ww), dx=hm.dx, dz=hm.dz, origin=hm.origin,
                   params={"method": method if curvature is None else "given", "scale": scale,
                           "distance": distance, "threshold": thr, "min_length": int(min_length)})


def hatch_strokes(heightmap: Heightmap, *, method: str = "three_normal", scale: float = 1.0, distance: int = 1,
                  length: float = 0.75, direction: str = "perp", threshold: float = 0.0,
                  normals: str = "quad", curvature: np.ndarray | None = None) -> Strokes:
    """Hatch shading: one stroke per vertex on its tangent plane.

    Args:
        heightmap: the terrain.
        method, scale, distance: passed to :func:`terrainwarp.compute_curvature`.
        length: stroke length in sample spacings (metres = length * (dx + dz) / 2), > 0.
        direction: ``"with"`` the weighted maximum-curvature direction or ``"perp"`` to it.
        threshold: vertices with maximum curvature <= threshold draw no stroke.
        normals: vertex-normal method for the tangent plane.
        curvature: (H, W, 4) float32 precomputed directional curvature (already scaled).

    Returns:
        :class:`Strokes` of kind ``"hatch"``; ``path_id`` is each stroke's vertex i*W + j.
    """
    hm = _check_heightmap(heightmap)
    if direction not in ("with", "perp"):
        raise ValueError(f"direction: expected 'with' or 'perp', got {direction!r}")
    ln = float(length)
    if not (np.isfinite(ln) and ln > 0.0):
        raise ValueError(f"length: expected a positive number of sample spacings, got {length!r}")
    k = _curvature_for(hm, curvature, method, scale, distance)
    kmax, kdir = max_curvature(k)
    hh, ww = hm.shape
    nrm = compute_normals(hm, normals, border="skip").reshape(-1, 3).astype(np.float64)
    # orientation average with doubled angles: a curvature direction has no sign, so x, z and the two
    # diagonals are averaged as axes (the paper's plain sum of the four signed unit vectors would tilt
    # a ridge's hatches by the two diagonals' unequal signs)
    theta = np.arctan2(_OFFSETS[:, 0] * hm.dz, _OFFSETS[:, 1] * hm.dx)
    kk = np.nan_to_num(k.reshape(-1, 4).astype(np.float64))
    c2 = kk @ np.cos(2 * theta)
    s2 = kk @ np.sin(2 * theta)
    ksum = kk.sum(axis=1)
    kmax_flat, kdir_flat = kmax.reshape(-1), kdir.reshape(-1)
    iso = np.hypot(c2, s2) <= 1e-6 * ksum  # no preferred axis (e.g. a sphere): the maximum's direction
    ang = np.where(iso, theta[np.clip(kdir_flat, 0, 3)], 0.5 * np.arctan2(s2, c2))
    w = np.stack([np.cos(ang), np.zeros_like(ang), np.sin(ang)], axis=1)
    t = w - np.sum(w * nrm, axis=1, keepdims=True) * nrm
    tn = np.linalg.norm(t, axis=1)
    sel = np.isfinite(kmax_flat) & (kmax_flat > float(threshold)) & (tn > 1e-12)
    idx = np.nonzero(sel)[0]
    t = t[idx] / tn[idx, None]
    if direction == "perp":
        t = np.cross(nrm[idx], t)
    half = 0.5 * ln * 0.5 * (hm.dx + hm.dz)
    p = _positions(hm, idx).astype(np.float64)
    seg = np.stack([p - half * t, p + half * t], axis=1).astype(np.float32)
    alpha = np.clip(kmax.reshape(-1)[idx], 0.0, 1.0).astype(np.float32)
    return Strokes(segments=seg.reshape(-1, 2, 3), alpha=alpha, path_id=idx.astype(np.int32), kind="hatch",
                   shape=(hh, ww), dx=hm.dx, dz=hm.dz, origin=hm.origin,
                   params={"method": method if curvature is None else "given", "scale": scale,
                           "distance": distance, "length": ln, "direction": direction,
                           "threshold": float(threshold)})

"""Peers on the same work: Martini (RTIN, mapbox/martini via pymartini) and Delatin (hmm's greedy Delaunay
insertion via pydelatin) meshing the same heightmap, as :class:`~terrainwarp.mesh.Mesh` objects our
rasterizer draws, with their meshing time kept apart from render time.

* Martini needs a (2^k + 1)^2 grid: the heightmap is padded by edge replication to the next such size
  and vertices beyond the real grid are clamped to its border (triangles that collapse are dropped);
  its ``max_error`` is a refinement threshold, not a bound (it tests only the middle of each
  triangle's long edge), so :func:`mesh_vertical_error` measures the real maximum error.
* Delatin's ``max_error`` is a bound on the vertical error at the samples, which the tests check.

Both work in grid units horizontally and heights vertically, so their errors are vertical metres.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from ..heightmap import Heightmap
from ..mesh import Mesh

__all__ = ["PeerMesh", "martini_mesh", "delatin_mesh", "mesh_vertical_error"]


@dataclass
class PeerMesh:
    """A peer's mesh in grid coordinates: vertices (n, 2) float64 (column, row), heights (n,) float64,
    triangles (m, 3) int32 counter-clockwise seen from +y, and its meshing time."""

    name: str
    setting: float
    grid_xy: np.ndarray
    heights: np.ndarray
    triangles: np.ndarray
    mesh_ms: float
    note: str = ""

    @property
    def n_triangles(self) -> int:
        return int(len(self.triangles))

    def to_mesh(self, heightmap: Heightmap, camera: Camera) -> Mesh:
        """Camera-relative float32 positions for the rasterizer (float64 subtraction of the eye first)."""
        e = camera.position
        x = heightmap.origin[0] + self.grid_xy[:, 0] * heightmap.dx - e[0]
        z = heightmap.origin[1] + self.grid_xy[:, 1] * heightmap.dz - e[2]
        pos = np.stack([x, self.heights - e[1], z], 1).astype(np.float32)
        n = len(pos)
        return Mesh(positions=pos, eye=e, triangles=self.triangles, uv=np.zeros((n, 2), np.float32),
                    level=np.zeros(n, np.int32), patch_id=np.zeros(n, np.int32))


def _ccw(grid_xy: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Orient triangles counter-clockwise seen from +y (x = column, z = row) and drop degenerate ones."""
    a, b, c = grid_xy[tri[:, 0]], grid_xy[tri[:, 1]], grid_xy[tri[:, 2]]
    # normal.y of (b - a) x (c - a) with (x, z) = (col, row): (bz - az)(cx - ax) - (bx - ax)(cz - az)
    ny = (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]) - (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1])
    t = tri.copy()
    flip = ny < 0
    t[flip] = t[flip][:, [0, 2, 1]]
    return np.ascontiguousarray(t[ny != 0], dtype=np.int32)


def martini_mesh(heightmap: Heightmap, max_error: float) -> PeerMesh:
    """Martini's RTIN mesh at ``max_error`` metres (a refinement threshold, see the module docstring)."""
    from pymartini import Martini  # lazy: heavy optional dependency

    h = heightmap.heights
    rows, cols = h.shape
    k = max(1, int(np.ceil(np.log2(max(rows, cols) - 1))) if max(rows, cols) > 1 else 1)
    size = 2 ** k + 1
    pad = np.pad(h, ((0, size - rows), (0, size - cols)), mode="edge").astype(np.float32)
    t0 = time.perf_counter()
    tile = Martini(size).create_tile(pad.reshape(-1))
    v, tri = tile.get_mesh(float(max_error))
    ms = (time.perf_counter() - t0) * 1e3
    v = np.asarray(v, np.float64).reshape(-1, 2)
    tri = np.asarray(tri, np.int64).reshape(-1, 3)
    xy = np.stack([np.minimum(v[:, 0], cols - 1), np.minimum(v[:, 1], rows - 1)], 1)
    hts = h[xy[:, 1].astype(np.int64), xy[:, 0].astype(np.int64)].astype(np.float64)
    note = f"padded {rows}x{cols} to {size}x{size} by edge replication" if (rows, cols) != (size, size) else ""
    return PeerMesh("martini", float(max_error), xy, hts, _ccw(xy, tri), ms, note)


def delatin_mesh(heightmap: Heightmap, max_error: float) -> PeerMesh:
    """Delatin's greedy Delaunay mesh with vertical error at most ``max_error`` metres."""
    from pydelatin import Delatin  # lazy: heavy optional dependency

    h = heightmap.heights
    rows = h.shape[0]
    t0 = time.perf_counter()
    tin = Delatin(h, max_error=float(max_error))
    v = np.asarray(tin.vertices, np.float64)
    tri = np.asarray(tin.triangles, np.int64)
    ms = (time.perf_counter() - t0) * 1e3
    xy = np.stack([v[:, 0], (rows - 1) - v[:, 1]], 1)  # Delatin's y runs up the rows
    return PeerMesh("delatin", float(max_error), xy, v[:, 2].astype(np.float64), _ccw(xy, tri), ms)


def mesh_vertical_error(heightmap: Heightmap, peer: PeerMesh, *, chunk: int = 1 << 20) -> float:
    """The real maximum vertical distance (metres) between a peer mesh and every heightmap sample, float64.

    Each triangle's (linearly interpolated) height is evaluated at the grid samples of its bounding box that lie
    inside it or on its edges (barycentric coordinates >= -1e-9); the largest distance to the sample's height
    wins. Samples no triangle covers do not count. ``chunk``: samples evaluated at once (memory, not result).
    """
    h = heightmap.heights.astype(np.float64)
    rows, cols = h.shape
    xy = np.asarray(peer.grid_xy, np.float64)
    z = np.asarray(peer.heights, np.float64)
    tri = np.asarray(peer.triangles, np.int64).reshape(-1, 3)
    lo = np.clip(np.ceil(xy[tri].min(axis=1) - 1e-9), 0, [cols - 1, rows - 1]).astype(np.int64)  # (m, 2) j, i
    hi = np.clip(np.floor(xy[tri].max(axis=1) + 1e-9), 0, [cols - 1, rows - 1]).astype(np.int64)
    w, n = hi[:, 0] - lo[:, 0] + 1, hi[:, 1] - lo[:, 1] + 1
    count = np.where((w > 0) & (n > 0), w * n, 0)
    worst, ends = -math.inf, np.cumsum(count)
    start = 0
    while start < len(tri):  # triangles in groups of about `chunk` box samples
        stop = max(int(np.searchsorted(ends, (ends[start - 1] if start else 0) + chunk, "right")), start + 1)
        worst = max(worst, _box_max(h, xy, z, tri[start:stop], lo[start:stop], w[start:stop], count[start:stop]))
        start = stop
    return float(worst) if math.isfinite(worst) else math.nan


def _box_max(h: np.ndarray, xy: np.ndarray, z: np.ndarray, tri: np.ndarray, lo: np.ndarray, w: np.ndarray,
             count: np.ndarray) -> float:
    """The largest |interpolated - sample| over the box samples inside the triangles ``tri``."""
    t = np.repeat(np.arange(len(tri)), count)  # each box sample's triangle
    k = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)  # its place in the box
    j, i = lo[t, 0] + k % w[t], lo[t, 1] + k // w[t]
    a, b, c = (xy[tri[t, q]] for q in range(3))
    det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    ok = det != 0
    with np.errstate(divide="ignore", invalid="ignore"):
        u = ((j - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (i - a[:, 1])) / det
        v = ((b[:, 0] - a[:, 0]) * (i - a[:, 1]) - (j - a[:, 0]) * (b[:, 1] - a[:, 1])) / det
    inside = ok & (u >= -1e-9) & (v >= -1e-9) & (u + v <= 1 + 1e-9)
    if not inside.any():
        return -math.inf
    zs = (1 - u - v) * z[tri[t, 0]] + u * z[tri[t, 1]] + v * z[tri[t, 2]]
    d = np.abs(zs[inside] - h[i[inside], j[inside]])
    return float(np.nanmax(d)) if np.isfinite(d).any() else -math.inf

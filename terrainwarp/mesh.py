"""Triangle meshes as the pipeline passes them between stages."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import pyvista as pv

__all__ = ["Mesh", "Draws"]


@dataclass(frozen=True, eq=False)
class Draws:
    """How a GPU draws an indexed mesh: the draw calls its family issues and what each vertex reads
    (:func:`terrainwarp.kernels.counters.indexed_draw_counters` counts them).

    Attributes:
        ranges: (D, 2) int32 triangle ranges [first, stop) of ``order``, one draw call each, in submission
            order; None: one draw of every triangle.
        order: (m,) int32 the triangles in the order the draws take them (None: as the mesh lists them).
        groups: (G, 2) int32 ranges of draws that may share vertices (draws of different groups never do);
            None: no two draws share a vertex.
        vertex_invocations: the vertex shader invocations of the family's own vertex layout when it differs from
            the mesh's (None: the distinct vertices of each draw).
        vertex_bytes: vertex attribute bytes fetched per invocation; texels_per_vertex: 4-byte heightmap texels
            the vertex shader fetches (displacement in the vertex stage).
    """

    ranges: np.ndarray | None = None
    order: np.ndarray | None = None
    groups: np.ndarray | None = None
    vertex_invocations: int | None = None
    vertex_bytes: int = 12
    texels_per_vertex: int = 0


@dataclass(frozen=True, eq=False)
class Mesh:
    """A displaced terrain mesh.

    Attributes:
        positions: (n, 3) float32, camera-relative (world minus ``eye``).
        eye: the float64 world point the positions are relative to.
        triangles: (m, 3) int32, counter-clockwise seen from above (+y).
        uv: (n, 2) float32 heightmap coordinates in [0, 1] (u along x, v along z), or None when
            nothing asked for them (a tessellated depth-only frame).
        level: (n,) int32 LOD level of the patch each vertex came from (0 for the full grid), or None
            likewise.
        patch_id: (n,) int32 index of the patch each vertex came from (0 for the full grid), or None
            likewise.
        normals: (n, 3) float32 unit vertex normals, or None when nothing asked for them.
        draws: how a GPU draws it as indexed triangles (:class:`Draws`; None: one draw, 12-byte positions).
        counters: the draw's pipeline statistics when the stage that made the mesh knows them (tessellated
            patches: :attr:`terrainwarp.kernels.tessellator.Tessellation.counters`); None: an indexed draw,
            counted from ``draws`` when a frame asks for counters.
    """

    positions: np.ndarray
    eye: tuple[float, float, float]
    triangles: np.ndarray
    uv: np.ndarray | None
    level: np.ndarray | None
    patch_id: np.ndarray | None
    normals: np.ndarray | None = None
    draws: Draws | None = None
    counters: dict[str, int] | None = None

    def __post_init__(self) -> None:
        # the per-vertex arrays must describe the same vertices: a mismatch is a pipeline bug, caught here
        n = getattr(self.positions, "shape", None)
        n = np.shape(self.positions) if n is None else n
        if len(n) != 2 or n[1] != 3:
            raise ValueError(f"positions: expected shape (n, 3), got {n}")
        if self.normals is not None and np.shape(self.normals) != n:
            raise ValueError(f"normals: expected shape {n}, got {np.shape(self.normals)}")

    @property
    def n_vertices(self) -> int:
        return int(self.positions.shape[0])

    @property
    def n_triangles(self) -> int:
        return int(self.triangles.shape[0])

    def world_positions(self) -> np.ndarray:
        """(n, 3) float64 world positions (positions + eye)."""
        return self.positions.astype(np.float64) + np.asarray(self.eye)

    def to_pyvista(self) -> pv.PolyData:
        """A ``pyvista.PolyData`` in world coordinates with level, patch_id and normals (those made) as point data."""
        import pyvista as pv  # lazy: heavy optional dependency

        faces = np.hstack([np.full((self.n_triangles, 1), 3, np.int64), self.triangles.astype(np.int64)])
        pd = pv.PolyData(self.world_positions(), faces.reshape(-1))
        for name in ("level", "patch_id"):
            if getattr(self, name) is not None:
                pd.point_data[name] = getattr(self, name)
        if self.normals is not None:
            pd.point_data["Normals"] = self.normals
        return pd

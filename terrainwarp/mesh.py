"""Triangle meshes as the pipeline passes them between stages."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import pyvista as pv

__all__ = ["Mesh"]


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
    """

    positions: np.ndarray
    eye: tuple[float, float, float]
    triangles: np.ndarray
    uv: np.ndarray | None
    level: np.ndarray | None
    patch_id: np.ndarray | None
    normals: np.ndarray | None = None

    def __post_init__(self) -> None:
        # the per-vertex arrays must describe the same vertices: a mismatch is a pipeline bug, caught here
        n = np.shape(self.positions)
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

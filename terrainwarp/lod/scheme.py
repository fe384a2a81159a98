"""What the schemes engines ship (CDLOD, geometry clipmaps, Chunked LOD) have in common: a frame is a timed
selection for the camera, then the mesh of that selection; the quadtree schemes start their descent from the
same root nodes with the same camera-relative origin and frustum."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from ..camera import Camera, relative_origin
from ..heightmap import Heightmap
from ..mesh import Mesh
from .quadtree import Terrain

__all__ = ["SelectThenMesh", "view_of", "root_nodes"]


class SelectThenMesh:
    """Mixin for a scheme with ``select(camera) -> selection`` and ``mesh(camera, selection) -> Mesh``."""

    def select(self, camera: Camera) -> Any:  # pragma: no cover - every scheme defines it
        raise NotImplementedError

    def mesh(self, camera: Camera, selection: Any) -> Mesh:  # pragma: no cover - every scheme defines it
        raise NotImplementedError

    def frame(self, camera: Camera) -> tuple[Mesh, float, Any]:
        """Select and mesh; returns (mesh, selection ms, selection). Only the selection is timed here: the
        mesh is the vertex stage, which ``render`` times as its own stage."""
        t0 = time.perf_counter()
        sel = self.select(camera)
        select_ms = (time.perf_counter() - t0) * 1e3
        return self.mesh(camera, sel), select_ms, sel


def view_of(heightmap: Heightmap, camera: Camera) -> tuple[tuple[float, float, float], np.ndarray]:
    """The camera-relative origin of the heightmap and the camera's frustum planes (camera-relative)."""
    rel = relative_origin(heightmap.origin, camera.position)
    return rel, camera.frustum_planes()


def root_nodes(terrain: Terrain) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) int64 of the terrain's root nodes, row by row: where a quadtree descent starts."""
    nx, nz = terrain.roots
    yy, xx = np.meshgrid(np.arange(nz, dtype=np.int64), np.arange(nx, dtype=np.int64), indexing="ij")
    return xx.reshape(-1), yy.reshape(-1)

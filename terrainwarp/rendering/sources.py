"""Prebuilt meshes as :class:`terrainwarp.rendering.pipeline.MeshSource` s, so ``render`` draws them too.

* :class:`PeerSource`: a Martini/Delatin mesh (:mod:`terrainwarp.lod.peers`) made camera-relative; no
  selection (0 ms).
* :class:`PolytreeSource`: level ``level`` of a taylor-barrett polytree; no selection (0 ms).
* :class:`BintreeSource`: the mrbsp apparent-size selection of a bintree; the whole call is selection.

Each holds what it was built from, the time that took (``build_ms``, kept apart from frame cost), and a
cache (the heightmap's normal map) that sources of the same heightmap may share::

    cache = {}
    src = PeerSource(delatin_mesh(hm, 2.0), hm, cache=cache)
    frame = render(scene, source=src)   # select_ms = 0, mesh_ms = to_mesh
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from ..camera import Camera
from ..heightmap import Heightmap
from ..lod.bintree import Bintree, select_bintree
from ..lod.peers import PeerMesh
from ..lod.polytree import Polytree
from ..mesh import Mesh

__all__ = ["SourceBase", "PeerSource", "PolytreeSource", "BintreeSource"]


@dataclass(eq=False)
class SourceBase:
    """What every source carries: a cache (a dict the caller may share between sources of one heightmap).
    Subclass it and add ``mesh_for(camera)`` for a new kind of source."""

    cache: dict = field(default_factory=dict, kw_only=True, repr=False)

    def cached(self, key: object, make: Callable[[], Any]) -> Any:
        if key not in self.cache:
            self.cache[key] = make()
        return self.cache[key]

    def is_cached(self, key: object) -> bool:
        return key in self.cache


@dataclass(eq=False)
class PeerSource(SourceBase):
    """A peer mesher's static mesh; ``error_m`` its measured vertical error (metres, NaN when not measured)."""

    peer: PeerMesh
    heightmap: Heightmap
    error_m: float = math.nan

    @property
    def build_ms(self) -> float:
        return self.peer.mesh_ms

    def mesh_for(self, camera: Camera) -> tuple[Mesh, float]:
        return self.peer.to_mesh(self.heightmap, camera), 0.0


@dataclass(eq=False)
class PolytreeSource(SourceBase):
    """One level of a polytree (view-independent: the finest level is used when ``level`` is past it)."""

    tree: Polytree
    level: int
    build_ms: float = 0.0
    error_m: float = math.nan

    def mesh_for(self, camera: Camera) -> tuple[Mesh, float]:
        return self.tree.mesh(min(int(self.level), self.tree.n_levels - 1), eye=camera.position), 0.0


@dataclass(eq=False)
class BintreeSource(SourceBase):
    """A bintree selected per frame with the paper's apparent-size rule; the whole call is selection."""

    tree: Bintree
    build_ms: float = 0.0
    error_m: float = math.nan

    def mesh_for(self, camera: Camera) -> tuple[Mesh, float]:
        t0 = time.perf_counter()
        mesh = select_bintree(self.tree, camera).mesh
        return mesh, (time.perf_counter() - t0) * 1e3

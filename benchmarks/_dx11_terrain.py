"""The NVIDIA "DirectX 11 Terrain Tessellation" sample's tessellation rule as a mesh source, for
bench_gpu_profiles.py: a uniform grid of quad patches (the continuous policy's level, frustum-culled), each edge's
factor the sample's projected sphere diameter over the target triangle width, capped at 64
(``terrainwarp.lod.policies.dx11_edge_pixels``; inner factors as the continuous policy's), fractional_even
spacing, displaced from the heightmap by the tessellator stage."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from terrainwarp.camera import Camera
from terrainwarp.kernels.tessellator import tessellate_patches
from terrainwarp.lod.policies import continuous_factors, dx11_edge_pixels, make_policy
from terrainwarp.lod.quadtree import Terrain, select
from terrainwarp.mesh import Mesh
from terrainwarp.rendering.sources import SourceBase
from terrainwarp.scene import LodConfig


@dataclass(eq=False)
class Dx11Source(SourceBase):
    """The sample's patches for ``tri_width`` pixels (the sample's ``g_tessellatedTriSize``)."""

    terrain: Terrain = None
    lod: LodConfig = None  # the continuous policy's patch grid (roots as the terrain's, its level)
    tri_width: float = 3.0
    last_patches: int = field(default=0, init=False)

    def mesh_for(self, camera: Camera) -> tuple[Mesh, float]:
        t0 = time.perf_counter()
        hm = self.terrain.heightmap
        p = select(self.terrain, camera, make_policy(self.lod))
        outer, inner = continuous_factors(dx11_edge_pixels(hm, camera, p.origin, p.size), self.tri_width)
        select_ms = (time.perf_counter() - t0) * 1e3
        t = tessellate_patches({"origin_xz": p.origin, "size": p.size, "outer": outer.astype("float32"),
                                "inner": inner.astype("float32"), "level": p.level}, hm.heights, hm.dx, hm.dz,
                               camera.position, spacing="fractional_even", origin=hm.origin,
                               need=("uv", "level", "patch_id"))
        self.patches, self.last_patches = p, len(p)  # (the selection; the factors drawn are the sample's)
        return Mesh(positions=t.positions, eye=camera.position, triangles=t.triangles, uv=t.uv, level=t.level,
                    patch_id=t.patch_id, counters=t.counters), select_ms

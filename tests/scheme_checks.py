"""Shared checks of the LOD schemes' tests (tests/lod/test_cdlod.py, test_clipmaps.py, test_chunked.py): small
terrains and cameras, and the crack check (no background seen through the terrain)."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from terrainwarp import Camera, Heightmap, Scene, render
from terrainwarp.camera import flyover
from terrainwarp.io.files import digest
from terrainwarp.kernels.parallel import set_min_items, set_threads
from terrainwarp.measure.sample_error import sample_error


def small_terrain() -> Heightmap:
    return Heightmap.fbm(129, seed=5, dx=10.0, max_height=300.0)


def ground_path(hm: Heightmap, n: int = 3, clearance_frac: float = 0.02, width: int = 96,
                height: int = 64) -> list[Camera]:
    (x0, z0), (x1, z1) = hm.bounds_xz
    w = [(x0 + 0.15 * (x1 - x0), z0 + 0.2 * (z1 - z0)), (x0 + 0.8 * (x1 - x0), z0 + 0.75 * (z1 - z0))]
    return flyover(hm, w, clearance_frac * (x1 - x0), n, width=width, height=height)


def top_down(hm: Heightmap, height_m: float, width: int = 96, height: int = 64) -> Camera:
    """Straight down over the centre: the terrain fills the view, so every pixel must be covered."""
    (x0, z0), (x1, z1) = hm.bounds_xz
    cx, cz = 0.5 * (x0 + x1), 0.5 * (z0 + z1)
    top = float(np.nanmax(hm.heights))
    return Camera(position=(cx, top + height_m, cz), target=(cx, 0.0, cz), up=(0.0, 0.0, -1.0), fov_y_deg=40.0,
                  width=width, height=height, near=1.0, far=1e5)


def coverage(hm: Heightmap, cam: Camera, source: object, device: str = "cpu") -> tuple[object, np.ndarray, np.ndarray]:
    """(the scheme's frame, its covered pixels, the full grid frame's covered pixels)."""
    scene = Scene(heightmap=hm, camera=cam, outputs=("depth",))
    grid = render(scene, device=device)
    frame = render(scene, source=source, device=device)
    return frame, frame.depth < 1.0, grid.depth < 1.0


def assert_crack_free(hm: Heightmap, cam: Camera, source: object, error_px: float, what: str,
                      device: str = "cpu") -> np.ndarray:
    """No background seen through the terrain: the covered pixels have no holes, and every pixel the full grid
    covers but the scheme does not lies on the terrain's silhouette (within the scheme's screen error, plus a
    pixel, of the grid frame's background), where a coarser surface legitimately shows sky. Returns the
    scheme frame's depth."""
    frame, got, want = coverage(hm, cam, source, device)
    assert np.array_equal(ndimage.binary_fill_holes(got), got), f"{what}: holes inside the terrain"
    to_background = ndimage.distance_transform_edt(want)
    lost = want & ~got
    assert (to_background[lost] <= error_px + 1.5).all(), (
        f"{what}: {int((to_background[lost] > error_px + 1.5).sum())} background pixels inside the terrain, "
        f"up to {to_background[lost].max():.1f} px from its silhouette")
    return frame.depth


def assert_fills_view(hm: Heightmap, cam: Camera, source: object, what: str) -> None:
    _, got, want = coverage(hm, cam, source)
    assert want.all(), "the top-down view must be all terrain"
    assert got.all(), f"{what}: {int((~got).sum())} background pixels seen through the terrain"


def finest_error(hm: Heightmap, cam: Camera, source: object, device: str = "cpu") -> float:
    scene = Scene(heightmap=hm, camera=cam, outputs=("depth",))
    grid = render(scene, device=device)
    frame = render(scene.with_(outputs=("mesh",)), source=source, device=device)
    return sample_error(hm, cam, frame.mesh, grid.depth, device=device).max_px


def mesh_digest(source: object, cams: list[Camera]) -> str:
    out = []
    for cam in cams:
        mesh, _ = source.mesh_for(cam)
        out.append(digest(mesh.positions, mesh.triangles, mesh.uv, mesh.level, mesh.patch_id))
    return digest(np.array([int(d, 16) % (1 << 62) for d in out], np.int64))


def digest_over_threads(make: object, cams: list[Camera], threads: tuple[int, ...] = (1, 3)) -> set[str]:
    """The mesh digests of fresh sources (``make()``) with every launch split as finely as ``threads`` allow."""
    out = set()
    set_min_items(1)
    try:
        for t in threads:
            set_threads(t)
            out.add(mesh_digest(make(), cams))
    finally:
        set_threads(None)
        set_min_items(None)
    return out

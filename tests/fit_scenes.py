"""The fit tests' small scene: an fBm, its default camera, a 3-camera path and their reference frames."""

from __future__ import annotations

from terrainwarp import Camera, Heightmap, LodConfig, Scene
from terrainwarp.fit.exact import references_for


def fit_scene(n: int = 129, max_height: float = 600.0, feature_size: float = 48.0, size: tuple[int, int] = (128, 96)):
    """(scene, cameras, references) on an n x n fBm (seed 4, 20 m spacing), roots 4, tess 8, 3 cameras."""
    hm = Heightmap.fbm(n, seed=4, dx=20.0, max_height=max_height, feature_size=feature_size)
    sc = Scene(hm, camera=Camera.default_for(hm, *size), lod=LodConfig(roots=4, tess=8))
    cams = sc.camera_path(3)
    return sc, cams, references_for(sc, cams)

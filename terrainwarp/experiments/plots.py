"""Pictures people would rather look at than read: top-down LOD maps and the like (matplotlib, Agg)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import Camera
from ..heightmap import Heightmap
from ..io.files import save_figure
from ..kernels.normals import sobel_normals
from ..kernels.shading import light_direction
from ..lod.quadtree import PatchList

__all__ = ["plot_patches"]


def _hillshade(heightmap: Heightmap) -> np.ndarray:
    """(H, W) grey Lambert term in [0, 1] of the pipeline's normal map under its default sun (no-data as 0 m)."""
    n = sobel_normals(np.nan_to_num(heightmap.heights), heightmap.dx, heightmap.dz, border="clamp")
    return np.clip(n.astype(np.float64) @ np.asarray(light_direction(315.0, 45.0)), 0, 1)


def plot_patches(heightmap: Heightmap, patches: PatchList, camera: Camera | None, path: str | Path,
                 title: str = "") -> Path:
    """Top-down map (north up: -z at the top) of the selected patches coloured by level over a hillshade,
    with the camera and the horizontal footprint of its frustum."""
    import matplotlib  # lazy: heavy optional dependency

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy: heavy optional dependency
    from matplotlib.collections import PatchCollection  # lazy: heavy optional dependency
    from matplotlib.patches import Rectangle  # lazy: heavy optional dependency

    (x0, z0), (x1, z1) = heightmap.bounds_xz
    fig, ax = plt.subplots(figsize=(8, 8 * max(0.3, (z1 - z0) / max(x1 - x0, 1e-9))) if x1 > x0 else (8, 8))
    hs = _hillshade(heightmap)
    ax.imshow(hs, cmap="gray", extent=(x0, x1, z1, z0), origin="upper", vmin=0, vmax=1, interpolation="nearest")
    lv = np.asarray(patches.level)
    cmap = plt.get_cmap("viridis", max(int(lv.max()) + 1 if len(lv) else 1, 1))
    rects = [Rectangle((o[0], o[1]), s[0], s[1]) for o, s in zip(patches.origin, patches.size)]
    pc = PatchCollection(rects, facecolor=[cmap(int(v)) for v in lv], edgecolor="k", linewidth=0.3, alpha=0.45)
    ax.add_collection(pc)
    if camera is not None:
        e = np.asarray(camera.position)
        f = camera.forward
        ax.plot([e[0]], [e[2]], "r^", ms=9)
        half = np.arctan(np.tan(np.radians(camera.fov_y_deg) / 2) * camera.aspect)
        fh = np.array([f[0], f[2]])
        if np.linalg.norm(fh) > 1e-9:
            fh /= np.linalg.norm(fh)
            reach = 1.5 * max(x1 - x0, z1 - z0)
            for sgn in (-1, 1):
                c, s = np.cos(sgn * half), np.sin(sgn * half)
                d = np.array([c * fh[0] - s * fh[1], s * fh[0] + c * fh[1]])
                ax.plot([e[0], e[0] + reach * d[0]], [e[2], e[2] + reach * d[1]], "r-", lw=1.2)
    lx0, lx1, lz0, lz1 = x0, x1, z0, z1
    if camera is not None:  # keep the camera in view
        m = 0.05 * max(x1 - x0, z1 - z0)
        lx0, lx1 = min(lx0, camera.position[0] - m), max(lx1, camera.position[0] + m)
        lz0, lz1 = min(lz0, camera.position[2] - m), max(lz1, camera.position[2] + m)
    ax.set_xlim(lx0, lx1)
    ax.set_ylim(lz1, lz0)
    ax.set_xlabel("x (m, east)")
    ax.set_ylabel("z (m, south)")
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(-0.5, cmap.N - 0.5))
    fig.colorbar(sm, ax=ax, label="level", ticks=range(cmap.N), fraction=0.04)
    ax.set_title(title or f"{len(lv)} patches")
    fig.tight_layout()
    return save_figure(fig, path, dpi=110)

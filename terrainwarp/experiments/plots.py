"""Pictures people would rather look at than read: top-down LOD maps and the like (matplotlib, Agg)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..heightmap import Heightmap, StreamedHeightmap
from ..io.files import new_figure, save_figure, write_text
from ..kernels.normals import sobel_normals
from ..kernels.shading import light_direction
from ..lod.quadtree import PatchList
from ..mesh import Mesh

__all__ = ["plot_patches", "patches_figure", "OVERHANG_NOTE", "Pieces", "mesh_pieces"]

#: The legend's word on patches that reach past the heightmap (the quadtree's power-of-two roots cover it):
#: they are drawn whole, and the tessellator clamps their points beyond the border onto it, so no terrain
#: lies there.
OVERHANG_NOTE = "beyond the heightmap: clamped onto its border by displacement (no terrain there)"


HILLSHADE_MAX = 2048  # samples a side of a streamed heightmap's hillshade (its overview at a power-of-two step)


def _hillshade(heightmap: Heightmap | StreamedHeightmap,
               light: tuple[float, float] = (315.0, 45.0)) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """(H, W) grey Lambert term in [0, 1] of the pipeline's normal map under the sun ``light`` (azimuth, elevation
    in degrees: a scene's ``light_azimuth_deg``, ``light_elevation_deg``; no-data as 0 m),
    and its extent (x0, x1, z1, z0) in world metres. A streamed heightmap is shaded from its point-sampled
    overview at the smallest power-of-two step with at most ``HILLSHADE_MAX`` samples a side (never read whole)."""
    (x0, z0), (x1, z1) = heightmap.bounds_xz
    if isinstance(heightmap, StreamedHeightmap):
        step = 1
        while max(heightmap.source.level_shape(step)) > HILLSHADE_MAX:
            step *= 2
        rows, cols = heightmap.source.level_shape(step)
        h = heightmap.window(step, 0, 0, rows, cols)
    else:
        step, h = 1, heightmap.heights
    dx, dz = heightmap.dx * step, heightmap.dz * step
    n = sobel_normals(np.nan_to_num(h), dx, dz, border="clamp")
    shade = np.clip(n.astype(np.float64) @ np.asarray(light_direction(*light)), 0, 1)
    return shade, (x0, x1, z1, z0)  # an overview's last row and column are the grid's (clamped)


def plot_patches(heightmap: Heightmap | StreamedHeightmap, patches: PatchList | Pieces, camera: Camera | None,
                 path: str | Path, title: str = "", light: tuple[float, float] = (315.0, 45.0)) -> Path:
    """Write :func:`patches_figure` to ``path`` (PNG)."""
    return save_figure(patches_figure(heightmap, patches, camera, title, light), path, dpi=110)


@dataclass(frozen=True)
class Pieces:
    """The pieces a mesh source drew (a scheme's nodes, chunks or rings: :func:`mesh_pieces`), as a top-down
    picture and a table take them: ``origin`` and ``size`` (n, 2) world (x, z) metres of each piece's footprint,
    ``level`` (n,) its LOD level, ``vertices`` and ``triangles`` (n,) what it holds, ``stats`` a summary."""

    origin: np.ndarray
    size: np.ndarray
    level: np.ndarray
    vertices: np.ndarray
    triangles: np.ndarray
    stats: dict

    def __len__(self) -> int:
        return len(self.level)

    def to_csv(self, path: str | Path) -> Path:
        lines = ["piece,level,origin_x,origin_z,size_x,size_z,vertices,triangles"]
        lines += [f"{i},{int(lv)},{o[0]:.6f},{o[1]:.6f},{sz[0]:.6f},{sz[1]:.6f},{int(v)},{int(t)}"
                  for i, (lv, o, sz, v, t) in enumerate(zip(self.level, self.origin, self.size, self.vertices,
                                                            self.triangles))]
        return write_text(path, "\n".join(lines) + "\n")


def mesh_pieces(mesh: Mesh) -> Pieces:
    """The pieces of a drawn mesh, one per patch id (a scheme's node, chunk or ring): the (x, z) bounding box
    of its vertices that triangles use, its level (the largest of its vertices'), its vertex and triangle
    counts."""
    tri = np.asarray(mesh.triangles)
    world = mesh.world_positions()
    pid = np.asarray(mesh.patch_id).astype(np.int64)
    used = np.unique(tri.reshape(-1)) if len(tri) else np.zeros(0, np.int64)
    ids, inv = np.unique(pid[used], return_inverse=True)
    lo = np.full((len(ids), 2), np.inf)
    hi = np.full((len(ids), 2), -np.inf)
    np.minimum.at(lo, inv, world[used][:, [0, 2]])
    np.maximum.at(hi, inv, world[used][:, [0, 2]])
    level = np.zeros(len(ids), np.int64)
    np.maximum.at(level, inv, np.asarray(mesh.level)[used].astype(np.int64))
    per_tri = np.searchsorted(ids, pid[tri[:, 0]]) if len(tri) else np.zeros(0, np.int64)
    return Pieces(origin=lo, size=hi - lo, level=level, vertices=np.bincount(inv, minlength=len(ids)),
                  triangles=np.bincount(per_tri, minlength=len(ids)),
                  stats={"pieces": int(len(ids)), "vertices": int(mesh.n_vertices), "triangles": int(len(tri))})


def patches_figure(heightmap: Heightmap | StreamedHeightmap, patches: PatchList | Pieces, camera: Camera | None,
                   title: str = "", light: tuple[float, float] = (315.0, 45.0)):
    """Top-down map (north up: -z at the top) of the selected patches coloured by level over a hillshade,
    with the heightmap's outline, the camera and the horizontal footprint of its frustum.

    Patches that overhang the heightmap are drawn whole; the part beyond its border is hatched and the
    legend says what happens there (:data:`OVERHANG_NOTE`). Returns the matplotlib figure."""
    import matplotlib  # lazy: heavy optional dependency
    from matplotlib.cm import ScalarMappable  # lazy: heavy optional dependency
    from matplotlib.collections import PatchCollection  # lazy: heavy optional dependency
    from matplotlib.colors import Normalize  # lazy: heavy optional dependency
    from matplotlib.patches import Rectangle  # lazy: heavy optional dependency

    (x0, z0), (x1, z1) = heightmap.bounds_xz
    fig, ax = new_figure(figsize=(8, 8 * max(0.3, (z1 - z0) / max(x1 - x0, 1e-9))) if x1 > x0 else (8, 8))
    hs, extent = _hillshade(heightmap, light)
    ax.imshow(hs, cmap="gray", extent=extent, origin="upper", vmin=0, vmax=1, interpolation="nearest")
    lv = np.asarray(patches.level)
    cmap = matplotlib.colormaps["viridis"].resampled(max(int(lv.max()) + 1 if len(lv) else 1, 1))
    rects = [Rectangle((o[0], o[1]), s[0], s[1]) for o, s in zip(patches.origin, patches.size)]
    pc = PatchCollection(rects, facecolor=[cmap(int(v)) for v in lv], edgecolor="k", linewidth=0.3, alpha=0.45)
    ax.add_collection(pc)
    lim = _outline(ax, heightmap, patches, Rectangle)
    if camera is not None:
        _camera(ax, camera, max(x1 - x0, z1 - z0))
        m = 0.05 * max(x1 - x0, z1 - z0)  # keep the camera in view
        lim = (min(lim[0], camera.position[0] - m), max(lim[1], camera.position[0] + m),
               min(lim[2], camera.position[2] - m), max(lim[3], camera.position[2] + m))
    ax.set_xlim(lim[0], lim[1])
    ax.set_ylim(lim[3], lim[2])
    ax.set_xlabel("x (m, east)")
    ax.set_ylabel("z (m, south)")
    sm = ScalarMappable(cmap=cmap, norm=Normalize(-0.5, cmap.N - 0.5))
    fig.colorbar(sm, ax=ax, label="level", ticks=range(cmap.N), fraction=0.04)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.08), fontsize=8, frameon=False, ncol=1)
    ax.set_title(title or f"{len(lv)} patches")
    fig.tight_layout()
    return fig


def _outline(ax, heightmap: Heightmap, patches: PatchList, rectangle: type) -> tuple[float, float, float, float]:
    """Draw the heightmap's border, and hatch the parts of the patches beyond it; the (x0, x1, z0, z1) to show."""
    (x0, z0), (x1, z1) = heightmap.bounds_xz
    ax.add_patch(rectangle((x0, z0), x1 - x0, z1 - z0, fill=False, edgecolor="k", linewidth=1.6, linestyle="--",
                           label="heightmap border", zorder=3))
    if not len(patches):
        return x0, x1, z0, z1
    o = np.asarray(patches.origin, np.float64)
    e = o + np.asarray(patches.size, np.float64).reshape(len(patches), -1)
    # each patch's parts beyond the border: its west and east bands, then north and south between them
    cx0, cx1 = np.clip(o[:, 0], x0, x1), np.clip(e[:, 0], x0, x1)
    bands = np.concatenate([
        np.stack([o[:, 0], o[:, 1], np.minimum(e[:, 0], x0) - o[:, 0], e[:, 1] - o[:, 1]], 1),
        np.stack([np.maximum(o[:, 0], x1), o[:, 1], e[:, 0] - np.maximum(o[:, 0], x1), e[:, 1] - o[:, 1]], 1),
        np.stack([cx0, o[:, 1], cx1 - cx0, np.minimum(e[:, 1], z0) - o[:, 1]], 1),
        np.stack([cx0, np.maximum(o[:, 1], z1), cx1 - cx0, e[:, 1] - np.maximum(o[:, 1], z1)], 1)])
    label = OVERHANG_NOTE
    for bx, bz, bw, bh in bands[(bands[:, 2] > 0) & (bands[:, 3] > 0)]:
        ax.add_patch(rectangle((bx, bz), bw, bh, facecolor="none", edgecolor="0.3", hatch="///", linewidth=0,
                               label=label, zorder=2))
        label = None  # one legend entry
    return min(x0, float(o[:, 0].min())), max(x1, float(e[:, 0].max())), min(z0, float(o[:, 1].min())), \
        max(z1, float(e[:, 1].max()))


def _camera(ax, camera: Camera, extent: float) -> None:
    """The eye (a red triangle) and the horizontal footprint of the frustum's sides."""
    e = np.asarray(camera.position)
    f = camera.forward
    ax.plot([e[0]], [e[2]], "r^", ms=9, label="camera and frustum")
    half = np.arctan(np.tan(np.radians(camera.fov_y_deg) / 2) * camera.aspect)
    fh = np.array([f[0], f[2]])
    if np.linalg.norm(fh) > 1e-9:
        fh /= np.linalg.norm(fh)
        reach = 1.5 * extent
        for sgn in (-1, 1):
            c, s = np.cos(sgn * half), np.sin(sgn * half)
            d = np.array([c * fh[0] - s * fh[1], s * fh[0] + c * fh[1]])
            ax.plot([e[0], e[0] + reach * d[0]], [e[2], e[2] + reach * d[1]], "r-", lw=1.2)

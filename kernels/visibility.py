"""Cell-to-node visibility for ground-based observers (mrbsp-lod-visibility.txt, section 4).

One launch evaluates every (cell, coarse node) pair: the node is visible from the cell when any of the
segments from the cell's eye samples to the node's target samples is not occluded by the blockers.

Conservative by construction for each segment it tests (see terrainwarp/visibility.py):

* blockers are a coarse grid of flat squares at the **minimum** height of the level-M surface over
  each square, so they lie below the terrain: a segment they occlude is truly occluded;
* the segment is only sampled (every half blocker square), so an occluder can be stepped over, which
  errs towards "visible";
* eye samples sit at the cell's **maximum** surface height + the eye height, targets at the node's
  **maximum** subtree height: raising an end point of a segment keeps its (x, z) path and raises every
  point of it, so it can only make the segment less occluded.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .parallel import launch_one


@wp.func
def _occluded(e: wp.vec3, t: wp.vec3, blk: wp.array2d(dtype=wp.float32), bx0: float, bz0: float, inv_bs: float,
              step: float) -> wp.bool:
    d = t - e
    lxz = wp.sqrt(d[0] * d[0] + d[2] * d[2])
    n = int(lxz / step)
    res = int(0)
    rows = blk.shape[0]
    cols = blk.shape[1]
    k = int(1)
    while k <= n and res == 0:
        s = float(k) * step / lxz
        if s < 1.0:
            p = e + d * s
            j = wp.clamp(int(wp.floor((p[0] - bx0) * inv_bs)), 0, cols - 1)
            i = wp.clamp(int(wp.floor((p[2] - bz0) * inv_bs)), 0, rows - 1)
            if p[1] < blk[i, j]:
                res = 1
        k += 1
    return res != 0


@wp.kernel(enable_backward=False)
def _cell_node_kernel(eyes: wp.array2d(dtype=wp.vec3), targets: wp.array2d(dtype=wp.vec3),
                      blk: wp.array2d(dtype=wp.float32), bx0: float, bz0: float, inv_bs: float, step: float,
                      # outputs
                      out_vis: wp.array2d(dtype=wp.uint8)):
    c, n = wp.tid()
    vis = int(0)
    ne = eyes.shape[1]
    nt = targets.shape[1]
    k = int(0)
    while k < ne * nt and vis == 0:
        a = k / nt
        if not _occluded(eyes[c, a], targets[n, k - a * nt], blk, bx0, bz0, inv_bs, step):
            vis = 1
        k += 1
    out_vis[c, n] = wp.uint8(vis)


def cell_node_visibility(eyes: np.ndarray, targets: np.ndarray, blockers: np.ndarray, blocker_origin: tuple,
                         blocker_size: float, device: str = "cpu") -> np.ndarray:
    """Visibility of every coarse node from every cell.

    Args:
        eyes: (C, E, 3) float32 eye samples per cell (world, or any frame shared with the others).
        targets: (N, T, 3) float32 target samples per node.
        blockers: (R, Q) float32 blocker heights, square (i, j) covering x in [bx0 + j*bs, bx0 + (j+1)*bs)
            and z in [bz0 + i*bs, ...); points outside are clamped to the border squares.
        blocker_origin: (bx0, bz0); blocker_size: bs in metres (segments are sampled every bs / 2).

    Returns:
        (C, N) uint8, 1 where the node is visible from the cell.
    """
    e = np.ascontiguousarray(eyes, np.float32)
    t = np.ascontiguousarray(targets, np.float32)
    out = wp.zeros((e.shape[0], t.shape[0]), dtype=wp.uint8, device=device)
    if e.shape[0] and t.shape[0]:
        launch_one(_cell_node_kernel, dim=(e.shape[0], t.shape[0]),
                  inputs=[wp.array(e, dtype=wp.vec3, device=device), wp.array(t, dtype=wp.vec3, device=device),
                          wp.array(np.ascontiguousarray(blockers, np.float32), dtype=wp.float32, device=device),
                          float(blocker_origin[0]), float(blocker_origin[1]), 1.0 / float(blocker_size),
                          0.5 * float(blocker_size)],
                  outputs=[out], device=device)
    return out.numpy()

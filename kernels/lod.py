"""Per-node LOD maths for quadtree selection: one launch per level over that level's candidate nodes.

For each node: its box (x/z extent, min/max height) relative to the eye, the distance from the eye to
the box (0 when the eye is inside it: a defined case, never a division by zero), a frustum test of
the box against the six planes of the view-projection matrix (Gribb-Hartmann extraction, p-vertex
test), and the policy's split decision:

* policy 0, distance (deaconu2021 "Rendering"): split while ``dist < threshold[level]``;
* policy 1, screen-space error (malafeev2014, Cesium's maximumScreenSpaceError):
  ``sse = geometric_error * focal_px / dist`` with ``focal_px = viewport_height / (2 tan(fovy/2))``,
  split while ``sse > tolerance_px``; at ``dist == 0`` a node with any error splits and a node with
  zero error does not (0 * inf is defined as 0).

Hysteresis (malafeev2014: separate thresholds for going to a finer and to a coarser level): with band
``h``, a node that was split in the previous frame stays split until the metric crosses the *merge*
threshold (``tolerance * (1 - h)`` for sse, ``threshold * (1 + h)`` for distance), and a node that was
not split splits only past the *split* threshold (``tolerance * (1 + h)``, ``threshold * (1 - h)``).
"Was split" is looked up by binary search in the sorted keys of the previous frame's split nodes.
"""

from __future__ import annotations

import numpy as np
import warp as wp


@wp.func
def _was_split(keys: wp.array(dtype=wp.int64), n: int, key: wp.int64) -> wp.bool:
    lo = int(0)
    hi = n
    while lo < hi:
        mid = (lo + hi) / 2
        if keys[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    return lo < n and keys[lo] == key


@wp.func
def box_outside(planes: wp.array(dtype=wp.vec4), lo: wp.vec3, hi: wp.vec3) -> int:
    """1 when the box [lo, hi] lies outside one of the six frustum planes (p-vertex test)."""
    out = int(0)
    for p in range(6):
        pl = planes[p]
        vx = wp.where(pl[0] >= 0.0, hi[0], lo[0])
        vy = wp.where(pl[1] >= 0.0, hi[1], lo[1])
        vz = wp.where(pl[2] >= 0.0, hi[2], lo[2])
        if pl[0] * vx + pl[1] * vy + pl[2] * vz + pl[3] < 0.0:
            out = 1
    return out


@wp.kernel(enable_backward=False)
def _select_kernel(
    node_x: wp.array(dtype=wp.int32),
    node_y: wp.array(dtype=wp.int32),
    node_key: wp.array(dtype=wp.int64),
    hmin: wp.array2d(dtype=wp.float32),
    hmax: wp.array2d(dtype=wp.float32),
    gerr: wp.array2d(dtype=wp.float32),
    rel_origin: wp.vec3,
    node_size: wp.vec2,
    planes: wp.array(dtype=wp.vec4),
    policy: int,
    threshold: float,
    focal_px: float,
    hysteresis: float,
    can_split: int,
    prev_split: wp.array(dtype=wp.int64),
    n_prev: int,
    # outputs
    out_split: wp.array(dtype=wp.int32),
    out_culled: wp.array(dtype=wp.int32),
    out_dist: wp.array(dtype=wp.float32),
    out_metric: wp.array(dtype=wp.float32),
):
    k = wp.tid()
    x = node_x[k]
    y = node_y[k]
    lo = wp.vec3(rel_origin[0] + float(x) * node_size[0], hmin[y, x] - rel_origin[1],
                 rel_origin[2] + float(y) * node_size[1])
    hi = wp.vec3(lo[0] + node_size[0], hmax[y, x] - rel_origin[1], lo[2] + node_size[1])
    # distance from the eye (the origin) to the box
    dx = wp.max(wp.max(lo[0], -hi[0]), 0.0)
    dy = wp.max(wp.max(lo[1], -hi[1]), 0.0)
    dz = wp.max(wp.max(lo[2], -hi[2]), 0.0)
    dist = wp.sqrt(dx * dx + dy * dy + dz * dz)
    out_dist[k] = dist
    culled = box_outside(planes, lo, hi)
    out_culled[k] = culled
    prev = _was_split(prev_split, n_prev, node_key[k])
    split = int(0)
    if policy == 0:
        thr = threshold * wp.where(prev, 1.0 + hysteresis, 1.0 - hysteresis)
        out_metric[k] = dist
        if dist < thr:
            split = 1
    else:
        e = gerr[y, x]
        sse = float(0.0)
        if e > 0.0:
            if dist > 0.0:
                sse = e * focal_px / dist
            else:
                sse = 3.0e38
        out_metric[k] = sse
        thr = threshold * wp.where(prev, 1.0 - hysteresis, 1.0 + hysteresis)
        if sse > thr:
            split = 1
    if culled != 0 or can_split == 0:
        split = 0
    out_split[k] = split


def frustum_planes(view_proj: np.ndarray) -> np.ndarray:
    """The six planes (a, b, c, d), inside where a x + b y + c z + d >= 0, of an OpenGL view-projection
    matrix (Gribb & Hartmann), normalised, float32 (6, 4): left, right, bottom, top, near, far."""
    m = np.asarray(view_proj, dtype=np.float64)
    r0, r1, r2, r3 = m
    pl = np.array([r3 + r0, r3 - r0, r3 + r1, r3 - r1, r3 + r2, r3 - r2])
    pl /= np.linalg.norm(pl[:, :3], axis=1, keepdims=True)
    return pl.astype(np.float32)


def _dev(a, device: str) -> wp.array:
    return a if isinstance(a, wp.array) else wp.array(np.ascontiguousarray(a, np.float32), dtype=wp.float32,
                                                      device=device)


def select_level(node_x: np.ndarray, node_y: np.ndarray, node_key: np.ndarray, stats: tuple, rel_origin,
                 node_size_world, planes: np.ndarray, policy: int, threshold: float, focal_px: float,
                 hysteresis: float, can_split: bool, prev_split: np.ndarray, device: str = "cpu"):
    """Evaluate one level's candidate nodes. Returns (split, culled, dist, metric) numpy arrays."""
    n = len(node_x)
    hmin, hmax, gerr = stats
    prev = np.ascontiguousarray(prev_split, dtype=np.int64)
    arrs = [wp.empty(n, dtype=wp.int32, device=device), wp.empty(n, dtype=wp.int32, device=device),
            wp.empty(n, dtype=wp.float32, device=device), wp.empty(n, dtype=wp.float32, device=device)]
    if n == 0:
        return tuple(a.numpy() for a in arrs)
    wp.launch(_select_kernel, dim=n, inputs=[
        wp.array(node_x.astype(np.int32), dtype=wp.int32, device=device),
        wp.array(node_y.astype(np.int32), dtype=wp.int32, device=device),
        wp.array(node_key.astype(np.int64), dtype=wp.int64, device=device),
        _dev(hmin, device), _dev(hmax, device), _dev(gerr, device),
        wp.vec3(*[float(v) for v in rel_origin]), wp.vec2(*[float(v) for v in node_size_world]),
        wp.array(planes, dtype=wp.vec4, device=device), int(policy), float(threshold), float(focal_px),
        float(hysteresis), int(bool(can_split)),
        wp.array(prev if len(prev) else np.zeros(1, np.int64), dtype=wp.int64, device=device), int(len(prev))],
        outputs=arrs, device=device)
    return tuple(a.numpy() for a in arrs)

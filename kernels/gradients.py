"""Deterministic backward passes: the resolve (perspective-correct interpolation) and the displacement
stage, and the fixed-order reductions every backward pass here shares.

nvdiffrast scatters gradients with float atomics, so its gradients change from run to run. Here no float is
ever added by an atomic; each sum has one owner that adds its terms in a fixed order:

- pixels -> triangle corners: each triangle's thread walks the pixels of its coverage box (the box of the
  pixels whose id is that triangle, found with integer atomic mins, whose result is order-free) in
  row-major order and adds the contributions of its own pixels (:func:`coverage_box`);
- triangle corners -> vertices: the corners are grouped by vertex (count -> scan -> fill, then each group
  sorted by corner index by its own thread), and each vertex adds its corners in that order
  (:func:`group_by`, :func:`segment_rows`);
- vertices -> heightmap samples: the vertices are grouped by bilinear cell the same way, and each sample
  adds, cell by cell in a fixed order, the weighted gradients of the vertices of the (up to) four cells
  around it.

Integer atomics (counts, cursors, box mins) are true CPU atomics (``parallel.atomic_*``) whose results do
not depend on order, so every output is bit-identical for any thread count and on every run.

Every launch goes through :func:`terrainwarp.kernels.parallel.launch`.
"""

from __future__ import annotations

import warp as wp

from .parallel import atomic_add_i32, atomic_min_i32, launch, launch_one, scan
from .raster import clip_barycentrics, pixel_ndc
from .sampling import sample_bilinear

_BIG = 1 << 30  # an empty coverage box: every min stays here
_OVERSPLIT = 4  # per-triangle work is uneven (near and far triangles)
_MIN_TRIANGLES = 1024
_MIN_PIXELS = 32768

# ------------------------------------------------------------------------------------------------
# functions
# ------------------------------------------------------------------------------------------------


@wp.func
def box_rows(box: wp.array2d(dtype=wp.int32), t: int) -> wp.vec4i:
    """Coverage box of triangle t as (row0, row1, col0, col1), inclusive; row0 > row1 when empty."""
    return wp.vec4i(box[t, 1], -box[t, 3], box[t, 0], -box[t, 2])


@wp.func
def _bilinear_taps(rows: int, cols: int, uv: wp.vec2) -> wp.vec4:
    """(i0, j0, fv, fu) of the bilinear sample at uv in [0, 1], as ``sampling.sample_bilinear`` takes it:
    grid coordinates clamped to the grid, the cell's low corner, the fractions."""
    uc = wp.clamp(uv[0] * float(cols - 1), 0.0, float(cols - 1))
    vc = wp.clamp(uv[1] * float(rows - 1), 0.0, float(rows - 1))
    j0 = wp.floor(uc)
    i0 = wp.floor(vc)
    return wp.vec4(i0, j0, vc - i0, uc - j0)


@wp.func
def _tap_weight(i: int, j: int, i0: int, j0: int, fv: float, fu: float, rows: int, cols: int) -> float:
    """d(bilinear sample)/d(sample (i, j)) for the sample with taps from (i0, j0) (edge taps clamped)."""
    i1 = wp.min(i0 + 1, rows - 1)
    j1 = wp.min(j0 + 1, cols - 1)
    wv = float(0.0)
    if i == i0:
        wv += 1.0 - fv
    if i == i1:
        wv += fv
    wu = float(0.0)
    if j == j0:
        wu += 1.0 - fu
    if j == j1:
        wu += fu
    return wv * wu


# ------------------------------------------------------------------------------------------------
# kernels: grouping and fixed-order sums
# ------------------------------------------------------------------------------------------------


@wp.kernel(enable_backward=False)
def _count_kernel(
    offset: int,
    keys: wp.array(dtype=wp.int32),
    # outputs
    out_count: wp.array(dtype=wp.int32),
):
    e = wp.tid() + offset
    atomic_add_i32(out_count, keys[e], 1)


@wp.kernel(enable_backward=False)
def _fill_kernel(
    offset: int,
    keys: wp.array(dtype=wp.int32),
    # outputs
    out_cursor: wp.array(dtype=wp.int32),
    out_items: wp.array(dtype=wp.int32),
):
    """Each item into a free slot of its key's segment (slot order varies; sorted afterwards)."""
    e = wp.tid() + offset
    out_items[atomic_add_i32(out_cursor, keys[e], 1)] = e


@wp.kernel(enable_backward=False)
def _sort_segments_kernel(
    offset: int,
    start: wp.array(dtype=wp.int32),
    # outputs
    out_items: wp.array(dtype=wp.int32),
):
    """Insertion sort of each key's segment (short: a vertex's corners, a cell's vertices)."""
    k = wp.tid() + offset
    s = start[k]
    e = start[k + 1]
    for a in range(s + 1, e):
        v = out_items[a]
        b = a - 1
        while b >= s and out_items[b] > v:
            out_items[b + 1] = out_items[b]
            b -= 1
        out_items[b + 1] = v


@wp.kernel(enable_backward=False)
def _segment_rows_kernel(
    offset: int,
    start: wp.array(dtype=wp.int32),
    items: wp.array(dtype=wp.int32),
    src: wp.array2d(dtype=wp.float32),
    # outputs
    out: wp.array2d(dtype=wp.float32),
):
    """out[k, :] = sum of src[items[s], :] over key k's segment, in segment order."""
    k = wp.tid() + offset
    for d in range(src.shape[1]):
        acc = float(0.0)
        for s in range(start[k], start[k + 1]):
            acc += src[items[s], d]
        out[k, d] = acc


@wp.kernel(enable_backward=False)
def _box_kernel(
    offset: int,
    ids: wp.array2d(dtype=wp.int32),
    # outputs
    out_box: wp.array2d(dtype=wp.int32),
):
    """Coverage box per triangle: min column, min row, min -column, min -row (integer atomics)."""
    i, j = wp.tid()
    i += offset
    t = ids[i, j]
    if t >= 0:
        atomic_min_i32(out_box, t, 0, j)
        atomic_min_i32(out_box, t, 1, i)
        atomic_min_i32(out_box, t, 2, -j)
        atomic_min_i32(out_box, t, 3, -i)


@wp.kernel(enable_backward=False)
def _block_sum_kernel(
    offset: int,
    src: wp.array2d(dtype=wp.float32),
    block: int,
    # outputs
    out: wp.array2d(dtype=wp.float32),
):
    """Partial sums of fixed blocks of rows (the block size, not the thread count, sets the order)."""
    b = wp.tid() + offset
    s = b * block
    e = wp.min(s + block, src.shape[0])
    for d in range(src.shape[1]):
        acc = float(0.0)
        for r in range(s, e):
            acc += src[r, d]
        out[b, d] = acc


# ------------------------------------------------------------------------------------------------
# kernels: interpolation
# ------------------------------------------------------------------------------------------------


@wp.kernel(enable_backward=False)
def _interpolate_kernel(
    offset: int,
    ids: wp.array2d(dtype=wp.int32),
    clip: wp.array(dtype=wp.vec4),
    tris: wp.array2d(dtype=wp.int32),
    attr: wp.array2d(dtype=wp.float32),
    # outputs
    out: wp.array3d(dtype=wp.float32),
):
    """Perspective-correct interpolation at each pixel centre (:func:`.raster.clip_barycentrics` at
    :func:`.raster.pixel_ndc`), every channel, one thread per pixel; 0 on background."""
    i, j = wp.tid()
    i += offset
    t = ids[i, j]
    if t < 0:
        for ch in range(attr.shape[1]):
            out[i, j, ch] = 0.0
        return
    i0 = tris[t, 0]
    i1 = tris[t, 1]
    i2 = tris[t, 2]
    b = clip_barycentrics(clip[i0], clip[i1], clip[i2], pixel_ndc(i, j, ids.shape[0], ids.shape[1]))
    for ch in range(attr.shape[1]):
        out[i, j, ch] = b[0] * attr[i0, ch] + b[1] * attr[i1, ch] + b[2] * attr[i2, ch]


@wp.kernel(enable_backward=False)
def _interpolate_grad_kernel(
    offset: int,
    box: wp.array2d(dtype=wp.int32),
    ids: wp.array2d(dtype=wp.int32),
    clip: wp.array(dtype=wp.vec4),
    tris: wp.array2d(dtype=wp.int32),
    attr: wp.array2d(dtype=wp.float32),
    g: wp.array3d(dtype=wp.float32),
    # outputs
    out_clip: wp.array2d(dtype=wp.float32),
    out_attr: wp.array2d(dtype=wp.float32),
):
    """Per triangle t: d(loss)/d(clip) and d(loss)/d(attr) of its three corners (rows 3t..3t+2), summed
    over its pixels in row-major order. b = cross(a, c) / s gives dL/dcross = (gb - dot(gb, b)) / s, then
    dL/da = cross(c, gcr) and dL/dc = cross(gcr, a)."""
    t = wp.tid() + offset
    nc = attr.shape[1]
    v0 = tris[t, 0]
    v1 = tris[t, 1]
    v2 = tris[t, 2]
    c0 = clip[v0]
    c1 = clip[v1]
    c2 = clip[v2]
    gc0 = wp.vec4()
    gc1 = wp.vec4()
    gc2 = wp.vec4()
    for ch in range(nc):
        out_attr[3 * t, ch] = 0.0
        out_attr[3 * t + 1, ch] = 0.0
        out_attr[3 * t + 2, ch] = 0.0
    r = box_rows(box, t)
    hh = ids.shape[0]
    ww = ids.shape[1]
    for i in range(r[0], r[1] + 1):
        for j in range(r[2], r[3] + 1):
            if ids[i, j] == t:
                p = pixel_ndc(i, j, hh, ww)
                a = wp.vec3(c0[0] - p[0] * c0[3], c1[0] - p[0] * c1[3], c2[0] - p[0] * c2[3])
                c = wp.vec3(c0[1] - p[1] * c0[3], c1[1] - p[1] * c1[3], c2[1] - p[1] * c2[3])
                cr = wp.cross(a, c)
                inv = 1.0 / (cr[0] + cr[1] + cr[2])
                b = cr * inv
                gb = wp.vec3()
                for ch in range(nc):
                    gv = g[i, j, ch]
                    gb += gv * wp.vec3(attr[v0, ch], attr[v1, ch], attr[v2, ch])
                    out_attr[3 * t, ch] += b[0] * gv
                    out_attr[3 * t + 1, ch] += b[1] * gv
                    out_attr[3 * t + 2, ch] += b[2] * gv
                gcr = (gb - wp.vec3(wp.dot(gb, b))) * inv
                ga = wp.cross(c, gcr)
                gcc = wp.cross(gcr, a)
                gc0 += wp.vec4(ga[0], gcc[0], 0.0, -p[0] * ga[0] - p[1] * gcc[0])
                gc1 += wp.vec4(ga[1], gcc[1], 0.0, -p[0] * ga[1] - p[1] * gcc[1])
                gc2 += wp.vec4(ga[2], gcc[2], 0.0, -p[0] * ga[2] - p[1] * gcc[2])
    for d in range(4):
        out_clip[3 * t, d] = gc0[d]
        out_clip[3 * t + 1, d] = gc1[d]
        out_clip[3 * t + 2, d] = gc2[d]


# ------------------------------------------------------------------------------------------------
# kernels: displacement
# ------------------------------------------------------------------------------------------------


@wp.kernel(enable_backward=False)
def _displace_kernel(
    offset: int,
    heights: wp.array2d(dtype=wp.float32),
    uv: wp.array(dtype=wp.vec2),
    spacing: wp.vec2,
    eye: wp.array(dtype=wp.float32),
    # outputs
    out_pos: wp.array2d(dtype=wp.float32),
):
    """Camera-relative position of the surface point at uv: grid origin at world (0, 0), so the relative
    origin is (-eye_x, eye_y, -eye_z) exactly (``camera.relative_origin`` with a zero origin)."""
    k = wp.tid() + offset
    rows = heights.shape[0]
    cols = heights.shape[1]
    u = uv[k][0] * float(cols - 1)
    v = uv[k][1] * float(rows - 1)
    out_pos[k, 0] = -eye[0] + u * spacing[0]
    out_pos[k, 1] = sample_bilinear(heights, u, v) - eye[1]
    out_pos[k, 2] = -eye[2] + v * spacing[1]


@wp.kernel(enable_backward=False)
def _cell_key_kernel(
    offset: int,
    rows: int,
    cols: int,
    uv: wp.array(dtype=wp.vec2),
    # outputs
    out_key: wp.array(dtype=wp.int32),
):
    k = wp.tid() + offset
    tap = _bilinear_taps(rows, cols, uv[k])
    out_key[k] = int(tap[0]) * cols + int(tap[1])


@wp.kernel(enable_backward=False)
def _height_grad_kernel(
    offset: int,
    uv: wp.array(dtype=wp.vec2),
    start: wp.array(dtype=wp.int32),
    items: wp.array(dtype=wp.int32),
    g: wp.array2d(dtype=wp.float32),
    # outputs
    out: wp.array2d(dtype=wp.float32),
):
    """d(loss)/d(sample (i, j)): the cells (i-1, j-1), (i-1, j), (i, j-1), (i, j) in that order, each
    cell's vertices in index order."""
    i, j = wp.tid()
    i += offset
    rows = out.shape[0]
    cols = out.shape[1]
    acc = float(0.0)
    for ci in range(wp.max(i - 1, 0), i + 1):
        for cj in range(wp.max(j - 1, 0), j + 1):
            cell = ci * cols + cj
            for s in range(start[cell], start[cell + 1]):
                k = items[s]
                tap = _bilinear_taps(rows, cols, uv[k])
                acc += _tap_weight(i, j, ci, cj, tap[2], tap[3], rows, cols) * g[k, 1]
    out[i, j] = acc


@wp.kernel(enable_backward=False)
def _negate_kernel(
    total: wp.array2d(dtype=wp.float32),
    # outputs
    out: wp.array(dtype=wp.float32),
):
    d = wp.tid()
    out[d] = -total[0, d]


# ------------------------------------------------------------------------------------------------
# host (Warp arrays in, Warp arrays out: called from the JAX callables of terrainwarp.diff)
# ------------------------------------------------------------------------------------------------


def group_by(keys: wp.array, nkeys: int) -> tuple[wp.array, wp.array]:
    """Group item indices by key: ``(start (nkeys+1,) int32, items (K,) int32)`` with key k's items at
    ``items[start[k]:start[k+1]]`` in increasing order (deterministic for any thread count)."""
    dev = keys.device
    n = keys.shape[0]
    count = wp.zeros(nkeys + 1, dtype=wp.int32, device=dev)
    launch(_count_kernel, n, [keys], [count], dev)
    start = wp.empty(nkeys + 1, dtype=wp.int32, device=dev)
    scan(count, start, inclusive=False)
    cursor = wp.clone(start)
    items = wp.empty(max(n, 1), dtype=wp.int32, device=dev)
    launch(_fill_kernel, n, [keys], [cursor, items], dev)
    launch(_sort_segments_kernel, nkeys, [start], [items], dev, min_items=_MIN_TRIANGLES)
    return start, items


def segment_rows(start: wp.array, items: wp.array, src: wp.array, out: wp.array) -> None:
    """``out[k] = sum(src[items[start[k]:start[k+1]]])`` row by row, in segment order; out is (nkeys, D)."""
    launch(_segment_rows_kernel, out.shape[0], [start, items, src], [out], out.device, min_items=_MIN_TRIANGLES)


def corners_to_vertices(tris: wp.array, corner: wp.array, out: wp.array) -> None:
    """Sum per-corner rows (3m, D) (row 3t+c: corner c of triangle t) into per-vertex rows ``out`` (n, D),
    each vertex adding its corners in increasing corner order."""
    start, items = group_by(tris.flatten(), out.shape[0])
    segment_rows(start, items, corner, out)


def coverage_box(ids: wp.array, m: int) -> wp.array:
    """(m, 4) int32 coverage box per triangle of the id image (see :func:`box_rows`)."""
    box = wp.full((max(m, 1), 4), _BIG, dtype=wp.int32, device=ids.device)
    launch(_box_kernel, ids.shape, [ids], [box], ids.device, min_items=_MIN_PIXELS)
    return box


def interpolate_forward(ids: wp.array, clip: wp.array, tris: wp.array, attr: wp.array, out: wp.array) -> None:
    """(H, W) ids, (n,) vec4 clip, (m, 3) triangles, (n, C) attributes -> ``out`` (H, W, C)."""
    launch(_interpolate_kernel, ids.shape, [ids, clip, tris, attr], [out], out.device, min_items=_MIN_PIXELS)


def interpolate_backward(ids: wp.array, clip: wp.array, tris: wp.array, attr: wp.array, g: wp.array,
                         out_clip: wp.array, out_attr: wp.array) -> None:
    """Gradients of :func:`interpolate_forward`: ``out_clip`` (n, 4) and ``out_attr`` (n, C) float32."""
    dev = ids.device
    m = tris.shape[0]
    nc = attr.shape[1]
    gclip = wp.empty((3 * m, 4), dtype=wp.float32, device=dev)
    gattr = wp.empty((3 * m, nc), dtype=wp.float32, device=dev)
    box = coverage_box(ids, m)
    launch(_interpolate_grad_kernel, m, [box, ids, clip, tris, attr, g], [gclip, gattr], dev,
           min_items=_MIN_TRIANGLES, oversplit=_OVERSPLIT)
    start, items = group_by(tris.flatten(), out_clip.shape[0])
    segment_rows(start, items, gclip, out_clip)
    segment_rows(start, items, gattr, out_attr)


def displace_forward(heights: wp.array, uv: wp.array, spacing: tuple[float, float], eye: wp.array,
                     out: wp.array) -> None:
    """(H, W) heights, (n,) vec2 uv in [0, 1], (dx, dz), eye (3,) -> camera-relative ``out`` (n, 3)."""
    launch(_displace_kernel, uv.shape[0], [heights, uv, wp.vec2(*spacing), eye], [out], out.device)


def displace_backward(uv: wp.array, g: wp.array, out_heights: wp.array, out_eye: wp.array,
                      block: int = 4096) -> None:
    """Gradients of :func:`displace_forward` for the (n, 3) gradient ``g``: ``out_heights`` (H, W) and
    ``out_eye`` (3,) = -(sum of g), summed in blocks of ``block`` rows, the blocks in order."""
    dev = uv.device
    rows, cols = out_heights.shape
    n = uv.shape[0]
    key = wp.empty(n, dtype=wp.int32, device=dev)
    launch(_cell_key_kernel, n, [rows, cols, uv], [key], dev)
    start, items = group_by(key, rows * cols)
    launch(_height_grad_kernel, (rows, cols), [uv, start, items, g], [out_heights], dev)
    nb = (n + block - 1) // block
    part = wp.empty((nb, 3), dtype=wp.float32, device=dev)
    launch(_block_sum_kernel, nb, [g, block], [part], dev, min_items=1)
    total = wp.empty((1, 3), dtype=wp.float32, device=dev)
    launch_one(_block_sum_kernel, 1, inputs=[0, part, nb], outputs=[total], device=dev)
    launch_one(_negate_kernel, 3, inputs=[total], outputs=[out_eye], device=dev)

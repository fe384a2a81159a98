"""Pipeline statistics of the draws that make a frame, as OpenGL's ARB_pipeline_statistics_query names them
(lower-case): what the input assembler, the vertex and tessellation stages would count for the draw calls a
family issues, and the rasterizer's tallies turned into its counters.

* The rasterizer (:func:`terrainwarp.kernels.raster.rasterize`) adds what it counts into an int64 array of
  ``TALLIES`` columns, one row per launch chunk (``T_*`` name the columns); :func:`raster_stats` and
  :func:`raster_counters` read the rows' sums into its ``stats`` and its pipeline statistics (``counters=True``).

* A patch draw (:func:`patch_draw_counters`): 4 control points per patch, each through the vertex shader;
  every patch through the tessellation control shader (``tess_control_shader_patches``, culled ones too); one
  evaluation shader invocation per domain point (``tess_evaluation_shader_invocations``: no point is shared
  across patches); the triangles the primitive generator emits (``primitives_generated``).
* Indexed triangle draws (:func:`indexed_draw_counters`): 3 indices per triangle submitted, one vertex shader
  invocation per distinct vertex a draw references (``vertex_shader_invocations``: a post-transform cache that
  holds the whole draw, what an index order made for the cache approaches), and llvmpipe's own count
  (``vertex_shader_invocations_llvmpipe``, equal to its query: Mesa's vertex splitter cuts each draw into
  segments of 1023 indices and shades a vertex again whenever it misses a 256-entry direct-mapped cache,
  ``index % 256``, cleared per segment; 13-33% more than distinct vertices on grid-like index orders, 5x on
  Delatin's).

Bytes read, counted before any cache: ``bytes_vertex`` (vertex attributes fetched per vertex shader invocation,
or per-patch records), ``bytes_index`` (4 per index), ``bytes_heightmap`` (texels a displacement fetches).
"""

import numpy as np
import warp as wp

from .parallel import launch
from .pool import pooled_rows_array

__all__ = ["patch_draw_counters", "indexed_draw_counters", "frame_counters", "raster_stats", "raster_counters",
           "PATCH_RECORD_BYTES", "INDEX_BYTES", "DRAW_COUNTERS", "RASTER_COUNTERS", "DERIVED_COUNTERS",
           "PIPELINE_COUNTERS", "TALLIES"]

PATCH_RECORD_BYTES = 48  # box (4 floats), outer (4), inner (2), padding (2): one storage-buffer record per patch
INDEX_BYTES = 4  # 32-bit indices
# the counters of the draws (the rasterizer adds its own), in the order reports list them
DRAW_COUNTERS = ("draw_calls", "vertices_submitted", "primitives_submitted", "vertex_shader_invocations",
                 "vertex_shader_invocations_llvmpipe", "tess_control_shader_patches",
                 "tess_evaluation_shader_invocations", "primitives_generated", "bytes_vertex", "bytes_index",
                 "bytes_heightmap")
VSPLIT_SEGMENT = 1023  # indices per segment of Mesa's vertex splitter (1024, whole triangles)
VSPLIT_CACHE = 256  # entries of its direct-mapped vertex cache
vec_vsplit = wp.types.vector(length=VSPLIT_CACHE, dtype=wp.int32)
# the rasterizer's (terrainwarp.kernels.raster.Fragments.counters), then what a frame's counters derive from them
RASTER_COUNTERS = ("clipping_input_primitives", "clipping_output_primitives", "fragment_shader_invocations",
                   "fragment_shader_invocations_llvmpipe", "samples_passed", "samples_covered", "pixels_covered")
DERIVED_COUNTERS = ("quad_efficiency", "overdraw")
PIPELINE_COUNTERS = DRAW_COUNTERS + RASTER_COUNTERS + DERIVED_COUNTERS
_MIN_TRIANGLES = 16384

# The rasterizer's tallies: the columns of its per-chunk int64 rows (kernels/raster.py adds into them)
T_RASTERIZED = 0  # triangles that reach the coverage test (after rejection, clipping, zero area and culling)
T_BINNED = 1  # large triangles (pixel box of SMALL_PX or more), drawn on the 16-pixel depth grid
T_TILE16 = 2  # the 16x16 screen tiles those large triangles may cover (their corners do not exclude them)
T_TESTED = 3  # pixel centres in the 4x4 blocks the corner tests did not reject
T_INSIDE = 4  # pixel centres covered, every (fan) triangle's: samples_covered
T_PASSED = 5  # fragments that passed GL_LESS in submission order: samples_passed
T_COVERED = 6  # pixels covered in the end
T_QUADS = 7  # 2x2 quads with a covered centre, per (fan) triangle
T_BLOCKS = 8  # 4x4 blocks with a covered centre, per (fan) triangle
T_CLIPPED = 9  # the clipper's output triangles
TALLIES = 10


def raster_stats(tally: np.ndarray, triangles: int) -> dict[str, int]:
    """The rasterizer's ``Fragments.stats`` from its tallies summed over the rows (``tally``, (TALLIES,) int64) for
    a draw of ``triangles`` triangles."""
    return {"triangles_in": int(triangles), "triangles_rasterized": int(tally[T_RASTERIZED]),
            "triangles_binned": int(tally[T_BINNED]), "tile_entries": int(tally[T_TILE16]),
            "fragments_tested": int(tally[T_TESTED]), "fragments_inside": int(tally[T_INSIDE]),
            "pixels_written": int(tally[T_PASSED]), "pixels_covered": int(tally[T_COVERED])}


def raster_counters(tally: np.ndarray, triangles: int) -> dict[str, int]:
    """The rasterizer's pipeline statistics (:data:`RASTER_COUNTERS`) from its summed tallies: the clipper's input
    and output, 4 fragment shader invocations per 2x2 quad (``quad2x2``) and 16 per 4x4 block (``llvmpipe``) a
    (fan) triangle covers a centre of, samples passed and covered, pixels covered."""
    return {"clipping_input_primitives": int(triangles), "clipping_output_primitives": int(tally[T_CLIPPED]),
            "fragment_shader_invocations": 4 * int(tally[T_QUADS]),
            "fragment_shader_invocations_llvmpipe": 16 * int(tally[T_BLOCKS]),
            "samples_passed": int(tally[T_PASSED]), "samples_covered": int(tally[T_INSIDE]),
            "pixels_covered": int(tally[T_COVERED])}


def frame_counters(draw: dict[str, int], raster: dict[str, int]) -> dict[str, float | int]:
    """A frame's counters (:data:`PIPELINE_COUNTERS`, in that order): its draws' and its rasterizer's, with
    ``quad_efficiency`` = covered samples / (4 x 2x2 quads touched) (1: no quad shades a helper lane) and
    ``overdraw`` = samples passed / pixels covered (1: every pixel shaded once after early depth)."""
    out: dict[str, float | int] = {k: int(draw.get(k, 0)) for k in DRAW_COUNTERS}
    out.update({k: int(raster.get(k, 0)) for k in RASTER_COUNTERS})
    quads = out["fragment_shader_invocations"]
    out["quad_efficiency"] = out["samples_covered"] / quads if quads else 1.0
    out["overdraw"] = out["samples_passed"] / out["pixels_covered"] if out["pixels_covered"] else 1.0
    return out


def patch_draw_counters(patches: int, domain_points: int, triangles: int, texels_per_point: int) -> dict[str, int]:
    """The counters of one draw of ``patches`` quad patches (``GL_PATCHES`` of 4 control points) that the
    tessellator turns into ``domain_points`` evaluation shader invocations and ``triangles``; the evaluation
    shader fetches ``texels_per_point`` 4-byte heightmap texels (4 bilinear, 16 bicubic)."""
    return {"draw_calls": 1 if patches else 0, "vertices_submitted": 4 * patches, "primitives_submitted": patches,
            "vertex_shader_invocations": 4 * patches, "vertex_shader_invocations_llvmpipe": 4 * patches,
            "tess_control_shader_patches": patches,
            "tess_evaluation_shader_invocations": domain_points, "primitives_generated": triangles,
            "bytes_vertex": PATCH_RECORD_BYTES * patches, "bytes_index": 0,
            "bytes_heightmap": 4 * texels_per_point * domain_points}


@wp.kernel(enable_backward=False)
def _mark_kernel(
    offset: int,
    tris: wp.array2d(dtype=wp.int32),
    # outputs
    out_mark: wp.array(dtype=wp.uint8),
):
    """Flag the vertices triangle t references (plain stores of 1: the same whatever the order)."""
    t = wp.tid() + offset
    for k in range(3):
        out_mark[tris[t, k]] = wp.uint8(1)


@wp.kernel(enable_backward=False)
def _group_kernel(
    offset: int,
    groups: wp.array(dtype=wp.vec2i),
    draws: wp.array(dtype=wp.vec2i),
    tris: wp.array2d(dtype=wp.int32),
    # outputs
    out_stamp: wp.array(dtype=wp.int32),
    out_count: wp.array(dtype=wp.int64),
):
    """Per group of draws (``groups[g]`` = draws [first, stop), in order, one thread: draws of a group may share
    vertices, draws of different groups do not): each draw's distinct vertices, by stamping every vertex with
    the draw that counted it last (``out_stamp`` starts at -1)."""
    g = groups[wp.tid() + offset]
    for d in range(g[0], g[1]):
        r = draws[d]
        n = wp.int64(0)
        for t in range(r[0], r[1]):
            for k in range(3):
                v = tris[t, k]
                if out_stamp[v] != d:
                    out_stamp[v] = d
                    n += wp.int64(1)
        out_count[d] = n


@wp.kernel(enable_backward=False)
def _vsplit_kernel(
    offset: int,
    segments: wp.array(dtype=wp.vec2i),
    indices: wp.array(dtype=wp.int32),
    # outputs
    out_count: wp.array(dtype=wp.int32),
):
    """Per segment [first, stop) of the index list: the vertex shader invocations of Mesa's vertex splitter, one
    per index that misses its direct-mapped cache (slot ``index % VSPLIT_CACHE``, empty at the segment's start)."""
    k = wp.tid() + offset
    seg = segments[k]
    cache = vec_vsplit()
    for h in range(VSPLIT_CACHE):
        cache[h] = -1
    n = int(0)  # noqa: UP018 -- a mutable Warp int
    for i in range(seg[0], seg[1]):
        v = indices[i]
        h = v % VSPLIT_CACHE
        if cache[h] != v:
            cache[h] = v
            n += 1
    out_count[k] = n


def _llvmpipe_vertex_invocations(tri: np.ndarray, draws: np.ndarray | None, device: str) -> int:
    """llvmpipe's vertex shader invocations of the draws (:func:`_vsplit_kernel` over every draw's segments)."""
    m = len(tri)
    if not m:
        return 0
    d = np.array([[0, m]], np.int64) if draws is None else draws.astype(np.int64)
    first, count = 3 * d[:, 0], 3 * (d[:, 1] - d[:, 0])
    n_seg = -(-count // VSPLIT_SEGMENT)
    draw_of = np.repeat(np.arange(len(d)), n_seg)
    k = np.arange(len(draw_of)) - np.repeat(np.cumsum(n_seg) - n_seg, n_seg)
    a = first[draw_of] + k * VSPLIT_SEGMENT
    b = np.minimum(a + VSPLIT_SEGMENT, first[draw_of] + count[draw_of])
    segs = np.ascontiguousarray(np.stack([a, b], 1), np.int32)
    out = wp.empty(max(len(segs), 1), dtype=wp.int32, device=device)
    launch(_vsplit_kernel, len(segs), [wp.array(segs, dtype=wp.vec2i, device=device),
                                       wp.array(tri.reshape(-1), dtype=wp.int32, device=device)], [out], device,
           min_items=64)
    return int(out.numpy()[:len(segs)].astype(np.int64).sum())


def _distinct_per_draw(tri: np.ndarray, n_vertices: int, draws: np.ndarray | None, groups: np.ndarray | None,
                       device: str) -> int:
    """The sum over draws of the distinct vertices each references."""
    m = len(tri)
    if not m:
        return 0
    tri_wp = wp.array(tri, dtype=wp.int32, device=device)
    if groups is None:  # every draw's vertices its own: the vertices referenced at all
        mark = pooled_rows_array(n_vertices, wp.uint8, device)
        mark.zero_()
        launch(_mark_kernel, m, [tri_wp], [mark], device, min_items=_MIN_TRIANGLES)
        return int(np.count_nonzero(mark.numpy()))
    stamp = wp.full(n_vertices, value=-1, dtype=wp.int32, device=device)
    count = wp.zeros(len(draws), dtype=wp.int64, device=device)
    launch(_group_kernel, len(groups), [wp.array(groups, dtype=wp.vec2i, device=device),
                                        wp.array(draws, dtype=wp.vec2i, device=device), tri_wp],
           [stamp, count], device, min_items=1)
    return int(count.numpy().sum())


def indexed_draw_counters(triangles: np.ndarray, n_vertices: int, draws: np.ndarray | None = None, *,
                          groups: np.ndarray | None = None, vertex_invocations: int | None = None,
                          vertex_bytes: int = 12, texels_per_vertex: int = 0, device: str = "cpu") -> dict[str, int]:
    """The counters of indexed triangle draws.

    Args:
        triangles: (m, 3) int32 indices into ``n_vertices`` vertices.
        draws: (D, 2) int32 triangle ranges [first, stop), one draw call each (None: one draw of everything).
        groups: (G, 2) int32 draw ranges [first, stop) whose draws may share vertices (draws of different groups
            do not); None: no two draws share a vertex.
        vertex_invocations: the vertex shader invocations when the family knows them (its reference draws
            another vertex layout), instead of counting distinct vertices per draw.
        vertex_bytes: attribute bytes fetched per vertex shader invocation; texels_per_vertex: 4-byte heightmap
            texels the vertex shader fetches.

    Returns:
        draw_calls, vertices_submitted, primitives_submitted, vertex_shader_invocations (and llvmpipe's count,
        of the triangles in the order given), primitives_generated, the tessellation counters (0) and the bytes
        read. Deterministic.
    """
    tri = np.ascontiguousarray(triangles, np.int32).reshape(-1, 3)
    m = len(tri)
    d = None if draws is None else np.ascontiguousarray(draws, np.int32).reshape(-1, 2)
    n_draws = (1 if m else 0) if d is None else int(len(d))
    vs = _distinct_per_draw(tri, int(n_vertices), d, None if groups is None else
                            np.ascontiguousarray(groups, np.int32).reshape(-1, 2), device) \
        if vertex_invocations is None else int(vertex_invocations)
    return {"draw_calls": n_draws, "vertices_submitted": 3 * m, "primitives_submitted": m,
            "vertex_shader_invocations": vs,
            "vertex_shader_invocations_llvmpipe": _llvmpipe_vertex_invocations(tri, d, device),
            "tess_control_shader_patches": 0, "tess_evaluation_shader_invocations": 0,
            "primitives_generated": m, "bytes_vertex": vertex_bytes * vs, "bytes_index": INDEX_BYTES * 3 * m,
            "bytes_heightmap": 4 * texels_per_vertex * vs}

"""Pipeline statistics of the rasterizer and of the draws (kernels/raster.py with ``counters=True``,
kernels/counters.py): against references that draw one triangle at a time, against llvmpipe's
ARB_pipeline_statistics_query on the same clip-space vertices, and for any thread count."""

from __future__ import annotations

import gl_raster_oracle as gl  # noqa: E402
import numpy as np
import pytest

from terrainwarp.experiments.gl import GLMesh
from terrainwarp.kernels import pool
from terrainwarp.kernels.counters import frame_counters, indexed_draw_counters, patch_draw_counters
from terrainwarp.kernels.parallel import set_threads
from terrainwarp.kernels.raster import rasterize_clip

needs_gl = pytest.mark.skipif(not gl.available(), reason="no EGL / OpenGL 4.5 context (llvmpipe) on this machine")


def _triangles(seed: int, m: int, spread: float = 1.3, clipped: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Random overlapping triangles in clip space: (3m, 4) vertices, (m, 3) indices. With ``clipped`` some reach
    past the viewport and the near plane (w > 0 everywhere), some are exact copies of others (equal depths)."""
    rng = np.random.default_rng(seed)
    c = rng.uniform(-spread, spread, (m, 1, 2)) + rng.uniform(-0.35, 0.35, (m, 3, 2))
    if not clipped:
        c = np.clip(c, -0.99, 0.99)
    z = rng.uniform(-0.9, 0.9, (m, 1)) + rng.uniform(-0.1, 0.1, (m, 3))
    if clipped:
        z[rng.random(m) < 0.1, 0] = -1.6  # a vertex in front of the near plane
    w = rng.uniform(0.8, 1.5, (m, 3))
    clip = np.concatenate([c * w[..., None], (z * w)[..., None], w[..., None]], axis=2).astype(np.float32)
    tri = np.arange(3 * m, dtype=np.int32).reshape(m, 3)
    flip = rng.random(m) < 0.5  # both windings
    tri[flip] = tri[flip][:, ::-1]
    dup = rng.random(m) < 0.15  # copies of the triangle before, vertex order too: the same depths, GL_LESS fails
    dup[0] = False
    for t in np.flatnonzero(dup):
        clip[t] = clip[t - 1]
        tri[t] = tri[t - 1] + 3
    return clip.reshape(-1, 4), tri


def _sequential(clip: np.ndarray, tri: np.ndarray, width: int, height: int, device: str = "cpu") -> dict[str, int]:
    """The reference: one draw per triangle, the depth test (GL_LESS, cleared to 1.0) done here in submission
    order; the 2x2 quads and 4x4 blocks (window-aligned) each unclipped triangle covers."""
    zbuf = np.ones((height, width), np.float32)
    passed = quads = blocks = 0
    for t in range(len(tri)):
        f = rasterize_clip(clip, tri[t:t + 1], width, height, device=device)
        cov = f.triangle_id >= 0
        ok = cov & (f.depth < zbuf)
        passed += int(ok.sum())
        zbuf[ok] = f.depth[ok]
        win = cov[::-1]  # window rows, y up
        quads += int(win.reshape(height // 2, 2, width // 2, 2).any(axis=(1, 3)).sum())
        blocks += int(win.reshape(height // 4, 4, width // 4, 4).any(axis=(1, 3)).sum())
    return {"samples_passed": passed, "quads": quads, "blocks": blocks}


def test_samples_passed_is_the_depth_test_in_submission_order(device):
    clip, tri = _triangles(1, 300)
    f = rasterize_clip(clip, tri, 96, 64, counters=True, device=device)
    ref = _sequential(clip, tri, 96, 64, device=device)
    assert f.counters["samples_passed"] == ref["samples_passed"]
    # overdraw in draw order counts: more passed than covered, fewer than drawn
    assert f.counters["pixels_covered"] < f.counters["samples_passed"] < f.counters["samples_covered"]


def test_back_to_front_every_fragment_passes_and_front_to_back_only_the_first(device):
    w, h = 32, 16
    quad = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], np.float32)
    layers = 6
    clip = np.concatenate([np.c_[quad, np.full(4, z), np.ones(4)] for z in np.linspace(0.8, -0.8, layers)])
    tri = np.concatenate([np.array([[0, 1, 2], [0, 2, 3]]) + 4 * k for k in range(layers)]).astype(np.int32)
    back_to_front = rasterize_clip(clip.astype(np.float32), tri, w, h, counters=True, device=device).counters
    front_to_back = rasterize_clip(clip.astype(np.float32), tri[::-1].copy(), w, h, counters=True,
                                   device=device).counters
    assert back_to_front["samples_passed"] == layers * w * h
    assert front_to_back["samples_passed"] == w * h
    assert back_to_front["samples_covered"] == front_to_back["samples_covered"] == layers * w * h


def test_quads_and_blocks_match_one_triangle_at_a_time(device):
    clip, tri = _triangles(2, 200, clipped=False)
    f = rasterize_clip(clip, tri, 96, 64, counters=True, device=device)
    ref = _sequential(clip, tri, 96, 64, device=device)
    assert f.counters["fragment_shader_invocations"] == 4 * ref["quads"]
    assert f.counters["fragment_shader_invocations_llvmpipe"] == 16 * ref["blocks"]
    assert f.counters["clipping_output_primitives"] == len(tri)  # nothing to clip


def test_a_frame_that_outgrows_the_lists_room_is_binned_again_with_the_same_counters(device):
    sparse = _triangles(3, 20, spread=0.2)
    dense = _triangles(3, 400, spread=0.2)  # every triangle over the middle of a small viewport
    pool.release_buffers()  # no room kept: the first frame is counted, then binned
    rasterize_clip(*sparse, 64, 64, counters=True, device=device)  # leaves room for 20 triangles' lists
    f = rasterize_clip(*dense, 64, 64, counters=True, device=device)  # overflows it: binned again, exact room
    again = rasterize_clip(*dense, 64, 64, counters=True, device=device)  # now in the room from the start
    ref = _sequential(*dense, 64, 64, device=device)
    assert f.counters == again.counters
    assert f.counters["samples_passed"] == ref["samples_passed"]
    assert np.array_equal(f.triangle_id, again.triangle_id) and np.array_equal(f.depth, again.depth)


@pytest.mark.parametrize("threads", [2, 3, 8])
def test_counters_are_identical_for_any_thread_count(threads):
    clip, tri = _triangles(4, 5000, spread=1.1)
    try:
        set_threads(1)
        one = rasterize_clip(clip, tri, 320, 200, counters=True)
        set_threads(threads)
        many = rasterize_clip(clip, tri, 320, 200, counters=True)
    finally:
        set_threads(None)
    assert one.counters == many.counters
    plain = rasterize_clip(clip, tri, 320, 200)
    assert plain.counters is None  # nothing counted unless asked
    with pytest.raises(TypeError, match="counters"):
        rasterize_clip(clip, tri, 32, 20, counters="yes")
    assert np.array_equal(plain.triangle_id, many.triangle_id) and np.array_equal(plain.depth, many.depth)


@needs_gl
def test_counters_equal_llvmpipes_query_on_random_triangles():
    clip, tri = _triangles(5, 3000, spread=1.2)
    ours = rasterize_clip(clip, tri, 200, 120, counters=True).counters
    g = GLMesh(200, 120)
    try:
        up = g.upload(clip, tri)
        _, _, _, _, got = g.draw(up, counters=True)
        g.release(up)
    finally:
        g.close()
    for name in ("clipping_input_primitives", "clipping_output_primitives", "samples_passed"):
        assert ours[name] == got[name], name
    assert ours["fragment_shader_invocations_llvmpipe"] == got["fragment_shader_invocations"]
    assert ours["clipping_output_primitives"] != len(tri)  # some were rejected or clipped


@needs_gl
def test_culled_clipped_triangles_leave_the_clipper_as_llvmpipe_counts_them():
    """With back faces culled, llvmpipe culls a triangle it must clip before the clipper (homogeneous
    orientation, any w), one it need not clip after (in triangle setup). Drawn one at a time: in a draw where
    some triangle needs clipping llvmpipe sends the whole vertex batch through its clipping pipeline and culls
    the unclipped back faces there too, a batching detail our count does not follow."""
    rng = np.random.default_rng(6)
    g = GLMesh(64, 64)
    try:
        for _ in range(120):
            c = rng.uniform(-2, 2, (3, 4)).astype(np.float32)
            c[:, 3] = rng.uniform(-1, 2, 3) if rng.random() < 0.5 else rng.uniform(0.1, 2, 3)
            t = np.array([[0, 1, 2]], np.int32)
            up = g.upload(c, t)
            _, _, _, _, got = g.draw(up, cull_back=True, counters=True)
            g.release(up)
            ours = rasterize_clip(c, t, 64, 64, cull_back=True, counters=True).counters
            assert ours["clipping_output_primitives"] == got["clipping_output_primitives"], c
    finally:
        g.close()


def test_draw_counters(device):
    p = patch_draw_counters(10, 900, 1500, 4)
    assert (p["vertices_submitted"], p["tess_control_shader_patches"], p["tess_evaluation_shader_invocations"],
            p["primitives_generated"], p["draw_calls"], p["bytes_heightmap"]) == (40, 10, 900, 1500, 1, 900 * 16)
    # two quads sharing an edge: one draw references 6 vertices, two draws (a group) reference 4 each
    tri = np.array([[0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4]], np.int32)
    one = indexed_draw_counters(tri, 7, device=device)
    assert (one["draw_calls"], one["vertex_shader_invocations"], one["vertices_submitted"]) == (1, 6, 12)
    two = indexed_draw_counters(tri, 7, np.array([[0, 2], [2, 4]]), groups=np.array([[0, 2]]), device=device)
    assert (two["draw_calls"], two["vertex_shader_invocations"], two["bytes_index"]) == (2, 8, 48)
    assert indexed_draw_counters(tri, 7, vertex_invocations=5, vertex_bytes=8, device=device)["bytes_vertex"] == 40
    c = frame_counters(two, {"samples_covered": 30, "fragment_shader_invocations": 40, "samples_passed": 25,
                             "pixels_covered": 20})
    assert c["quad_efficiency"] == 0.75 and c["overdraw"] == 1.25
    assert indexed_draw_counters(np.zeros((0, 3), np.int32), 0, device=device)["draw_calls"] == 0

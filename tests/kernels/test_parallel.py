"""The parallel-launch helper (kernels/parallel.py): every output is bit-identical for 1, 2, 3 and 8 threads.

Each launch is split as finely as the thread count allows (``set_min_items(1)``), so small scenes exercise
the chunk borders; 8 threads on a 2-core machine only oversubscribe. Run as a script, this file prints the
digests (``.venv/bin/python tests/kernels/test_parallel.py``), to compare two versions of the code.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import warp as wp

import terrainwarp as tw
from terrainwarp.io.files import digest
from terrainwarp.kernels import parallel
from terrainwarp.kernels.noise import fbm
from terrainwarp.kernels.tessellator import tessellate_domains

THREADS = (1, 2, 3, 8)


def _error_digest(err) -> str:
    row = err.row()
    return digest(np.array([float("nan") if row[k] is None else row[k] for k in sorted(row)], np.float64))


def _frame_digests(frame, name: str) -> dict[str, str]:
    out = {f"{name}.image": digest(frame.image), f"{name}.depth": digest(frame.depth),
           f"{name}.triangle_id": digest(frame.triangle_id),
           f"{name}.mesh": digest(frame.mesh.positions, frame.mesh.triangles, frame.mesh.uv)}
    if frame.error is not None:
        out[f"{name}.error"] = _error_digest(frame.error)
    if frame.normals is not None:
        out[f"{name}.normals"] = digest(frame.normals)
    return out


def digests() -> dict[str, str]:
    """Digests of a small LOD frame (select, tessellate, displace, raster, shade, error), a grid frame, the
    frame tessellator alone, normals and curvature by every method, and an fBm window."""
    hm = tw.Heightmap.example()
    cam = tw.Camera.default_for(hm, 160, 120)
    out: dict[str, str] = {}
    lod = tw.LodConfig(tolerance_px=2.0, roots=4, tess=16, spacing="fractional_even")
    out |= _frame_digests(tw.render(tw.Scene(hm, camera=cam, mesh="lod", lod=lod,
                                             outputs=("image", "depth", "error", "mesh"))), "lod")
    out |= _frame_digests(tw.render(tw.Scene(hm, camera=cam, outputs=("image", "depth", "normals", "mesh"))),
                          "grid")
    rng = np.random.default_rng(3)
    t = tessellate_domains(rng.uniform(1, 40, (300, 4)).astype(np.float32),
                           rng.uniform(1, 40, (300, 2)).astype(np.float32), "fractional_even")
    out["tessellate"] = digest(t["uv"], t["patch_id"], t["triangles"], t["vertex_offsets"], t["triangle_offsets"])
    for m in ("sobel", "edge", "triangle", "quad"):
        out[f"normals.{m}"] = digest(tw.compute_normals(hm, m))
    for m in ("two_normal", "three_normal", "three_vertex", "edge_angle"):
        out[f"curvature.{m}"] = digest(tw.compute_curvature(hm, m))
    out["fbm"] = digest(fbm(97, 65, seed=5, row0=1000, col0=-300))
    return out


@pytest.fixture(scope="module")
def by_threads():
    got = {}
    try:
        parallel.set_min_items(1)
        for n in THREADS:
            tw.set_threads(n)
            got[n] = digests()
    finally:
        parallel.set_min_items(None)
        tw.set_threads(None)
    return got


@pytest.mark.parametrize("n", THREADS[1:])
def test_outputs_identical_for_any_thread_count(by_threads, n):
    one = by_threads[1]
    differ = sorted(k for k in one if by_threads[n][k] != one[k])
    assert not differ, f"{n} threads: differ from 1 thread in {differ}"
    assert set(by_threads[n]) == set(one)


def test_chunks_cover_the_range_in_order():
    try:
        tw.set_threads(3)
        assert parallel.chunks(10, min_items=1) == [(0, 4), (4, 8), (8, 10)]
        assert parallel.chunks(10, min_items=1, oversplit=2) == [(0, 2), (2, 4), (4, 6), (6, 8), (8, 10)]
        assert parallel.chunks(2, min_items=1) == [(0, 1), (1, 2)]
        assert parallel.chunks(100, min_items=4096) == [(0, 100)]  # too little work to split
        assert parallel.chunks(0) == []
    finally:
        tw.set_threads(None)


@wp.kernel(enable_backward=False)
def _probe_kernel(offset: int, part: int, out_part: wp.array2d(dtype=wp.int32)):
    i, j = wp.tid()
    out_part[i + offset, j] = part * 1000 + i + offset


def test_launch_gives_each_chunk_its_offset_and_part():
    out = wp.full((9, 2), value=-1, dtype=wp.int32)
    try:
        tw.set_threads(3)
        parallel.launch(_probe_kernel, (9, 2), [], [out], "cpu", parts=True, min_items=1)
    finally:
        tw.set_threads(None)
    got = out.numpy()
    assert np.array_equal(got % 1000, np.repeat(np.arange(9), 2).reshape(9, 2))
    assert np.array_equal(got // 1000, np.repeat([0, 0, 0, 1, 1, 1, 2, 2, 2], 2).reshape(9, 2))


def test_set_threads_validates():
    for bad, err in ((0, ValueError), (-2, ValueError), (1.5, TypeError), (True, TypeError), ("2", TypeError)):
        with pytest.raises(err, match="n: expected"):
            tw.set_threads(bad)


def test_thread_count_from_environment():
    code = "import terrainwarp as tw; from terrainwarp.kernels import parallel; print(parallel.threads())"
    env = dict(os.environ, TERRAINWARP_THREADS="3")
    got = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert got.stdout.split()[-1] == "3"
    env["TERRAINWARP_THREADS"] = "zero"
    bad = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert bad.returncode != 0 and "TERRAINWARP_THREADS: expected a positive integer" in bad.stderr


def test_default_is_the_cores_this_process_may_use():
    if os.environ.get(parallel.THREADS_ENV):
        pytest.skip("TERRAINWARP_THREADS is set")
    assert parallel.threads() == len(os.sched_getaffinity(0))


_FRAME_MEMORY = """
import resource, sys, numpy as np
import terrainwarp
from terrainwarp.kernels import parallel
def frame():  # three 24 MiB outputs, written, then dropped, as a frame's images and vertices are
    blocks = [np.empty(24 << 20, np.uint8) for _ in range(3)]
    for b in blocks:
        b.fill(1)
faults = []
for _ in range(3):
    r0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    frame()
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - r0)
print(parallel.keep_frame_memory(), faults[-1])
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt: Linux only")
def test_freed_frame_memory_is_reused_without_page_faults():
    got = subprocess.run([sys.executable, "-c", _FRAME_MEMORY], capture_output=True, text=True, check=True)
    kept, faults = got.stdout.split()
    assert kept == "True"
    assert int(faults) < 100  # 72 MiB written again: ~18,000 4 KiB pages if they went back to the kernel
    env = dict(os.environ, TERRAINWARP_KEEP_MEMORY="0")
    off = subprocess.run([sys.executable, "-c", _FRAME_MEMORY], env=env, capture_output=True, text=True, check=True)
    assert off.stdout.split()[0] == "False"  # the opt-out leaves glibc's defaults alone


if __name__ == "__main__":
    print(json.dumps(digests(), indent=1, sort_keys=True))


def test_pooled_buffers_are_reused_only_once_nothing_holds_them():
    shape = (123, 7)
    a = parallel.pooled(shape, np.float64)
    addr = a.ctypes.data
    b = parallel.pooled(shape, np.float64)  # a is held: another buffer
    assert b.ctypes.data != addr
    view_of_a = a[3:5]
    del a
    c = parallel.pooled(shape, np.float64)
    assert c.ctypes.data != addr  # a view of a keeps it
    del view_of_a, b, c
    assert parallel.pooled(shape, np.float64).ctypes.data == addr  # nothing holds it: taken again
    w = parallel.pooled_array(shape, wp.float32, "cpu")
    held = w.numpy()  # the caller's numpy result holds the pooled buffer through the Warp array
    del w
    assert parallel.pooled_array(shape, wp.float32, "cpu").ptr != held.ctypes.data
    held[...] = 1.5
    assert parallel.release_buffers() >= 123 * 7 * 8 and parallel.release_buffers() == 0
    assert (held == 1.5).all()  # a held buffer stays with its holder


def test_pooled_rows_serve_frames_of_changing_length_and_never_a_held_one():
    """A tessellation's outputs change length every frame: a kept buffer with enough rows serves a shorter
    frame (the smallest such), a longer one gets a new buffer (up to 1/64 more rows) that takes the place of
    the smallest free one, and a buffer a caller holds (through a view or a Warp array) is never handed out."""
    parallel.release_buffers()
    a = parallel.pooled_rows((1000, 3), np.int32)
    assert a.shape == (1000, 3) and 1000 <= a.base.shape[0] <= 1000 * 65 // 64
    base = a.base.ctypes.data
    del a
    b = parallel.pooled_rows((900, 3), np.int32)  # shorter: the same buffer
    assert b.base.ctypes.data == base and b.shape == (900, 3)
    c = parallel.pooled_rows((800, 3), np.int32)  # b holds it: a second buffer
    assert c.base.ctypes.data != base
    del b, c
    big = parallel.pooled_rows((5000, 3), np.int32)  # longer: new, replaces the smallest free kept one
    kept = parallel._POOL[("rows", (3,), np.dtype(np.int32).str)]
    assert len(kept) == 2 and any(k is big.base for k in kept)
    w = parallel.pooled_rows_array(4000, wp.vec3i, "cpu")  # 4000 rows fit the big one, but big is held
    assert w.ptr != big.ctypes.data  # a new one, in place of the free 1000-row buffer
    held, w_ptr, big_ptr = big.copy(), w.ptr, big.ctypes.data
    del big, w
    again = parallel.pooled_rows((4000, 3), np.int32)
    assert again.ctypes.data == w_ptr  # the smallest free buffer with enough rows
    assert parallel.pooled_rows((4500, 3), np.int32).ctypes.data == big_ptr
    assert parallel.release_buffers() > 0 and held.shape == (5000, 3)

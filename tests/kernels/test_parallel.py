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
import threading
import time

import numpy as np
import pytest
import warp as wp

import terrainwarp as tw
from terrainwarp.io.files import digest
from terrainwarp.kernels import parallel, pool
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
            tw.kernels.parallel.set_threads(n)
            got[n] = digests()
    finally:
        parallel.set_min_items(None)
        tw.kernels.parallel.set_threads(None)
    return got


@pytest.mark.parametrize("n", THREADS[1:])
def test_outputs_identical_for_any_thread_count(by_threads, n):
    one = by_threads[1]
    differ = sorted(k for k in one if by_threads[n][k] != one[k])
    assert not differ, f"{n} threads: differ from 1 thread in {differ}"
    assert set(by_threads[n]) == set(one)


def test_chunks_cover_the_range_in_order():
    try:
        tw.kernels.parallel.set_threads(3)
        assert parallel.chunks(10, min_items=1) == [(0, 4), (4, 8), (8, 10)]
        assert parallel.chunks(10, min_items=1, oversplit=2) == [(0, 2), (2, 4), (4, 6), (6, 8), (8, 10)]
        assert parallel.chunks(2, min_items=1) == [(0, 1), (1, 2)]
        assert parallel.chunks(100, min_items=4096) == [(0, 100)]  # too little work to split
        assert parallel.chunks(0) == []
    finally:
        tw.kernels.parallel.set_threads(None)


@wp.kernel(enable_backward=False)
def _probe_kernel(offset: int, part: int, out_part: wp.array2d(dtype=wp.int32)):
    i, j = wp.tid()
    out_part[i + offset, j] = part * 1000 + i + offset


def test_launch_gives_each_chunk_its_offset_and_part():
    out = wp.full((9, 2), value=-1, dtype=wp.int32)
    try:
        tw.kernels.parallel.set_threads(3)
        parallel.launch(_probe_kernel, (9, 2), [], [out], "cpu", parts=True, min_items=1)
    finally:
        tw.kernels.parallel.set_threads(None)
    got = out.numpy()
    assert np.array_equal(got % 1000, np.repeat(np.arange(9), 2).reshape(9, 2))
    assert np.array_equal(got // 1000, np.repeat([0, 0, 0, 1, 1, 1, 2, 2, 2], 2).reshape(9, 2))


@wp.kernel(enable_backward=False)
def _spin_kernel(offset: int, n: int, out: wp.array(dtype=wp.float32)):
    i = wp.tid() + offset
    acc = float(0.0)  # noqa: UP018 -- a mutable Warp float
    for k in range(n):
        acc = acc + wp.sin(float(i + k))
    out[i] = acc


def test_the_kernel_clock_counts_launches_of_its_thread_and_nests():
    out = wp.zeros(64, dtype=wp.float32)
    parallel.launch_one(_spin_kernel, 64, [0, 10], [out])  # loaded
    t0 = time.perf_counter()
    with parallel.kernel_clock() as outer:
        sum(range(200_000))  # host work: not on the clock
        with parallel.kernel_clock() as inner:
            parallel.launch(_spin_kernel, 64, [20_000], [out], min_items=1)
            parallel.launch_one(_spin_kernel, 64, [0, 20_000], [out])
            cmd = parallel.record(_spin_kernel, 64, [0, 20_000], [out])
            parallel.replay(cmd)
        seen = []
        other = threading.Thread(target=lambda: seen.append(parallel.launch_one(_spin_kernel, 64, [0, 20_000], [out])))
        other.start()
        other.join()  # another thread's launch is not this thread's
    assert 0 < inner[0] <= outer[0] and outer[0] == pytest.approx(inner[0])  # the other thread's launch left out
    assert outer[0] < time.perf_counter() - t0
    with parallel.kernel_clock() as idle:
        sum(range(100_000))
    assert idle[0] == 0.0


def test_threads_that_start_together_load_a_module_once_and_one_at_a_time():
    """Eight threads ask for the same new module and two others at once: each is loaded once, never two loads at
    the same time (CPython 3.11's ast cannot parse from two threads at once: four threads rendering a new module
    died with 'AST constructor recursion depth mismatch'), and on the CPU for block_dim 1, the build wp.launch runs
    there (the module's default, 256, was compiled too and never run)."""
    inside, most, loads = [0], [0], []
    guard = threading.Lock()

    class Module:
        def load(self, device, block_dim=None):
            with guard:
                inside[0] += 1
                most[0] = max(most[0], inside[0])
            time.sleep(0.02)
            loads.append((self, str(device), block_dim))
            with guard:
                inside[0] -= 1

    class Kernel:
        def __init__(self, module):
            self.module = module

    mods = [Module(), Module(), Module()]
    start = threading.Barrier(8)

    def work(t: int) -> None:
        start.wait()
        parallel.load(Kernel(mods[0]), "cpu")
        parallel.load(Kernel(mods[1 + t % 2]), "cpu")

    ths = [threading.Thread(target=work, args=(t,)) for t in range(8)]
    for th in ths:
        th.start()
    for th in ths:
        th.join()
    assert most[0] == 1 and sorted(id(m) for m, _, _ in loads) == sorted(id(m) for m in mods)
    assert all(b == 1 for _, _, b in loads)


def test_a_module_is_built_once_for_the_block_size_its_launches_use():
    """parallel.load loaded Warp's default variant (block_dim 256) and wp.launch on the CPU then built a second
    (block_dim 1): every module compiled twice on a first run. Now only the launched variant is loaded."""
    from terrainwarp.kernels import noise

    tw.Heightmap.fbm(9, seed=3)
    dims = {dim for (_, dim) in noise._fbm_kernel.module.execs}
    assert dims == {1}


def test_set_threads_validates():
    for bad, err in ((0, ValueError), (-2, ValueError), (1.5, TypeError), (True, TypeError), ("2", TypeError)):
        with pytest.raises(err, match="n: expected"):
            tw.kernels.parallel.set_threads(bad)


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
if sys.argv[1] != "-":
    print(terrainwarp.configure(keep_memory=sys.argv[1] == "on").keep_memory)
else:
    print("unset")
def frame():  # three 24 MiB outputs, written, then dropped, as a frame's images and vertices are
    blocks = [np.empty(24 << 20, np.uint8) for _ in range(3)]
    for b in blocks:
        b.fill(1)
faults = []
for _ in range(3):
    r0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    frame()
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - r0)
print(faults[-1])
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt: Linux only")
def test_freed_frame_memory_is_reused_without_page_faults_when_asked():
    def run(arg):
        got = subprocess.run([sys.executable, "-c", _FRAME_MEMORY, arg], capture_output=True, text=True, check=True)
        return got.stdout.split()

    kept, faults = run("on")
    assert kept == "True" and int(faults) < 100  # 72 MiB written again: ~18,000 4 KiB pages if given back
    assert run("off")[0] == "False"  # (that import alone calls no mallopt: tests/core/test_runtime.py)


_FORK = """
import os, sys, numpy as np
import terrainwarp as tw
tw.configure(threads=2)
h = np.random.default_rng(0).normal(size=(64, 64)).astype(np.float32)
want = tw.compute_normals(tw.Heightmap.from_array(h, 1.0, 1.0), "sobel")  # the pool's threads exist now
pid = os.fork()
if pid == 0:  # the child: no pool threads; a launch split across threads still works and gives the same bits
    got = tw.compute_normals(tw.Heightmap.from_array(h, 1.0, 1.0), "sobel")
    os._exit(0 if np.array_equal(got, want) else 3)
print(os.waitpid(pid, 0)[1] >> 8)
"""


def test_pool_and_thread_count_start_afresh_in_a_forked_child():
    """No fork handler: a forked child notices the new process on use and starts its own launch threads (a
    fresh interpreter: this one has JAX's threads, which fork must not meet)."""
    got = subprocess.run([sys.executable, "-c", _FORK], capture_output=True, text=True, timeout=300)
    assert got.returncode == 0 and got.stdout.split()[-1] == "0", got.stderr


if __name__ == "__main__":
    print(json.dumps(digests(), indent=1, sort_keys=True))


def test_pooled_buffers_are_reused_only_once_their_lease_has_ended():
    pool.release_buffers()
    shape = (123, 7)
    a = pool.pooled(shape, np.float64)
    addr = a.ctypes.data
    assert isinstance(a.base, pool.Lease)
    b = pool.pooled(shape, np.float64)  # a is held: another buffer
    assert b.ctypes.data != addr
    view_of_a = a[3:5]
    del a
    c = pool.pooled(shape, np.float64)
    assert c.ctypes.data != addr  # a view of a keeps its lease
    del view_of_a, b, c
    assert pool.pooled(shape, np.float64).ctypes.data == addr  # the lease ended: lent again
    w = pool.pooled_array(shape, wp.float32, "cpu")
    held = w.numpy()  # the caller's numpy result holds the lease through the Warp array
    sliced = pool.pooled_array(shape, wp.float32, "cpu")[2:]  # a Warp view of a Warp array holds it too
    del w
    assert pool.pooled_array(shape, wp.float32, "cpu").ptr not in (held.ctypes.data, sliced.ptr - 2 * 7 * 4)
    held[...] = 1.5
    assert pool.release_buffers() >= 123 * 7 * 8 and pool.release_buffers() == 0
    assert (held == 1.5).all()  # a held buffer stays with its holder
    del held, sliced
    assert pool.kept_bytes()["free_buffers"] == 0  # leases taken before release_buffers() end without coming back


def test_pooled_rows_serve_frames_of_changing_length_and_never_a_held_one():
    """A tessellation's outputs change length every frame: a kept buffer with enough rows serves a shorter
    frame (the smallest such), a longer one gets a new buffer (up to 1/64 more rows) that takes the place of
    the smallest free one, and a buffer a caller holds (through a view or a Warp array) is never handed out."""
    pool.release_buffers()
    a = pool.pooled_rows((1000, 3), np.int32)
    assert a.shape == (1000, 3) and 1000 <= a.base.buffer.shape[0] <= 1000 * 65 // 64
    base = a.ctypes.data
    del a
    b = pool.pooled_rows((900, 3), np.int32)  # shorter: the same buffer
    assert b.ctypes.data == base and b.shape == (900, 3)
    c = pool.pooled_rows((800, 3), np.int32)  # b holds it: a second buffer
    assert c.ctypes.data != base
    del b, c
    big = pool.pooled_rows((5000, 3), np.int32)  # longer: new, replaces the smallest free kept one
    assert pool.kept_bytes()["free_buffers"] == 1 and pool.kept_bytes()["leased_buffers"] == 1
    w = pool.pooled_rows_array(4000, wp.vec3i, "cpu")  # 4000 rows fit the big one, but big is held
    assert w.ptr != big.ctypes.data  # a new one, in place of the free 1000-row buffer
    held, w_ptr, big_ptr = big.copy(), w.ptr, big.ctypes.data
    del big, w
    again = pool.pooled_rows((4000, 3), np.int32)
    assert again.ctypes.data == w_ptr  # the smallest free buffer with enough rows
    assert pool.pooled_rows((4500, 3), np.int32).ctypes.data == big_ptr
    assert pool.release_buffers() > 0 and held.shape == (5000, 3)


def test_a_scratch_lease_comes_back_only_when_given_back():
    pool.release_buffers()
    made = []

    def make():
        made.append(np.zeros(16, np.uint8))
        return made[-1]

    one = pool.take(("t", 16), make)
    one.buffer[:] = 7
    one.give_back()
    one.give_back()  # once only
    two = pool.take(("t", 16), make)
    assert two.buffer is made[0] and len(made) == 1 and (two.buffer == 7).all()  # as the last holder left it
    del two  # dropped, not given back (its function failed part-way): the buffer goes with it
    three = pool.take(("t", 16), make)
    assert three.buffer is made[1]


def test_leases_under_threads_never_lend_a_held_buffer():
    """Eight threads take output leases of one kind, write their own mark, hold some, drop the rest; a buffer
    still held is never lent to another thread (its mark survives), and dropped ones are lent again."""
    pool.release_buffers()
    errors, addrs = [], set()
    lock = threading.Lock()

    def work(t: int) -> None:
        held = []
        for i in range(300):
            a = pool.pooled((64, 64), np.float32, keep=4)
            a.fill(t * 1000 + i)
            with lock:
                addrs.add(a.ctypes.data)
            if i % 7 == 0:
                held.append((a, float(t * 1000 + i)))
            for h, mark in held:
                if not (h == mark).all():
                    errors.append((t, i))
            if len(held) > 3:
                held.pop(0)

    threads = [threading.Thread(target=work, args=(t,)) for t in range(8)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert not errors
    assert pool.kept_bytes()["leased_buffers"] == 0  # every lease ended when its last holder let go
    assert len(addrs) < 8 * 300 // 4  # buffers were lent again (4 kept; the rest are plain allocations)


def test_frames_rendered_and_held_by_threads_keep_their_bits():
    """Four threads render frames of one scene and hold every other one; a held frame is never written by a
    later one (the pool lends only buffers whose lease has ended), and every frame has the serial bits."""
    hm = tw.Heightmap.fbm(65, seed=4)
    sc = tw.Scene(hm, camera=tw.Camera.default_for(hm, 96, 64), mesh="lod", outputs=("image", "depth"))
    want = digest(*(lambda f: (f.image, f.depth))(tw.render(sc)))
    bad = []

    def work() -> None:
        held = []
        for i in range(6):
            f = tw.render(sc)
            if i % 2 == 0:
                held.append(f)
            bad.extend(1 for h in held if digest(h.image, h.depth) != want)

    threads = [threading.Thread(target=work) for _ in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert not bad




def test_pooled_arrays_share_one_lease_that_ends_with_the_last_of_them():
    """A call's outputs carved from one kept buffer: each aligned, none overlapping, and the buffer lent again only
    once every one of them (or a view of it) is dropped; a buffer of another tag is never lent for it."""
    pool.release_buffers()
    pos, tri = pool.pooled_arrays([(100, wp.vec3), (37, wp.vec3i)], "cpu", tag="t")
    assert pos.shape == (100,) and tri.shape == (37,) and pos.dtype == wp.vec3 and tri.dtype == wp.vec3i
    assert pos.ptr % pool.BLOCK_ALIGN == tri.ptr % pool.BLOCK_ALIGN and tri.ptr >= pos.ptr + 100 * 12
    base = pos.ptr
    held = tri.numpy()
    del pos, tri
    assert pool.pooled_arrays([(100, wp.vec3)], "cpu", tag="t")[0].ptr != base  # held through tri's numpy view
    del held
    assert pool.pooled_arrays([(10, wp.vec3)], "cpu", tag="other")[0].ptr != base  # free, but of another tag
    again = pool.pooled_arrays([(90, wp.vec3), (30, wp.vec3i)], "cpu", tag="t")
    assert again[0].ptr == base  # every array dropped: the buffer is lent again
    assert pool.release_buffers() > 0

"""The report sweep on dask.distributed: speed-up with 1 and 2 worker processes on this 2-core machine,
identical results with 4 (oversubscribed), and the bytes sent per job.

    python benchmarks/bench_sweep.py [--quick]

200 jobs: 20 settings (grid, sse, distance, continuous, Martini, Delatin) x 10 cameras of an orbit, at
160x120 pixels on a 257x257 fractal terrain. Each cluster is started and warmed up first (its workers import
terrainwarp and load the Warp kernels from the cache) so the timed sweep measures the jobs, the reference
frames (one per camera, also jobs) and the scatter of the shared inputs, not process start-up.
"""

from __future__ import annotations

import argparse
import os
import time

from _common import md_table, write_result

from terrainwarp import Camera, Heightmap, Scene
from terrainwarp.report import TIMING_COLUMNS, Setting, _Context, rows_to_csv, run_sweep
from terrainwarp.sweep import Runner, _nbytes, close_local_clusters


def settings() -> list[Setting]:
    s = [Setting("grid", 0.0)]
    s += [Setting("sse", v) for v in (0.5, 1.0, 2.0, 4.0, 8.0, 16.0)]
    s += [Setting("distance", v) for v in (8.0, 4.0, 2.0, 1.0)]
    s += [Setting("continuous", v) for v in (2.0, 4.0, 8.0, 16.0)]
    s += [Setting("martini", v) for v in (1.0, 8.0)] + [Setting("delatin", v) for v in (0.5, 2.0, 8.0)]
    return s


def _cpu_s() -> float:
    import psutil

    t = psutil.Process().cpu_times()
    return t.user + t.system


def cpu_seconds(runner: Runner) -> float:
    """CPU seconds used so far by this process (client + scheduler) and the worker processes."""
    own = _cpu_s()
    if runner.client is None:
        return own
    return own + sum(runner.client.run(_cpu_s).values())


def table(rows) -> str:
    return rows_to_csv([{k: v for k, v in r.items() if k not in (*TIMING_COLUMNS, "retries")} for r in rows])


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="4 cameras, 64x48 (a smoke run)")
    a = ap.parse_args(argv)
    n_cams, (w, h) = (4, (64, 48)) if a.quick else (10, (160, 120))
    hm = Heightmap.fbm(257, seed=4, dx=10.0, max_height=300.0)
    sc = Scene(hm, camera=Camera.default_for(hm, w, h), name="fbm257")
    cams = sc.camera_path(n_cams)
    st = settings()
    n_jobs = len(st) * n_cams

    results = {}
    lines = []
    for workers in (0, 1, 2, 4):
        t0 = time.perf_counter()
        runner = Runner(workers=workers)
        t_start = time.perf_counter() - t0
        t0 = time.perf_counter()
        run_sweep(sc, cams[:1], st, runner=runner, progress=False)  # warm-up: imports, every kernel's load
        t_warm = time.perf_counter() - t0
        runner.bytes_shared = 0
        c0 = cpu_seconds(runner)
        t0 = time.perf_counter()
        res = run_sweep(sc, cams, st, runner=runner, progress=False)
        wall = time.perf_counter() - t0
        cpu = cpu_seconds(runner) - c0
        results[workers] = res
        frame_ms = sum(r["frame_ms"] for r in res.rows) / len(res.rows)
        lines.append((workers, res, wall, t_start, t_warm, frame_ms, os.getloadavg()[0], cpu))
        print(f"workers={workers}: {wall:.1f} s, {res.summary()}", flush=True)
        if workers:
            close_local_clusters()

    base = results[1]
    ref_table = table(base.rows)
    rows = []
    for workers, res, wall, t_start, t_warm, frame_ms, load, cpu in lines:
        t1 = next(x[2] for x in lines if x[0] == 1)
        rows.append(["in-process (no Dask)" if workers == 0 else str(workers), res.n_jobs, res.n_failed,
                     f"{t_start:.1f}", f"{t_warm:.1f}", f"{wall:.1f}", f"{res.n_jobs / wall:.1f}",
                     f"{t1 / wall:.2f}", f"{cpu:.1f}", f"{cpu / wall:.2f}", f"{frame_ms:.1f}",
                     "yes" if table(res.rows) == ref_table else "NO", f"{load:.1f}"])
    two = results[2]
    ctx_bytes = _nbytes(_Context("x" * 32, sc, tuple(cams), True, "cpu", True))
    refs_bytes = two.bytes_shared / two.workers - ctx_bytes
    per_job = two.bytes_jobs / two.n_run
    naive = per_job + ctx_bytes + refs_bytes / n_cams  # scene in every job + its camera's reference
    body = [
        f"{n_jobs} jobs = {len(st)} settings x {n_cams} cameras at {w}x{h}, heightmap {hm.shape[0]}x{hm.shape[1]} "
        f"(fbm), plus {n_cams} reference-frame jobs. One single-threaded worker process per worker "
        "(LocalCluster(processes=True, threads_per_worker=1)); this machine has "
        f"{os.cpu_count()} cores and is shared (1-min load average at the end of each run in the last column).",
        "",
        md_table(["workers", "jobs", "failed", "cluster start s", "warm-up s", "sweep s", "jobs/s",
                  "speed-up vs 1", "cpu s", "cores busy",
                  "mean frame_ms", "table = 1 worker's", "load"], rows),
        "",
        "`table = 1 worker's`: every column but timings (" + ", ".join(TIMING_COLUMNS) + ") and `retries`, "
        "as CSV text, equals the 1-worker table. `mean frame_ms` is the per-frame cost measured inside the "
        "workers: with 4 processes on 2 cores each frame takes longer, the table stays the same. `cpu s`: CPU "
        "time of this process (client and scheduler) and the workers during the sweep; `cores busy` = cpu s / "
        "sweep s, how much of the machine the sweep got (other processes share it: see the load average).",
        "",
        "## Bytes sent (2 workers)",
        "",
        md_table(["what", "bytes"], [
            ["shared inputs, once per worker (scene with heightmap, cameras; reference frames)",
             f"{two.bytes_shared / two.workers:,.0f} per worker, {two.bytes_shared:,.0f} in all"],
            ["  of which scene + cameras", f"{ctx_bytes:,}"],
            ["  of which reference frames (all cameras)", f"{refs_bytes:,.0f}"],
            ["per job: function + (setting, camera index)", f"{per_job:,.0f}"],
            ["per job, shared inputs spread over the jobs", f"{two.bytes_per_job:,.0f}"],
            ["per job if the scene and the camera's reference went with every job", f"{naive:,.0f}"],
            ["per job, the row sent back", f"{two.bytes_results / two.n_run:,.0f}"],
        ]),
        "",
        "Sizes are cloudpickle (protocol 5) sizes of what the client hands to Dask; the shared inputs are sent with "
        "`client.scatter(..., broadcast=True)` and each job receives them as a future, so a job's own payload "
        "is its setting and camera index.",
    ]
    write_result("sweep", "Sweeps on dask.distributed: speed-up, oversubscription, bytes per job", "\n".join(body))


if __name__ == "__main__":
    main()

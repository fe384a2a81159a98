"""The sweep runner (terrainwarp.experiments.runner) on real dask.distributed LocalClusters of worker processes.

One LocalCluster is kept per size and reused (terrainwarp.experiments.runner caches it); the tests that need a second
size run first, so the module starts two clusters in all.
"""

import csv
import io
import os
import random
import signal
import socket
import sys
import time
from pathlib import Path

import cloudpickle
import pytest

import terrainwarp.experiments.pareto as report
from terrainwarp import Camera, Heightmap, Scene
from terrainwarp.cli import main
from terrainwarp.experiments.pareto import TIMING_COLUMNS, Setting, rows_to_csv, run_sweep
from terrainwarp.experiments.runner import Job, Runner, SchedulerUnreachableError, close_local_clusters
from terrainwarp.kernels.parallel import threads

# the job functions below live in this test module, which the workers cannot import: send them by value
cloudpickle.register_pickle_by_value(sys.modules[__name__])

SETTINGS = [Setting("grid", 0.0), Setting("sse", 1.0), Setting("sse", 8.0), Setting("continuous", 8.0),
            Setting("delatin", 2.0), Setting("martini", 8.0)]


@pytest.fixture(scope="module", autouse=True)
def _close_clusters():
    yield
    close_local_clusters()


@pytest.fixture(scope="module")
def small():
    hm = Heightmap.fbm(65, 80, seed=9, dx=20.0, max_height=400.0)
    sc = Scene(hm, camera=Camera.default_for(hm, 64, 48))
    return sc, sc.camera_path(3)


def _table(rows) -> list[dict]:
    """The result proper: every column but timings and the run's retry count."""
    return list(csv.DictReader(io.StringIO(rows_to_csv(
        [{k: v for k, v in r.items() if k not in (*TIMING_COLUMNS, "retries")} for r in rows]))))


def _square(i: int, log: str | None = None) -> dict:
    if log:
        with open(log, "a") as f:
            f.write(f"{i}\n")
    if i == 5:
        raise ValueError(f"job {i} is bad")
    return {"value": i * i, "half": i / 2}


def _die_once(i: int, marker: str) -> dict:
    """Job 3 kills its worker process the first time it runs (the nanny starts a new one)."""
    if i == 3 and not os.path.exists(marker):
        Path(marker).touch()
        os.kill(os.getpid(), signal.SIGKILL)
    time.sleep(0.05)
    return {"value": i * i, "pid_ok": True}


def _jobs(n: int, *extra) -> list[Job]:
    return [Job(id=f"j{i}", sort_key=(i,), fields={"i": i}, args=(i, *extra)) for i in range(n)]


# ------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_report_sweep_identical_for_one_and_two_workers(small):
    sc, cams = small
    one = run_sweep(sc, cams, SETTINGS, workers=1, progress=False)
    assert one.workers == 1 and one.n_failed == 0
    two = run_sweep(sc, cams, SETTINGS, workers=2, progress=False)
    assert two.workers == 2 and two.n_failed == 0
    assert len(two.rows) == len(SETTINGS) * len(cams)
    assert [(r["setting"], r["frame"]) for r in two.rows] == [(s.label, k) for s in SETTINGS for k in range(len(cams))]
    assert _table(one.rows) == _table(two.rows)
    # the same table as the in-process run (no Dask at all)
    assert _table(run_sweep(sc, cams, SETTINGS, workers=0, progress=False).rows) == _table(two.rows)
    # heavy inputs were scattered, not shipped with every job: a job's payload is ~100 bytes while the
    # scene (heightmap) went to each of the 2 workers once
    assert two.bytes_jobs / two.n_run < 1000
    assert two.bytes_shared > 2 * sc.heightmap.heights.nbytes


def test_any_job_order_gives_the_same_table():
    r = Runner(workers=2)
    jobs = _jobs(12)
    a = r.run(jobs, _square, progress=False)
    shuffled = jobs[:]
    random.Random(3).shuffle(shuffled)
    b = r.run(shuffled, _square, progress=False)
    assert a.rows == b.rows
    assert [row["i"] for row in a.rows] == list(range(12))
    # the same through the scheduler's address, as an existing cluster is used
    with Runner(scheduler=r.client.scheduler.address) as remote:
        assert remote.n_workers == 2
        assert remote.run(shuffled, _square, progress=False).rows == a.rows


def _kernel_threads(i: int) -> dict:
    return {"threads": threads()}


def test_sweep_workers_run_one_kernel_thread_each():
    # a sweep's parallelism is its worker processes: thread-parallel launches there would oversubscribe
    r = Runner(workers=2)
    rows = r.run(_jobs(4), _kernel_threads, progress=False).rows
    assert [row["threads"] for row in rows] == [1] * 4
    # in-process runs keep this process's setting
    assert Runner(workers=0).run(_jobs(2), _kernel_threads, progress=False).rows[0]["threads"] == threads()


def test_a_raising_job_is_recorded_and_the_sweep_goes_on(small, capsys):
    r = Runner(workers=2)
    res = r.run(_jobs(8), _square, progress=True, desc="squares")
    assert res.n_failed == 1 and len(res.rows) == 8
    bad = res.rows[5]
    assert bad["error"] == "ValueError: job 5 is bad" and bad["value"] != bad["value"]  # NaN filled
    assert all(row["error"] == "" and row["value"] == row["i"] ** 2 for row in res.rows if row["i"] != 5)
    err = capsys.readouterr().err
    assert "squares: 8 jobs: 8 run, 0 resumed, 1 failed" in err and "failed=1" in err  # bar and summary
    # a report setting that raises in the workers (invalid tolerance) is recorded the same way
    sc, cams = small
    res = run_sweep(sc, cams, [Setting("sse", -1.0), Setting("sse", 4.0)], workers=2, progress=False)
    assert [r["error"].startswith("ValueError: lod.tolerance_px") for r in res.rows] == [True] * 3 + [False] * 3
    assert all(r["p99_px"] >= 0 for r in res.rows[3:])


def test_a_killed_worker_has_its_job_retried(tmp_path):
    r = Runner(workers=2)
    res = r.run(_jobs(10, str(tmp_path / "killed")), _die_once, progress=False)
    assert (tmp_path / "killed").exists()  # a worker really died
    assert res.n_failed == 0 and [row["value"] for row in res.rows] == [i * i for i in range(10)]
    assert res.n_retried >= 1 and res.rows[3]["retries"] >= 1
    r.client.wait_for_workers(2, timeout=60)  # the nanny starts a new worker in its place


class _Stop(KeyboardInterrupt):
    pass


def test_resume_redoes_nothing_finished(tmp_path):
    r = Runner(workers=2)
    out = tmp_path / "t.csv"
    log1, log2 = tmp_path / "run1.log", tmp_path / "run2.log"
    seen = []

    def stop_after_4(row):
        seen.append(row["i"])
        if len(seen) == 4:
            raise _Stop

    with pytest.raises(_Stop):
        r.run(_jobs(16, str(log1)), _square, out=out, fingerprint="abc", columns=["i", "value", "half"],
              progress=False, on_row=stop_after_4)
    assert not out.exists()
    partial = out.with_name("t.csv.partial")
    assert partial.exists()
    saved = {int(row["i"]) for row in csv.DictReader(io.StringIO(partial.read_text().split("\n", 1)[1]))}
    assert saved == set(seen) and len(saved) == 4

    res = r.run(_jobs(16, str(log2)), _square, out=out, fingerprint="abc", columns=["i", "value", "half"],
                progress=False)
    redone = {int(x) for x in log2.read_text().split()}
    assert redone & saved == saved & {5} and redone | saved == set(range(16))  # the failed job 5 runs again
    assert res.n_resumed == len(saved - {5}) and res.n_run == 16 - res.n_resumed and out.exists()
    assert partial.exists()  # kept beside the table: job 5 failed again, and a rerun runs it alone
    fresh = Runner(workers=0).run(_jobs(16), _square, progress=False)  # uninterrupted, in-process
    assert rows_to_csv(res.rows) == rows_to_csv(fresh.rows)
    assert res.rows[5]["error"] == "ValueError: job 5 is bad"
    # another sweep's partial file (other fingerprint) is not resumed
    partial.write_text('# terrainwarp sweep zzz\njob_id,i,value,half,error,retries\nj0,0,0,0.0,"",0\n')
    res = r.run(_jobs(3), _square, out=out, fingerprint="abc", columns=["i", "value", "half"], progress=False)
    assert res.n_resumed == 0 and res.n_run == 3


def test_unreachable_scheduler_is_a_clear_error_within_seconds(tmp_path, capsys):
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t0 = time.perf_counter()
    with pytest.raises(SchedulerUnreachableError, match=f"no Dask scheduler answered at tcp://127.0.0.1:{port}"):
        Runner(scheduler=f"tcp://127.0.0.1:{port}")
    assert time.perf_counter() - t0 < 20  # Dask's own default would wait 30 s
    capsys.readouterr()
    assert main(["report", "--scheduler", f"tcp://127.0.0.1:{port}", "--out", str(tmp_path), "--frames", "1",
                 "--quick", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("terrainwarp: error: scheduler: no Dask scheduler answered")
    with pytest.raises(ValueError, match="scheduler: expected an address like tcp://HOST:PORT"):
        Runner(scheduler="localhost")
    with pytest.raises(ValueError, match="workers: expected an integer >= 0"):
        Runner(workers=-1)


def test_report_cli_uses_the_runner_and_leaves_no_partial_file(tmp_path, capsys):
    assert main(["report", "--out", str(tmp_path), "--frames", "1", "--quick", "--policies", "grid,sse",
                 "--width", "48", "--height", "32", "--workers", "2", "--no-progress", "--no-images"]) == 0
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["frames.csv", "pareto.png", "report.md", "scene.toml", "timing.md"]
    rows = list(csv.DictReader(io.StringIO((tmp_path / "frames.csv").read_text())))
    assert len(rows) == 3 and all(r["error"] == "" and r["retries"] == "0" for r in rows)
    assert "Jobs (setting, frame): 3, failed 0, retried after a worker died 0." in (tmp_path / "timing.md").read_text()


def test_an_interrupted_report_sweep_resumes(small, tmp_path, monkeypatch):
    sc, cams = small
    out = tmp_path / "frames.csv"
    real, calls = report._frame_job, []

    def interrupted_after_5(*args):
        if len(calls) == 5:
            raise KeyboardInterrupt
        calls.append(args[-2:])
        return real(*args)

    monkeypatch.setattr(report, "_frame_job", interrupted_after_5)
    with pytest.raises(KeyboardInterrupt):
        run_sweep(sc, cams, SETTINGS, workers=0, progress=False, out=out)
    monkeypatch.setattr(report, "_frame_job", real)
    assert not out.exists() and out.with_name("frames.csv.partial").exists()
    res = run_sweep(sc, cams, SETTINGS, workers=2, progress=False, out=out)
    assert res.n_resumed == 5 and res.n_run == len(SETTINGS) * len(cams) - 5
    full = run_sweep(sc, cams, SETTINGS, workers=2, progress=False)
    assert _table(res.rows) == _table(full.rows)
    assert out.read_text() == rows_to_csv(res.rows)


# ------------------------------------------------------------------------------------------------
# issue 43: sweeps that finish (failed rows retried on a rerun, lost workers' jobs resubmitted)
# ------------------------------------------------------------------------------------------------
def _fails_while(i: int, marker: str, log: str) -> dict:
    """Jobs 2 and 5 raise while ``marker`` exists; every run is logged."""
    with open(log, "a") as f:
        f.write(f"{i}\n")
    if i in (2, 5) and os.path.exists(marker):
        raise RuntimeError(f"job {i} is flaky")
    return {"value": i * i}


def test_a_rerun_retries_the_failed_rows_alone(tmp_path):
    r = Runner(workers=0)
    out, marker, cols = tmp_path / "t.csv", tmp_path / "fail", ["i", "value"]
    marker.touch()
    log1, log2 = tmp_path / "1.log", tmp_path / "2.log"
    first = r.run(_jobs(8, str(marker), str(log1)), _fails_while, out=out, fingerprint="f", columns=cols,
                  progress=False)
    assert first.n_failed == 2 and [row["error"] != "" for row in first.rows].count(True) == 2
    assert out.exists() and out.with_name("t.csv.partial").exists()  # kept: the failed jobs are to run again
    marker.unlink()
    again = r.run(_jobs(8, str(marker), str(log2)), _fails_while, out=out, fingerprint="f", columns=cols,
                  progress=False)
    assert sorted(int(x) for x in log2.read_text().split()) == [2, 5]  # the failed rows alone, never counted done
    assert again.n_resumed == 6 and again.n_run == 2 and again.n_failed == 0
    assert [row["value"] for row in again.rows] == [i * i for i in range(8)]
    assert not out.with_name("t.csv.partial").exists()


def _worker_pids(r: Runner) -> set[int]:
    return set(r.client.run(os.getpid).values())


def _kill_when(journal: Path, rows: int, pids: set[int], killed: list) -> None:
    """SIGKILL the worker processes ``pids`` once ``journal`` holds ``rows`` rows (a header and a magic line)."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < 120:
        if journal.exists() and journal.read_text().count("\n") >= rows + 2:
            for pid in pids:
                os.kill(pid, signal.SIGKILL)
            killed.extend(pids)
            return
        time.sleep(0.01)


def test_the_only_worker_killed_mid_sweep_still_gives_the_reference_rows(small, tmp_path):
    import threading

    sc, cams = small
    reference = run_sweep(sc, cams, SETTINGS, workers=0, progress=False)
    r = Runner(workers=1)
    before, killed = _worker_pids(r), []
    out = tmp_path / "frames.csv"
    t = threading.Thread(target=_kill_when, args=(out.with_name("frames.csv.partial"), 2, before, killed))
    t.start()
    try:
        res = run_sweep(sc, cams, SETTINGS, runner=r, progress=False, out=out)
    finally:
        t.join()
    assert killed == list(before)  # the only worker really died mid-run (2 of 18 rows in)
    assert _worker_pids(r).isdisjoint(before)  # and its nanny started another
    assert res.n_failed == 0 and res.n_retried >= 1
    assert _table(res.rows) == _table(reference.rows)


def test_losing_every_worker_restarts_the_local_cluster():
    r = Runner(workers=1, worker_wait_s=2)
    seen = []

    def scale_to_nothing(row):  # the cluster loses its only worker, and no nanny brings one back
        seen.append(row)
        if len(seen) == 2:
            r.client.cluster.scale(0)

    res = r.run(_jobs(8), _square, progress=False, on_row=scale_to_nothing)
    assert r.restarts == 1 and r.n_workers == 1
    assert [row["value"] for row in res.rows if row["i"] != 5] == [i * i for i in range(8) if i != 5]
    assert res.rows[5]["error"] == "ValueError: job 5 is bad"


def test_losing_every_worker_of_a_remote_scheduler_is_one_clear_error(tmp_path):
    from distributed import LocalCluster

    from terrainwarp.experiments.runner import WorkersLostError

    with LocalCluster(n_workers=1, processes=False, protocol="tcp://", dashboard_address=":0") as cluster:
        r = Runner(scheduler=cluster.scheduler_address, worker_wait_s=1)
        seen = []

        def scale_to_nothing(row):
            seen.append(row)
            if len(seen) == 1:
                cluster.scale(0)

        with pytest.raises(WorkersLostError, match="workers: every Dask worker was lost and none came back within 1 s"):
            r.run(_jobs(40, None), _slow_square, out=tmp_path / "t.csv", fingerprint="x", columns=["i", "value"],
                  progress=False, on_row=scale_to_nothing)
        r.close()
    journal = (tmp_path / "t.csv.partial").read_text()
    assert journal.count("\n") >= 3  # the rows done are kept: a rerun resumes from them


def _slow_square(i: int, _unused: object) -> dict:
    time.sleep(0.05)
    return {"value": i * i}

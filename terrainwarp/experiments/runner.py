"""The sweep runner: independent jobs on ``dask.distributed``, one row of a table per job.

A sweep is a list of :class:`Job` s. Each job is evaluated by a function ``fn(*shared, *job.args) -> dict``
(a row) on a Dask worker; ``shared`` are the heavy inputs (heightmap, scene, reference frames), sent to
every worker once (:meth:`Runner.share`, ``client.scatter(..., broadcast=True)``) and passed to each job as
a future, never pickled into the job itself. Rows come back as jobs finish and are returned sorted by
``Job.sort_key``, so the table does not depend on the number of workers or the completion order.

Where it runs (:class:`Runner`):

- default: a ``LocalCluster`` with one single-threaded worker *process* per core (Warp's CPU launches
  are single-threaded; processes, not threads, give the parallelism). Clusters are kept per process and
  reused by later sweeps of the same size (closed at exit, or by :func:`close_local_clusters`).
- ``scheduler="tcp://HOST:PORT"``: an existing cluster; an unreachable address raises
  :class:`SchedulerUnreachableError` after ``connect_timeout_s`` (3 s).
- ``workers=0``: in this process, one job after another (debugging; no Dask).

Faults:

- a job that raises is recorded as a row with its ``error`` ("Type: message") and the sweep goes on; a rerun
  with the same ``out`` retries it (a failed row in the journal is never counted as done);
- a worker that dies mid-sweep has its jobs rescheduled by the Dask scheduler (up to
  ``distributed.scheduler.allowed-failures`` times); a job whose inputs or result died with the worker (the
  only worker lost: its copy of the shared inputs went with it) is submitted again, up to ``MAX_TRIES`` times,
  once a worker is back (a LocalCluster's nanny restarts its worker; the shared inputs are sent again). The
  ``retries`` column says how many times each job was rescheduled or resubmitted and the summary counts them;
- losing every worker for ``worker_wait_s`` (60 s): a LocalCluster is closed and started afresh (once per run);
  on a remote scheduler, or when the fresh cluster is lost too, :class:`WorkersLostError` (one line; the
  journal keeps the rows done, and a rerun resumes from it);
- a LocalCluster that fails to start (a worker killed while it starts) is :class:`ClusterStartError`, one line;
- with ``out=PATH`` every row is appended, as it arrives (rows are collected at most 0.5 s, the time
  between two asks to the scheduler for retry counts), to ``PATH.partial`` (CSV, each cell JSON-encoded
  so floats and strings read back exactly); at the end the sorted table is written to a temporary name and
  renamed to ``PATH`` and the partial file removed (inside a :func:`terrainwarp.io.files.output_set`: both
  once the whole set is written, so a run that fails later still resumes), unless a job failed: then the
  partial file stays beside the table, and a rerun runs the failed jobs alone. A sweep interrupted before that
  resumes from the partial file: jobs whose id is there with no error are not run again (the file's first
  line holds the sweep's ``fingerprint``; a partial file of another sweep is ignored).

Warp compiles a kernel module on first use in each process (cached in ``~/.cache/warp``, so workers reuse
the cache); JAX is not imported by the workers.
"""

from __future__ import annotations

import atexit
import contextlib
import csv
import io
import itertools
import json
import logging
import math
import os
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..io.files import remove_when_written, temp_path, write_text
from ..kernels.checks import check_int, check_number
from ..kernels.parallel import set_threads
from .dask_worker import PRELOAD

__all__ = ["Job", "Runner", "SweepResult", "SchedulerUnreachableError", "WorkersLostError", "ClusterStartError",
           "close_local_clusters", "pending_jobs", "RUN_COLUMNS", "MAX_TRIES", "pickled_nbytes"]

#: Columns the runner adds to every row: the job's error ("" when it succeeded) and how many times the
#: scheduler rescheduled it after a worker died. Not part of the result proper (``retries`` depends on
#: the run, like timings).
RUN_COLUMNS = ("error", "retries")

_CONNECT_TIMEOUT_S = 3.0
MAX_TRIES = 3  # submissions of a job whose worker was lost with its inputs or its result (then a failed row)
WORKER_WAIT_S = 60.0  # how long a sweep waits for a worker to come back before it restarts the cluster
RESULT_WAIT_S = 10.0  # a finished job's row is fetched within this, else taken as lost with its worker
_KEYS = itertools.count()  # task keys: unique within the process


class SchedulerUnreachableError(ConnectionError, ValueError):
    """No Dask scheduler answered at the given address (a ValueError too, so the CLI reports it in one line)."""


class WorkersLostError(RuntimeError, ValueError):
    """Every worker was lost and none came back (a ValueError too: the CLI reports it in one line, the journal
    kept)."""


class ClusterStartError(RuntimeError, ValueError):
    """A LocalCluster that failed to start (a ValueError too: the CLI reports it in one line)."""


@dataclass(frozen=True)
class Job:
    """One unit of a sweep.

    Attributes:
        id: stable identity across runs (what a resumed sweep recognises as done), e.g. ``"sse=1|3"``.
        sort_key: the row's place in the table (tuples of numbers/strings).
        fields: columns every row of this job carries, also when it fails (e.g. setting, frame).
        args: extra positional arguments of the job function (small: they are sent once per job).
    """

    id: str
    sort_key: tuple
    fields: dict = field(default_factory=dict)
    args: tuple = ()


@dataclass
class SweepResult:
    """Rows sorted by job key plus what the run cost."""

    rows: list[dict]
    n_jobs: int
    n_run: int
    n_resumed: int
    n_failed: int
    n_retried: int
    workers: int
    wall_s: float
    bytes_shared: int
    bytes_jobs: int
    bytes_results: int
    where: str

    @property
    def bytes_per_job(self) -> float:
        """Bytes sent per job: the job's own payload plus the shared inputs' broadcast spread over the jobs."""
        return (self.bytes_jobs + self.bytes_shared) / max(self.n_run, 1)

    def summary(self) -> str:
        return (f"{self.n_jobs} jobs: {self.n_run} run, {self.n_resumed} resumed, {self.n_failed} failed, "
                f"{self.n_retried} retried after a worker died; {self.workers} worker(s) ({self.where}), "
                f"{self.wall_s:.1f} s; sent {self.bytes_shared / 1e6:.2f} MB shared once per worker + "
                f"{self.bytes_jobs / max(self.n_run, 1):.0f} B per job")


# ------------------------------------------------------------------------------------------------
# clusters
# ------------------------------------------------------------------------------------------------
_LOCAL: dict[int, Any] = {}


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def close_local_clusters() -> None:
    """Close the LocalClusters this process started (also done at exit)."""
    for n in list(_LOCAL):
        client = _LOCAL.pop(n)
        cluster = client.cluster
        with contextlib.suppress(Exception):
            client.close(timeout=10)
        with contextlib.suppress(Exception):
            cluster.close(timeout=10)
    with contextlib.suppress(ValueError):
        atexit.unregister(close_local_clusters)


def _local_client(n: int):
    from distributed import Client, LocalCluster  # lazy: heavy optional dependency

    if not _LOCAL:  # registered after distributed's own exit handlers, so it runs before them
        atexit.register(close_local_clusters)
    c = _LOCAL.get(n)
    if c is not None and c.status == "running":
        return c
    close_local_clusters()  # one local cluster at a time: its workers hold a core each
    try:
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=":0",
                               silence_logs=logging.CRITICAL,  # faults are in the table
                               preload=[PRELOAD])  # workers ignore Ctrl-C (the driver handles it), Warp quiet
    except Exception as e:  # noqa: BLE001 - "Nanny failed to start" and whatever else stops the start
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise ClusterStartError(f"workers: the local Dask cluster of {n} worker process(es) failed to start "
                                f"({type(e).__name__}: {msg}); run again, or use --workers 0 to run in this "
                                "process") from None
    c = Client(cluster, set_as_default=False)
    _LOCAL[n] = c
    return c


def _check_address(scheduler: str) -> str:
    if not isinstance(scheduler, str):
        raise TypeError(f"scheduler: expected an address string like tcp://HOST:PORT, got {type(scheduler).__name__}")
    proto, sep, rest = scheduler.partition("://")
    host, _, port = rest.rpartition(":")
    if not sep or proto not in ("tcp", "tls", "ws", "wss", "inproc", "ucx") or not host or not port.isdigit():
        raise ValueError(f"scheduler: expected an address like tcp://HOST:PORT, got {scheduler!r}")
    return scheduler


# ------------------------------------------------------------------------------------------------
# worker side
# ------------------------------------------------------------------------------------------------
def _remote_attempt(fn: Callable, n_shared: int, *args) -> tuple[str, Any]:
    """A job on a worker process: one kernel thread there (a sweep's parallelism is its processes, one a
    core, so thread-parallel launches would only oversubscribe the cores), then :func:`_attempt`."""
    set_threads(1)
    return _attempt(fn, n_shared, *args)


def _attempt(fn: Callable, n_shared: int, *args) -> tuple[str, Any]:
    """Run one job; an exception becomes ("error", "Type: message") so the sweep goes on."""
    try:
        return "ok", fn(*args)
    except Exception as e:  # noqa: BLE001 - every job error is recorded, not raised
        msg = str(e).splitlines()[0] if str(e) else ""
        return "error", f"{type(e).__name__}: {msg}" if msg else type(e).__name__


def pickled_nbytes(obj: Any) -> int:
    """Pickled size (cloudpickle, as Dask sends functions and arguments)."""
    import cloudpickle  # lazy: comes with the heavy optional dask/distributed

    return len(cloudpickle.dumps(obj, protocol=5))


def _suspicious(dask_scheduler, keys: list[str]) -> dict[str, int]:
    """(On the scheduler) how many workers died while holding each task."""
    out = {}
    for k in keys:
        ts = dask_scheduler.tasks.get(k)
        if ts is not None:
            out[k] = int(ts.suspicious)
    return out


# ------------------------------------------------------------------------------------------------
# partial results
# ------------------------------------------------------------------------------------------------
_MAGIC = "# terrainwarp sweep "


def _partial_path(out: str | os.PathLike) -> Path:
    p = Path(out)
    return p.with_name(p.name + ".partial")


def _read_partial(path: Path, fingerprint: str) -> dict[str, dict]:
    """Rows of a partial file by job id; {} when absent, of another sweep, or unreadable."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        return {}
    first, _, body = text.partition("\n")
    if first != _MAGIC + fingerprint:
        return {}
    rows: dict[str, dict] = {}
    reader = csv.reader(io.StringIO(body))
    header = next(reader, None)
    if not header or header[0] != "job_id":
        return {}
    for rec in reader:
        if len(rec) != len(header):  # a line cut short by the interruption
            continue
        try:
            vals = [json.loads(v) for v in rec[1:]]
        except json.JSONDecodeError:
            continue
        rows[rec[0]] = dict(zip(header[1:], vals))
    return rows


class _Journal:
    """Appends rows to ``out.partial`` as they arrive (flushed line by line)."""

    def __init__(self, out: str | os.PathLike, fingerprint: str, columns: Sequence[str], resumed: dict[str, dict]):
        self.path = _partial_path(out)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.columns = list(columns)
        tmp = temp_path(self.path)
        with open(tmp, "w", newline="") as f:  # rewrite what we keep, then append
            f.write(_MAGIC + fingerprint + "\n")
            w = csv.writer(f, lineterminator="\n")
            w.writerow(["job_id", *self.columns])
            for jid, row in resumed.items():
                w.writerow(self._cells(jid, row))
        os.replace(tmp, self.path)
        self.f = open(self.path, "a", newline="")  # noqa: SIM115 - closed in close()
        self.w = csv.writer(self.f, lineterminator="\n")

    def _cells(self, jid: str, row: dict) -> list[str]:
        return [jid] + [json.dumps(row.get(c, math.nan)) for c in self.columns]

    def append(self, jid: str, row: dict) -> None:
        self.w.writerow(self._cells(jid, row))
        self.f.flush()

    def close(self) -> None:
        self.f.close()


def _finished(out: str | os.PathLike | None, fingerprint: str) -> dict[str, dict]:
    """The rows of ``out``'s partial file that count as done: those without an error (a failed row is run
    again)."""
    if out is None:
        return {}
    return {k: v for k, v in _read_partial(_partial_path(out), fingerprint).items() if not v.get("error")}


def pending_jobs(jobs: Sequence[Job], out: str | os.PathLike | None, fingerprint: str = "") -> list[Job]:
    """The jobs a sweep with this ``out`` and ``fingerprint`` would still run: not in its partial file, or
    there with an error."""
    done = _finished(out, fingerprint)
    return [j for j in jobs if j.id not in done]


def _default_csv(rows: list[dict]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0]) if rows else [], lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: repr(v) if isinstance(v, float) else v for k, v in r.items()})
    return buf.getvalue()


# ------------------------------------------------------------------------------------------------
# the runner
# ------------------------------------------------------------------------------------------------
class Runner:
    """Where a sweep's jobs run: a LocalCluster (default), a remote scheduler, or this process.

    Args:
        scheduler: ``"tcp://HOST:PORT"`` of a running Dask scheduler, or None for a LocalCluster.
        workers: LocalCluster size (default: one process per core); 0 runs jobs in this process. With a
            scheduler: wait until that many workers have joined (default 1).
        connect_timeout_s: how long to try reaching ``scheduler`` before :class:`SchedulerUnreachableError`.
        worker_wait_s: how long a sweep that lost every worker waits for one to come back before it restarts
            a LocalCluster (or, on a remote scheduler, raises :class:`WorkersLostError`).
    """

    def __init__(self, scheduler: str | None = None, workers: int | None = None, *,
                 connect_timeout_s: float = _CONNECT_TIMEOUT_S, worker_wait_s: float = WORKER_WAIT_S):
        if workers is not None:
            workers = check_int("workers", workers, 0)
        self.worker_wait_s = check_number("worker_wait_s", worker_wait_s, 0.0, lo_open=True)
        self.bytes_shared = 0
        self.client = None
        self._local_n = 0  # the LocalCluster's size (0: none)
        self._shared: dict[str, tuple[Any, Any]] = {}  # first future's key -> (current future, the object)
        self.restarts = 0
        if scheduler is not None:
            from distributed import Client  # lazy: heavy optional dependency

            addr = _check_address(scheduler)
            if workers == 0:
                raise ValueError("workers: expected >= 1 with a scheduler, got 0")
            try:
                self.client = Client(addr, timeout=connect_timeout_s, set_as_default=False)
            except (OSError, TimeoutError) as e:
                raise SchedulerUnreachableError(
                    f"scheduler: no Dask scheduler answered at {addr} within {connect_timeout_s:g} s "
                    f"({type(e).__name__})") from None
            try:
                self.client.wait_for_workers(workers or 1, timeout=60)
            except TimeoutError:
                self.client.close()
                raise SchedulerUnreachableError(
                    f"scheduler: {addr} has fewer than {workers or 1} worker(s) after 60 s") from None
            self.where = addr
        elif workers == 0:
            self.where = "in-process"
        else:
            self._local_n = workers or _cores()
            self.client = _local_client(self._local_n)
            self.where = "LocalCluster, processes"

    def close(self) -> None:
        """Disconnect from a remote scheduler (a LocalCluster stays up for the next sweep)."""
        if self.client is not None and self.where not in ("in-process", "LocalCluster, processes"):
            self.client.close()
            self.client = None

    def __enter__(self) -> Runner:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def n_workers(self) -> int:
        if self.client is None:
            return 1
        return len(self.client.scheduler_info(n_workers=-1)["workers"])

    def share(self, obj: Any) -> Any:
        """Send ``obj`` to every worker once; returns what to pass to :meth:`run` / :meth:`map` as shared (sent
        again, under the same handle, when the workers holding it were lost)."""
        if self.client is None:  # nothing is sent
            return obj
        fut = self._scatter(obj)
        self._shared[fut.key] = (fut, obj)
        return fut

    def _scatter(self, obj: Any) -> Any:
        nbytes = pickled_nbytes(obj)
        n = self.n_workers
        fut = self.client.scatter([obj], broadcast=True, hash=False)[0]  # a list: a dict is one object
        self.bytes_shared += nbytes * n
        return fut

    def _live(self, shared: tuple) -> tuple:
        """The shared arguments as their current futures (those sent again after a loss replace the first)."""
        return tuple(self._shared[a.key][0] if getattr(a, "key", None) in self._shared else a for a in shared)

    def _recover(self) -> bool:
        """After a loss: wait for a worker (a nanny restarts a killed one), else restart a LocalCluster once;
        then send again every shared input no worker holds any more. Returns whether the cluster was restarted
        (the jobs submitted to the old one are gone)."""
        try:
            self.client.wait_for_workers(1, timeout=self.worker_wait_s)
        except (TimeoutError, OSError) as e:
            if not self._local_n or self.restarts:
                raise WorkersLostError(
                    f"workers: every Dask worker was lost and none came back within {self.worker_wait_s:g} s "
                    f"({self.where}{', after a restart' if self.restarts else ''}; {type(e).__name__})") from None
            self.restarts += 1
            close_local_clusters()
            self.client = _local_client(self._local_n)
            for key, (_, obj) in self._shared.items():
                self._shared[key] = (self._scatter(obj), obj)
            return True
        for key, (fut, obj) in list(self._shared.items()):
            if fut.status != "finished" or not self.client.who_has([fut]).get(fut.key):
                self._shared[key] = (self._scatter(obj), obj)
        return False

    def map(self, fn: Callable, items: Iterable, *shared) -> list:
        """``[fn(*shared, item) for item in items]`` on the workers, in order; a job's exception is
        returned in its place (not raised). For preparatory work whose results are not rows."""
        items = list(items)
        if self.client is None:
            res = [_attempt(fn, len(shared), *shared, it) for it in items]
        else:
            res = [None] * len(items)

            def keep(i: int, status: str, value: Any, retries: int) -> None:
                res[i] = (status, value)

            self._each([(i, (it,)) for i, it in enumerate(items)], fn, shared, "tw-map-", "", keep)
        return [v if s == "ok" else RuntimeError(v) for s, v in res]

    def run(self, jobs: Sequence[Job], fn: Callable, *shared, out: str | os.PathLike | None = None,
            fingerprint: str = "", columns: Sequence[str] | None = None, to_csv: Callable | None = None,
            progress: bool = True, desc: str = "sweep", on_row: Callable[[dict], None] | None = None) -> SweepResult:
        """Run ``fn(*shared, *job.args)`` for every job; rows sorted by ``job.sort_key``.

        Args:
            jobs: the sweep; ids must be unique.
            fn: an importable function returning a dict (the row, without the job's ``fields``).
            shared: values from :meth:`share` (or plain small values).
            out: final CSV path; rows are appended to ``out.partial`` as they arrive and a sweep with the
                same ``fingerprint`` resumes from it (its failed rows are run again).
            fingerprint: identifies the sweep's inputs (scene, cameras...) so a partial file of another
                sweep is not resumed.
            columns: the table's columns in order (job fields first); default: the first successful row's.
                Required with ``out``.
            to_csv: ``rows -> str`` for the final file (default: repr floats).
            on_row: called with each row as it arrives (in completion order).

        Raises:
            WorkersLostError: every worker lost and none back (the journal keeps the rows done).
        """
        from tqdm import tqdm  # lazy: heavy optional dependency

        ids = [j.id for j in jobs]
        if len(set(ids)) != len(ids):
            raise ValueError("jobs: expected unique ids")
        if out is not None and columns is None:
            raise ValueError("columns: expected the table's columns when out is given")
        cols = None if columns is None else [*columns, *(c for c in RUN_COLUMNS if c not in columns)]
        t0 = time.perf_counter()
        by_id = {j.id: j for j in jobs}
        done = {k: v for k, v in _finished(out, fingerprint).items() if k in by_id}
        n_resumed = len(done)
        todo = [j for j in jobs if j.id not in done]
        bar = tqdm(total=len(jobs), initial=n_resumed, desc=desc, unit="job", disable=not progress, leave=False,
                   file=sys.stderr)
        tally = _Tally(done, _Journal(out, fingerprint, cols, done) if out is not None else None, bar, on_row,
                       measure=self.client is not None)
        bytes_jobs = sum(pickled_nbytes((fn, j.args)) for j in todo) if self.client is not None else 0
        try:
            if self.client is None:
                for j in todo:
                    tally.record(j, *_attempt(fn, len(shared), *shared, *j.args), 0)
            else:
                self._each([(j, j.args) for j in todo], fn, shared, f"tw-{desc}-{fingerprint[:12]}-", fingerprint,
                           tally.record)
        finally:
            tally.close()
        rows = _table(jobs, done, cols)
        if out is not None:
            write_text(out, (to_csv or _default_csv)(rows))
            if not any(r.get("error") for r in rows):  # else kept: a rerun runs the failed jobs alone
                remove_when_written(_partial_path(out))  # inside an output set: once the table is in place
        res = SweepResult(rows=rows, n_jobs=len(jobs), n_run=len(todo), n_resumed=n_resumed,
                          n_failed=tally.n_failed, n_retried=tally.n_retried, workers=self.n_workers,
                          wall_s=time.perf_counter() - t0, bytes_shared=self.bytes_shared, bytes_jobs=bytes_jobs,
                          bytes_results=tally.bytes_results, where=self.where)
        if progress:
            print(f"{desc}: {res.summary()}", file=sys.stderr)
        return res

    # -- distributed: submit every job, collect results as they finish, resubmit the lost ----------------
    def _submit(self, fn: Callable, shared: tuple, args: tuple, prefix: str) -> Any:
        sh = self._live(shared)
        return self.client.submit(_remote_attempt, fn, len(sh), *sh, *args,
                                  key=f"{prefix}{time.time_ns()}-{next(_KEYS)}", pure=False)

    def _each(self, items: list[tuple[Any, tuple]], fn: Callable, shared: tuple, prefix: str, fingerprint: str,
              record: Callable[[Any, str, Any, int], None]) -> None:
        """Run ``fn(*shared, *args)`` for each ``(tag, args)`` of ``items`` on the cluster and call
        ``record(tag, status, value, retries)`` as each finishes (a job's error is a status, not raised). A job
        lost with a worker (its inputs or its result) is submitted again once a worker is back, up to
        ``MAX_TRIES`` times in all; ``retries`` counts the scheduler's reschedules and these resubmissions. While
        no worker is left, :meth:`_recover` waits for one (or restarts the LocalCluster, every job still out
        submitted again)."""
        futures: dict = {}  # future -> (tag, args, submissions so far)
        try:
            for tag, args in items:
                futures[self._submit(fn, shared, args, prefix)] = (tag, args, 1)
            waiting, finished, last = set(futures), [], time.monotonic()
            while waiting or finished:
                done: set = set()
                if waiting:
                    done = _first_done(waiting, 0.5)
                    waiting -= done
                    finished += sorted(done, key=lambda f: f.key)
                if not done and waiting and self.n_workers == 0 and self._recover():
                    # a fresh cluster: every job still out belongs to the old one
                    waiting = set(self._again([*finished, *waiting], futures, fn, shared, prefix, record))
                    finished.clear()
                elif finished and (not waiting or time.monotonic() - last >= 0.5):
                    waiting |= set(self._flush(finished, futures, fn, shared, prefix, record))
                    last = time.monotonic()
        except BaseException:
            for f in futures:
                f.cancel()
            raise

    def _flush(self, finished: list, futures: dict, fn: Callable, shared: tuple, prefix: str,
               record: Callable[[Any, str, Any, int], None]) -> list:
        """Record the jobs finished since the last flush (at most every 0.5 s), with one scheduler round trip
        for their retry counts; the futures are held until then so the scheduler still knows their tasks.
        Returns the futures of the jobs submitted again (lost with a worker)."""
        try:
            susp = self.client.run_on_scheduler(_suspicious, keys=[f.key for f in finished])
        except Exception:  # noqa: BLE001 - the count is informative; never fail the sweep over it
            susp = {}
        lost = []
        for f in finished:
            outcome = _outcome(f)
            if outcome is None:
                lost.append(f)
                continue
            tag, _, tries = futures.pop(f)
            record(tag, *outcome, susp.get(f.key, 0) + tries - 1)
            f.release()
        finished.clear()
        if lost:
            self._recover()
        return self._again(lost, futures, fn, shared, prefix, record)

    def _again(self, lost: list, futures: dict, fn: Callable, shared: tuple, prefix: str,
               record: Callable[[Any, str, Any, int], None]) -> list:
        """Submit the jobs of ``lost`` futures again (a failed row once one has been submitted ``MAX_TRIES``
        times); returns the new futures."""
        again = []
        for f in lost:
            tag, args, tries = futures.pop(f)
            f.release()
            if tries >= MAX_TRIES:
                record(tag, "error", f"WorkerLost: the job's worker was lost {tries} times, its inputs or result "
                                     "with it", tries - 1)
                continue
            g = self._submit(fn, shared, args, prefix)
            futures[g] = (tag, args, tries + 1)
            again.append(g)
        return again


def _first_done(futures: set, timeout_s: float) -> set:
    """The futures of ``futures`` that are done, once one is or ``timeout_s`` has passed (their states are kept
    up to date by the client's own thread)."""
    t0 = time.monotonic()
    while True:
        done = {f for f in futures if f.done()}
        if done or time.monotonic() - t0 >= timeout_s:
            return done
        time.sleep(0.01)


def _outcome(f: Any) -> tuple[str, Any] | None:
    """A finished future's (status, value): the job's own, or ("error", ...) for a job that killed its workers
    (``KilledWorker``) or could not run; None when it was lost with a worker (cancelled, its inputs or result
    gone, or its row not fetched within ``RESULT_WAIT_S``): to be submitted again."""
    from distributed import CancelledError  # lazy: heavy optional dependency

    if f.status in ("cancelled", "lost"):
        return None
    try:
        return f.result(timeout=RESULT_WAIT_S)
    except (CancelledError, TimeoutError):  # a result that died with its worker is never fetched: run it again
        return None
    except Exception as e:  # noqa: BLE001 - KilledWorker (a job that kills its worker again and again) and the like
        msg = str(e).splitlines()[0] if str(e) else ""
        return "error", f"{type(e).__name__}: {msg}"


class _Tally:
    """A run's rows as they arrive: kept by job id, appended to the journal, counted, shown on the bar."""

    def __init__(self, done: dict[str, dict], journal: _Journal | None, bar: Any,
                 on_row: Callable[[dict], None] | None, measure: bool):
        self.done, self.journal, self.bar, self.on_row, self.measure = done, journal, bar, on_row, measure
        self.n_failed = sum(1 for r in done.values() if r.get("error"))
        self.n_retried = 0
        self.bytes_results = 0

    def record(self, job: Job, status: str, value: Any, retries: int) -> None:
        if status == "ok" and not isinstance(value, dict):
            status, value = "error", f"TypeError: fn: expected a dict row, got {type(value).__name__}"
        row = {**job.fields, **(value if status == "ok" else {}), "error": "" if status == "ok" else value,
               "retries": retries}
        self.n_failed += status != "ok"
        self.n_retried += retries > 0
        if self.measure:
            self.bytes_results += pickled_nbytes(value)
        self.done[job.id] = row
        if self.journal is not None:
            self.journal.append(job.id, row)
        if self.on_row is not None:
            self.on_row(row)
        self.bar.update(1)
        self.bar.set_postfix(failed=self.n_failed, retried=self.n_retried, refresh=status != "ok" or retries > 0)

    def close(self) -> None:
        self.bar.close()
        if self.journal is not None:
            self.journal.close()


def _table(jobs: Sequence[Job], done: dict[str, dict], cols: list[str] | None) -> list[dict]:
    """The rows sorted by job key, in ``cols`` (default: the first successful row's columns)."""
    if cols is None:
        first = next((done[j.id] for j in jobs if j.id in done and not done[j.id].get("error")), None)
        cols = list(first) if first else [*(jobs[0].fields if jobs else {}), *RUN_COLUMNS]
        cols += [c for c in RUN_COLUMNS if c not in cols]
    return [{c: done[j.id].get(c, "" if c == "error" else 0 if c == "retries" else math.nan) for c in cols}
            for j in sorted(jobs, key=lambda j: j.sort_key)]

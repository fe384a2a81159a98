"""The fuzz suite's runner (issue 31, "A fuzz suite"): cases from :mod:`fuzz_corpus`, run in batches inside a
worker subprocess, judged there, counted here.

* The worker (``python tests/fuzz_runner.py --worker``) imports terrainwarp once and runs case after case:
  each case's files are written to a fresh folder, the loader (or ``terrainwarp.cli.main(argv)``) is called,
  and the result is judged (:func:`judge_load`, :func:`judge_cli`). It says ``start`` before each case and
  sends the verdict after it, so the supervisor always knows which input was in flight.
* The supervisor (:class:`Supervisor`) feeds batches and waits for each verdict at most ``HANG_S`` seconds.
  A worker that dies (segfault, abort, SIGBUS, an exit from native code) or does not answer in time is
  killed (its whole process group) and restarted; the input in flight is kept in the findings folder as a
  ``crash`` or a ``hang``, and the batch goes on from the next case. The worker runs under an address-space
  limit (``MEMORY_MB``), so a case that allocates without bound is a MemoryError, not a machine out of memory,
  and its size guard is told the worker has ``GUARD_MB``, so that its refusals are the same on every run.
* :func:`fuzz` draws the cases with hypothesis (deterministic for a seed: ``@seed``, no database, the
  generate phase only) and returns the counts (:class:`Counts`); every finding is also written to the
  findings folder: the input file(s) and ``finding.json`` (what was called, what happened, how the input
  was made).

Verdicts: ``ok``; a refusal counted by its kind (``ValueError``, ``TypeError``, ``OSError``) when the
exception is one of those and its message names the input (the file's name or path, the argument or key
given); and the findings: ``crash``, ``hang``, ``exception`` (any other type escaped), ``unnamed`` (an
allowed type whose message names no input), ``bad-result`` (a load that returned something the loader's
own rules forbid, or a streamed read that differs from the in-memory one), ``traceback`` (the CLI let an
exception out or printed a traceback), ``cli-output`` (an error run without its one ``terrainwarp: error:``
line, an unexpected exit code, or files left in ``--out``).
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import pickle
import re
import resource
import select
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
import tomllib
import traceback
import warnings
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from fuzz_corpus import SCENE_KEYS, TARGETS, Case, case_strategy
from hypothesis import HealthCheck, Phase, Verbosity, given, settings
from hypothesis import seed as hseed
from hypothesis import strategies as st

__all__ = ["HANG_S", "Counts", "Supervisor", "fuzz", "judge_cli", "judge_load", "names_input", "run_case"]

HANG_S = 20.0  # a case that runs longer is a hang: the worker is killed and restarted
MEMORY_MB = 6144  # the worker's address-space limit (RLIMIT_AS): a case that allocates without bound fails fast
# (a MemoryError, a finding) instead of taking the shared machine's memory
GUARD_MB = 2048  # what the size guard (terrainwarp.io.memory) is told the worker has: the same refusals on every
# run, whatever the shared machine has free and however large the worker's address space has grown
BATCH = 64  # cases sent to the worker at once
ALLOWED = (ValueError, TypeError, OSError)
FINDINGS = ("crash", "hang", "exception", "unnamed", "bad-result", "traceback", "cli-output")
MAX_COMPARE = 1 << 22  # samples: a streamed file at most this big is also read whole and compared with load()


# ------------------------------------------------------------------------------------------------
# judging
# ------------------------------------------------------------------------------------------------
def names_input(message: str, names: set[str]) -> bool:
    """True when ``message`` names the input: it holds one of the file names or paths in ``names``, or it
    starts with ``NAME:`` or ``NAME ...:`` where NAME (or its last dotted part, or its option form
    ``--name``) is one of ``names``."""
    if any(n in message for n in names if ("." in n or "/" in n) and len(n) > 3):
        return True
    head = message.split(":", 1)[0].strip()
    cands = {head, head.split(" ")[0], head.rsplit(".", 1)[-1], head.removeprefix("argument ").strip()}
    cands |= {c.lstrip("-").replace("-", "_") for c in list(cands)}
    return bool(cands & names)


def _error(e: BaseException, names: set[str]) -> dict[str, Any]:
    msg = str(e)
    first = msg.splitlines()[0] if msg else ""
    res = {"type": type(e).__name__, "mro": [c.__name__ for c in type(e).__mro__], "message": first[:2000]}
    if not isinstance(e, ALLOWED):
        res["verdict"] = "exception"
        res["traceback"] = "".join(traceback.format_exception(e))[-6000:]
    elif not names_input(first, names):
        res["verdict"] = "unnamed"
        res["traceback"] = "".join(traceback.format_exception(e))[-6000:]
    else:
        res["verdict"] = next(k.__name__ for k in ALLOWED if isinstance(e, k))
    return res


def _check_heightmap(hm: object, *, holes: bool) -> str | None:
    """What a loaded heightmap breaks of the loader's rules, or None."""
    from terrainwarp import Heightmap

    if not isinstance(hm, Heightmap):
        return f"load returned {type(hm).__name__}, not a Heightmap"
    h = hm.heights
    if h.dtype != np.float32 or h.ndim != 2 or h.size == 0:
        return f"heights {h.dtype} {h.shape}"
    if np.isinf(h).any():
        return "infinite heights"
    nan = int(np.isnan(h).sum())
    if nan == h.size or (nan and not holes):
        return f"{nan} NaN heights of {h.size}"
    if not all(np.isfinite(v) and v > 0 for v in (hm.dx, hm.dz)):
        return f"spacing dx={hm.dx}, dz={hm.dz}"
    return None


def _load_kwargs(call: dict[str, Any]) -> dict[str, Any]:
    return {k: call[k] for k in ("dx", "dz", "max_height", "channel", "allow_nan", "window", "bounds", "decimate",
                                 "resampling") if k in call}


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and a.dtype == b.dtype and bool(np.array_equal(a, b, equal_nan=True))


def _open_geotiff(path: Path, call: dict[str, Any]) -> str | None:
    """Heightmap.open, then a window or the whole grid; the whole grid must equal Heightmap.load's."""
    from terrainwarp import Heightmap
    from terrainwarp.io import geotiff

    sh = Heightmap.open(path, call.get("dx"), call.get("dz"), band=call.get("band", 1), cache_mb=call.get("cache_mb"))
    rows, cols = sh.shape
    if rows < 1 or cols < 1 or not (np.isfinite(sh.dx) and sh.dx > 0 and np.isfinite(sh.dz) and sh.dz > 0):
        return f"open: shape {sh.shape}, dx={sh.dx}, dz={sh.dz}"
    if "window" in call:
        step, r0, c0, n, m = call["window"]
        w = sh.window(step, r0, c0, n, m)
        return None if w.dtype == np.float32 and w.shape == (n, m) and not np.isinf(w).any() else \
            f"window {call['window']}: {w.dtype} {w.shape}"
    if rows * cols > MAX_COMPARE:
        w = sh.window(1, 0, 0, min(rows, 257), min(cols, 257))
        return None if not np.isinf(w).any() else "infinite heights in the first tile"
    whole = sh.load()
    bad = _check_heightmap(whole, holes=True)
    if bad is not None:
        return "open().load(): " + bad
    lo, hi = sh.height_range
    if (lo, hi) != whole.height_range:
        return f"height_range {(lo, hi)} != the grid's {whole.height_range}"
    if geotiff.is_gdal_raster(path):
        try:
            mem = Heightmap.load(path, call.get("dx"), call.get("dz"), channel=call.get("band", 1) - 1)
        except ALLOWED as e:
            return f"open().load() read what load() refuses ({type(e).__name__}: {str(e)[:300]})"
        if not _same(mem.heights, whole.heights) or (mem.dx, mem.dz) != (whole.dx, whole.dz):
            return "open().load() differs from load()"
    return None


def _run_load(case: Case, path: Path) -> str | None:
    """Call the loader a case asks for; a description of a bad result, or None."""
    from terrainwarp import Heightmap
    from terrainwarp.io import geotiff

    call = case.call
    if case.target == "geotiff" and call.get("how", "load").startswith("open"):
        return _open_geotiff(path, call)
    hm = Heightmap.load(path, **_load_kwargs(call))
    # a GDAL raster's no-data cells are NaN whatever allow_nan says (Heightmap.load); elsewhere only with it
    return _check_heightmap(hm, holes=bool(call.get("allow_nan")) or geotiff.is_gdal_raster(path)
                            or bool(set(call) & {"window", "bounds", "decimate", "resampling"}))


def _scene_names(case: Case, scene_path: Path) -> set[str]:
    """What a scene error may name: the scene file, the files beside it, every table and key of the schema
    and of the case's TOML (when it parses), dotted and plain."""
    names = {scene_path.name, str(scene_path), *case.files, "scene"}
    for table, keys in SCENE_KEYS.items():
        names |= {table, *keys, *(f"{table}.{k}" for k in keys if table)}
    try:
        d = tomllib.loads(case.data.decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError):
        return names

    def walk(t: dict, prefix: str) -> None:
        for k, v in t.items():
            names.add(str(k))
            names.add(f"{prefix}{k}")
            if isinstance(v, dict):
                walk(v, f"{prefix}{k}.")
            elif isinstance(v, str) and v:
                names.add(v)

    walk(d, "")
    return names


def _run_scene(case: Case, path: Path) -> str | None:
    from terrainwarp import Scene

    sc = Scene.load(path)
    cam = sc.camera
    if not (np.all(np.isfinite(cam.position)) and np.all(np.isfinite(cam.target))):
        return f"camera {cam}"
    sc.path_info()
    for c in sc.camera_path():
        if not (np.all(np.isfinite(c.position)) and np.all(np.isfinite(c.target))):
            return f"camera path: {c}"
    return None


def judge_load(case: Case, d: Path) -> dict[str, Any]:
    """Run a file or scene case in folder ``d`` and judge it."""
    path = d / case.name
    names = {path.name, str(path), *(k for k in case.call if k != "how")}
    if "window" in case.call and case.call.get("how") == "open_window":
        names |= {"step", "r0", "c0", "rows", "cols"}  # StreamedHeightmap.window(step, r0, c0, rows, cols)
    if case.target == "toml":
        names |= _scene_names(case, path)
    try:
        with warnings.catch_warnings(record=True) as ws:
            warnings.simplefilter("always")
            bad = _run_scene(case, path) if case.target == "toml" else _run_load(case, path)
    except Exception as e:  # noqa: BLE001 - judging is the point
        res = _error(e, names)
    else:
        res = {"verdict": "ok"} if bad is None else {"verdict": "bad-result", "message": bad}
    res["warnings"] = sorted({f"{w.category.__name__}: {str(w.message)[:200]}" for w in ws})
    return res


_OUT_LINE = re.compile(r"^terrainwarp: error: (.+)$")


def _cli_argv(case: Case, d: Path) -> list[str]:
    fill = {"SCENE": str(d / case.name), "OUT": str(d / "out"), "FILE": str(d / "hm.png")}
    return [fill.get(a, a) for a in case.argv or []]


def _cli_names(case: Case, d: Path, argv: list[str]) -> set[str]:
    names = _scene_names(case, d / case.name) | {"COMMAND", "NAME", "scene", "names", "out", "path", "bench"}
    for a in argv:
        if len(a.strip()) >= 2:
            names |= {a, a.strip(), a.lstrip("-"), a.lstrip("-").replace("-", "_")}
    return names | {str(d / n) for n in case.files}


def _cli_names_input(message: str, names: set[str], argv: list[str]) -> bool:
    """As :func:`names_input`, and argparse's own forms: an option named anywhere (``argument --width: ...``,
    ``the following arguments are required: --inner``), or a token of the command line quoted back
    (``unrecognized arguments: 16 1``)."""
    if names_input(message, names) or re.search(r"(^|[\s(\[,'\"])--[a-z][a-z-]*", message):
        return True
    if message.startswith("unrecognized arguments:"):  # argparse quotes them back, blanks included
        return True
    words = set(re.findall(r"[^\s,'\"\[\]()]+", message))
    if any(w in names for w in words if len(w) >= 3):  # a metavariable or key: "required: COMMAND"
        return True
    return any(a.strip() in words or (len(a.strip()) >= 3 and a.strip() in message) for a in argv if a.strip())


def judge_cli(case: Case, d: Path) -> dict[str, Any]:
    """Run ``terrainwarp.cli.main(argv)`` in folder ``d`` and judge what it printed and left."""
    from terrainwarp import cli

    argv = _cli_argv(case, d)
    out_dir = d / "out"
    out, err = io.StringIO(), io.StringIO()
    res: dict[str, Any] = {"argv": argv}
    with warnings.catch_warnings(record=True) as ws, contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        warnings.simplefilter("always")
        try:
            rc = cli.main(argv)
        except SystemExit as e:
            rc = e.code
        except BaseException as e:  # noqa: BLE001 - a traceback is the finding
            res.update(verdict="traceback", type=type(e).__name__, message=str(e)[:2000],
                       traceback="".join(traceback.format_exception(e))[-6000:])
            rc = None
    res["warnings"] = sorted({f"{w.category.__name__}: {str(w.message)[:200]}" for w in ws})
    text = err.getvalue()
    res["stderr"] = text[-3000:]
    res["rc"] = rc
    if "verdict" in res:
        return res
    if "Traceback (most recent call last)" in text:
        return {**res, "verdict": "traceback"}
    if rc in (0, 1) or (rc == 2 and not argv):  # done (1: stability's unexplained failures); bare: usage
        return {**res, "verdict": "ok"}
    lines = [ln for ln in text.replace("\r", "\n").splitlines() if ln.strip()]
    m = _OUT_LINE.match(lines[-1]) if lines else None
    if rc != 2 or m is None:
        return {**res, "verdict": "cli-output", "message": f"exit {rc!r}, stderr ends {lines[-1:]!r}"}
    res["message"] = m.group(1)[:2000]
    if out_dir.exists() and any(out_dir.rglob("*")):
        return {**res, "verdict": "cli-output", "message": f"left {sorted(str(p) for p in out_dir.rglob('*'))[:5]} "
                                                            f"after: {m.group(1)[:300]}"}
    if not _cli_names_input(m.group(1), _cli_names(case, d, argv), argv):
        return {**res, "verdict": "unnamed"}
    return {**res, "verdict": "refused"}


def judge_selftest(case: Case, d: Path) -> dict[str, Any]:
    """The supervisor's own test (``target="selftest"``, never drawn): ``call["do"]`` crashes the worker the
    way native code would (``segv``, ``bus``, ``abort``, ``exit``), sleeps ``call["s"]`` seconds, or returns."""
    do = case.call.get("do")
    if do in ("segv", "bus"):
        os.kill(os.getpid(), signal.SIGSEGV if do == "segv" else signal.SIGBUS)
    elif do == "abort":
        os.abort()
    elif do == "exit":
        os._exit(3)
    elif do == "sleep":
        time.sleep(float(case.call["s"]))
    return {"verdict": "ok"}


_JUDGES = {"cli": judge_cli, "selftest": judge_selftest}


def run_case(case: Case, root: Path) -> dict[str, Any]:
    """Write a case's files into a fresh folder under ``root``, run and judge it, remove the folder."""
    d = root / f"c{case.index:05d}"
    shutil.rmtree(d, ignore_errors=True)
    d.mkdir(parents=True)
    for n, b in case.files.items():
        (d / n).write_bytes(b)
    (d / case.name).write_bytes(case.data)
    here = os.getcwd()
    t0 = time.perf_counter()
    with _fd2_captured() as native:
        try:
            os.chdir(d)
            res = _JUDGES.get(case.target, judge_load)(case, d)
        finally:
            os.chdir(here)
            shutil.rmtree(d, ignore_errors=True)
    res["secs"] = time.perf_counter() - t0
    res["native_stderr"] = native.getvalue()[-2000:]
    if res["native_stderr"].strip() and case.target == "cli" and res["verdict"] == "refused":
        res["verdict"] = "cli-output"  # the one error line is not alone on stderr
        res["message"] = f"native stderr besides the error line: {res['native_stderr'].strip()[:300]!r}"
    return res


@contextlib.contextmanager
def _fd2_captured():
    """What native code (and anything else) writes to file descriptor 2 while the block runs."""
    got = io.StringIO()
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as f:
        os.dup2(f.fileno(), 2)
        try:
            yield got
        finally:
            with contextlib.suppress(Exception):
                sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            f.seek(0)
            got.write(f.read().decode("utf-8", "replace"))


# ------------------------------------------------------------------------------------------------
# the worker process
# ------------------------------------------------------------------------------------------------
def _send(f, obj: object) -> None:
    b = pickle.dumps(obj)
    f.write(struct.pack("<Q", len(b)) + b)
    f.flush()


def _recv(f) -> object | None:
    head = f.read(8)
    if len(head) < 8:
        return None
    (n,) = struct.unpack("<Q", head)
    return pickle.loads(f.read(n))


def worker_main() -> int:
    """Read batches of cases on stdin, answer ``("start", i)`` and ``("result", i, verdict)`` on the
    original stdout; everything else the process prints (Python or native) goes to stderr."""
    limit = int(os.environ.get("TERRAINWARP_FUZZ_MEMORY_MB", MEMORY_MB)) << 20
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    proto = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)  # native code that prints must not corrupt the protocol
    sys.stdout = sys.stderr
    from terrainwarp.io import memory
    from terrainwarp.runtime import configure

    # imported once (the point of a long-lived worker); Warp started quiet, as the command starts it, so its
    # greeting is not taken for a case's output on stderr
    configure(quiet=True)
    guard = int(os.environ.get("TERRAINWARP_FUZZ_GUARD_MB", GUARD_MB)) << 20
    if guard:  # verdicts independent of the machine's free memory (0: the machine's own)
        memory.available_bytes = lambda: guard

    root = Path(tempfile.mkdtemp(prefix="tw-fuzz-worker-"))
    inp = os.fdopen(os.dup(0), "rb")
    try:
        while True:
            batch = _recv(inp)
            if batch is None:
                return 0
            for case in batch:
                _send(proto, ("start", case.index))
                _send(proto, ("result", case.index, run_case(case, root)))
    finally:
        shutil.rmtree(root, ignore_errors=True)


# ------------------------------------------------------------------------------------------------
# the supervisor
# ------------------------------------------------------------------------------------------------
class Supervisor:
    """One worker subprocess, restarted after a crash or a hang. :meth:`run` sends a batch and yields
    ``(case, verdict)`` for each case, a crash or a hang included."""

    def __init__(self, log: Path | None = None, hang_s: float = HANG_S, memory_mb: int = MEMORY_MB):
        self.hang_s = hang_s
        self.memory_mb = memory_mb
        self.log = log
        self.proc: subprocess.Popen | None = None
        self.restarts = 0
        self._buf = b""

    def _start(self) -> None:
        env = dict(os.environ, PYTHONUNBUFFERED="1", TERRAINWARP_THREADS=os.environ.get("TERRAINWARP_THREADS", "1"),
                   MPLBACKEND="Agg", TERRAINWARP_FUZZ_MEMORY_MB=str(self.memory_mb))
        err = open(self.log, "ab") if self.log is not None else subprocess.DEVNULL  # noqa: SIM115
        self.proc = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--worker"], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=err, env=env, start_new_session=True,
                                     cwd=tempfile.gettempdir())
        if err is not subprocess.DEVNULL:
            err.close()
        self._buf = b""

    def _kill(self) -> int | None:
        p = self.proc
        self.proc = None
        if p is None:
            return None
        if p.poll() is None:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(p.pid, signal.SIGKILL)  # the worker's own session: it and anything it started
        for f in (p.stdin, p.stdout):
            with contextlib.suppress(OSError):
                f.close()
        return p.wait()

    def close(self) -> None:
        p = self.proc
        if p is not None:
            with contextlib.suppress(OSError):
                p.stdin.close()
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                pass
            self._kill()

    def _read(self, deadline: float) -> object | str:
        """The next message, ``"eof"`` when the worker died, ``"timeout"`` past ``deadline``."""
        fd = self.proc.stdout.fileno()
        while True:
            if len(self._buf) >= 8:
                (n,) = struct.unpack("<Q", self._buf[:8])
                if len(self._buf) >= 8 + n:
                    msg = pickle.loads(self._buf[8:8 + n])
                    self._buf = self._buf[8 + n:]
                    return msg
            left = deadline - time.monotonic()
            if left <= 0:
                return "timeout"
            r, _, _ = select.select([fd], [], [], left)
            if not r:
                return "timeout"
            chunk = os.read(fd, 1 << 20)
            if not chunk:
                return "eof"
            self._buf += chunk

    def run(self, batch: list[Case]):
        pending = list(batch)
        retried = False
        while pending:
            if self.proc is None:
                self._start()
            try:
                _send(self.proc.stdin, pending)
            except BrokenPipeError:
                self._kill()
                self.restarts += 1
                if retried:
                    raise RuntimeError(f"the fuzz worker does not start; see {self.log}") from None
                retried = True
                continue
            by_index = {c.index: c for c in pending}
            current = None
            t_start = time.monotonic()
            while pending:
                msg = self._read(time.monotonic() + (self.hang_s if current is not None else self.hang_s + 60))
                if isinstance(msg, tuple) and msg[0] == "start":
                    current, t_start = by_index[msg[1]], time.monotonic()
                    continue
                if isinstance(msg, tuple) and msg[0] == "result":
                    pending = [c for c in pending if c.index != msg[1]]
                    current = None
                    yield by_index[msg[1]], msg[2]
                    continue
                rc = self._kill()
                self.restarts += 1
                if current is None and not retried:  # died between cases: the batch again, on a fresh worker
                    retried = True
                    break
                current = current or pending[0]  # a worker that cannot even start: each case in turn is charged
                retried = False
                secs = time.monotonic() - t_start
                kind = "hang" if msg == "timeout" else "crash"
                sig = -rc if rc is not None and rc < 0 else None
                how = f"killed after {secs:.1f} s" if kind == "hang" else \
                    f"worker exited with {'signal ' + signal.Signals(sig).name if sig else f'code {rc}'}"
                pending = [c for c in pending if c.index != current.index]
                yield current, {"verdict": kind, "message": how, "secs": secs, "rc": rc,
                                "log_tail": self._log_tail()}
                break

    def _log_tail(self) -> str:
        if self.log is None or not self.log.exists():
            return ""
        with self.log.open("rb") as f:
            f.seek(max(0, self.log.stat().st_size - 3000))
            return f.read().decode("utf-8", "replace")


# ------------------------------------------------------------------------------------------------
# counting and the run
# ------------------------------------------------------------------------------------------------
@dataclass
class Counts:
    """Verdicts per target, the exception classes seen, the warnings, timings and the findings kept."""

    verdicts: dict[str, Counter] = field(default_factory=dict)
    classes: dict[str, Counter] = field(default_factory=dict)
    warnings: dict[str, Counter] = field(default_factory=dict)
    native: dict[str, Counter] = field(default_factory=dict)  # first line of what a case printed on fd 2
    native_cases: dict[tuple[str, str], list[int]] = field(default_factory=dict)  # (target, that line) -> cases
    secs: dict[str, list[float]] = field(default_factory=dict)
    findings: list[dict[str, Any]] = field(default_factory=list)
    restarts: int = 0
    wall_s: float = 0.0

    def add(self, case: Case, res: dict[str, Any]) -> None:
        t = case.target
        self.verdicts.setdefault(t, Counter())[res["verdict"]] += 1
        if "type" in res:
            self.classes.setdefault(t, Counter())[res["type"]] += 1
        for w in res.get("warnings", []):
            self.warnings.setdefault(t, Counter())[w] += 1
        if res.get("native_stderr", "").strip():
            first = res["native_stderr"].strip().splitlines()[0][:200]
            self.native.setdefault(t, Counter())[first] += 1
            self.native_cases.setdefault((t, first), []).append(case.index)
        self.secs.setdefault(t, []).append(float(res.get("secs", 0.0)))

    def n_findings(self) -> int:
        return sum(c[k] for c in self.verdicts.values() for k in FINDINGS)


def keep_finding(folder: Path, case: Case, res: dict[str, Any], seed: int) -> Path:
    """Write the input (and the files beside it) and ``finding.json`` to ``folder/<target>-<index>-<verdict>``."""
    d = folder / f"{case.target}-{case.index:05d}-{res['verdict']}"
    d.mkdir(parents=True, exist_ok=True)
    (d / case.name).write_bytes(case.data)
    for n, b in case.files.items():
        (d / n).write_bytes(b)
    meta = {"target": case.target, "index": case.index, "seed": seed, "file": case.name, "call": repr(case.call),
            "argv": case.argv, "how": case.how, **{k: v for k, v in res.items() if k != "warnings"}}
    (d / "finding.json").write_text(json.dumps(meta, indent=2, default=repr) + "\n")
    return d


def each_case(target: str, n: int, seed: int, fn) -> None:
    """Call ``fn(case)`` for ``n`` cases of ``target`` drawn by hypothesis, the same cases for the same seed.

    They are drawn in a subprocess (``--generate``) that imports this suite and nothing of terrainwarp: hypothesis
    draws some values from the literals in the source of the non-library modules loaded in its process, so in
    the caller's (pytest's, a benchmark's) the same seed gave other cases whenever other modules were loaded."""
    p = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--generate", target, str(n), str(seed)],
                         stdout=subprocess.PIPE, cwd=tempfile.gettempdir(), env=dict(os.environ, PYTHONHASHSEED="0"))
    try:
        while (case := _recv(p.stdout)) is not None:
            fn(case)
    finally:
        p.stdout.close()
        rc = p.wait()
    if rc:
        raise RuntimeError(f"drawing the {target} cases failed (exit {rc}): python {__file__} --generate {target} "
                           f"{n} {seed}")


def _generate(target: str, n: int, seed: int) -> int:
    """The ``--generate`` subprocess: draw the cases of :func:`each_case` and send them on stdout."""
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)  # a library that prints must not corrupt the stream
    counter = iter(range(10**9))
    fn = lambda case: _send(out, case)  # noqa: E731

    @settings(max_examples=n, database=None, phases=[Phase.generate], deadline=None, derandomize=False,
              suppress_health_check=list(HealthCheck), verbosity=Verbosity.quiet, print_blob=False)
    @hseed(seed * 1000 + TARGETS.index(target))
    @given(st.data())
    def draw(data) -> None:
        fn(data.draw(case_strategy(target, next(counter))))

    draw()
    out.close()
    return 0


def fuzz(plan: dict[str, int], seed: int = 0, findings: Path | None = None, progress: bool = False,
         log: Path | None = None, hang_s: float = HANG_S, memory_mb: int = MEMORY_MB) -> Counts:
    """Run ``plan`` (target -> number of cases) in a worker subprocess; the counts, and every finding kept
    under ``findings`` (when given)."""
    counts = Counts()
    sup = Supervisor(log=log, hang_s=hang_s, memory_mb=memory_mb)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=sum(plan.values()), unit="case", dynamic_ncols=True)
    t0 = time.perf_counter()

    def flush(batch: list[Case]) -> None:
        for case, res in sup.run(batch):
            counts.add(case, res)
            if res["verdict"] in FINDINGS:
                counts.findings.append({"target": case.target, "index": case.index, "how": case.how,
                                        "argv": case.argv, "call": repr(case.call), **res})
                if findings is not None:
                    counts.findings[-1]["kept"] = str(keep_finding(findings, case, res, seed))
            if bar is not None:
                bar.update(1)
                bar.set_postfix(target=case.target, findings=counts.n_findings(), refresh=False)
        batch.clear()

    try:
        for target, n in plan.items():
            if target not in TARGETS:
                raise ValueError(f"plan: unknown target {target!r}; expected some of {list(TARGETS)}")
            batch: list[Case] = []

            def take(case: Case, batch=batch) -> None:
                batch.append(case)
                if len(batch) >= BATCH:
                    flush(batch)

            each_case(target, n, seed, take)
            flush(batch)
    finally:
        sup.close()
        if bar is not None:
            bar.close()
    counts.restarts = sup.restarts
    counts.wall_s = time.perf_counter() - t0
    return counts


def counts_table(counts: Counts) -> str:
    """The counts as a markdown table: one row per target and a total."""
    cols = ["ok", "ValueError", "TypeError", "OSError", "refused", *FINDINGS]
    header = ["target", "cases", *cols, "cases with warnings", "mean ms", "max s"]
    rows, tot = [], Counter()
    for t in [t for t in TARGETS if t in counts.verdicts]:
        v = counts.verdicts[t]
        n = sum(v.values())
        s = counts.secs[t]
        nw = sum(counts.warnings.get(t, Counter()).values())
        rows.append([t, n, *(v.get(c, 0) for c in cols), nw, f"{1000 * sum(s) / max(n, 1):.1f}", f"{max(s):.2f}"])
        tot.update(v)
        tot["cases"] += n
        tot["warn"] += nw
    rows.append(["**all**", tot["cases"], *(tot.get(c, 0) for c in cols), tot["warn"], "", ""])
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(str(x) for x in r) + " |" for r in rows]
    return "\n".join(lines)


def plan_for(total: int, targets: tuple[str, ...] = TARGETS) -> dict[str, int]:
    """``total`` cases split over ``targets`` by fixed weights (GeoTIFF most: the most code behind it)."""
    weights = {"png": 17, "tiff": 17, "geotiff": 20, "npy": 15, "toml": 18, "cli": 13}
    w = {t: weights[t] for t in targets}
    plan = {t: total * w[t] // sum(w.values()) for t in targets}
    plan[targets[0]] += total - sum(plan.values())
    return plan


if __name__ == "__main__":
    if sys.argv[1:] == ["--worker"]:
        sys.exit(worker_main())
    if len(sys.argv) == 5 and sys.argv[1] == "--generate":
        sys.exit(_generate(sys.argv[2], int(sys.argv[3]), int(sys.argv[4])))
    print("usage: python tests/fuzz_runner.py --worker | --generate TARGET N SEED (started by the fuzz supervisor)",
          file=sys.stderr)
    sys.exit(2)


"""File output helpers: every file is written to a temporary name in its folder and renamed into
place, so an interrupted or failed write never leaves a partial file behind; and a set of files written
together (a frame's images and report, a sweep's table, plot and summary) is committed at once when every
one of them is written (:func:`output_set`), so a failure leaves the previous set whole. Also strict JSON
(:func:`strict_json`, what :func:`write_json` writes: no ``Infinity`` or ``NaN`` token, a ``null`` with its
reason beside it), the one digest of arrays that determinism checks compare, and the one way figures are
saved.

What an output set guarantees, at any instant a process may die:

* **Before the commit** (files being written): the new files exist only under temporary names
  (``.NAME.tmpPID-N.EXT``); the folder's files are the previous set, whole.
* **The commit** writes a commit record, ``.terrainwarp-commit.json`` (under a temporary name, then renamed:
  the rename is the commit point), naming every rename to make; then renames each file into place and removes
  the record. A catchable signal (SIGINT, SIGTERM, SIGHUP through :func:`interrupt_handler`) that arrives
  during the commit waits until it is done (:func:`interrupts_deferred`): the set is then the new one, whole.
* **Killed in the commit** (SIGKILL, power): the record is there, and :func:`recover` (which every
  ``terrainwarp`` command runs on its ``--out`` before it starts) finishes the renames it names: the new set,
  whole. A reader that finds the record knows the set is being switched and may call :func:`recover` itself.
* **Killed before the commit**: :func:`recover` removes the temporaries that the dead process left
  (``.NAME.tmpPID-N.EXT`` of a process that is gone); the previous set is untouched.

A write that runs out of space says so, naming the file and the size it needed: ``OSError(ENOSPC,
"no space left on device writing depth.exr (8.3 MB)", path)``."""

from __future__ import annotations

import contextlib
import errno
import hashlib
import itertools
import json
import math
import os
import re
import shutil
import signal
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .memory import format_bytes
from .native import native_stderr_silenced

if TYPE_CHECKING:
    from matplotlib.figure import Figure

_IMAGE_EXTS = {".png", ".tif", ".tiff", ".exr", ".jpg", ".jpeg", ".bmp"}


_NO_SPACE = (errno.ENOSPC, errno.EDQUOT)
_SEQ = itertools.count()
COMMIT_RECORD = ".terrainwarp-commit.json"  # present only while an output set is being switched
TEMP_PATTERN = re.compile(r"^\..*\.tmp(\d+)-\d+(\.[^.]*)?$")  # temp_path's names; group 1: the writer's PID
_SETS: list[OutputSet] = []  # the output sets open now, innermost last
_SETS_LOCK = threading.Lock()


def temp_path(path: str | os.PathLike) -> Path:
    """A fresh temporary name beside ``path`` (``.NAME.tmpPID-N.EXT``: hidden, same extension, the writer's
    process id, which :func:`recover` reads to tell a dead writer's leftovers from a live one's files)."""
    p = Path(path)
    return p.with_name(f".{p.stem}.tmp{os.getpid()}-{next(_SEQ)}{p.suffix}")


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's process: alive
        return True
    return True


# ------------------------------------------------------------------------------------------------
# signals: a commit is never cut short by SIGINT, SIGTERM or SIGHUP
# ------------------------------------------------------------------------------------------------
class Interrupted(KeyboardInterrupt):
    """SIGINT, SIGTERM or SIGHUP, raised by :func:`interrupt_handler` (a KeyboardInterrupt: what Ctrl-C
    raises). ``signum``: the signal."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


_DEFER = {"depth": 0, "pending": None}
_DEFER_LOCK = threading.Lock()


def interrupt_handler(signum: int, frame: object) -> None:
    """A signal handler (``signal.signal(SIGTERM, interrupt_handler)``; the ``terrainwarp`` command installs it
    for SIGINT, SIGTERM and SIGHUP): raises :class:`Interrupted`, or, inside :func:`interrupts_deferred` (an
    output set's commit), keeps the signal and raises it when the block ends."""
    with _DEFER_LOCK:
        if _DEFER["depth"]:
            _DEFER["pending"] = _DEFER["pending"] or signum
            return
    raise Interrupted(signum)


@contextlib.contextmanager
def interrupts_deferred() -> Iterator[None]:
    """Hold back :func:`interrupt_handler`'s signals for the block; one that arrived is raised as it ends."""
    with _DEFER_LOCK:
        _DEFER["depth"] += 1
    try:
        yield
    finally:
        with _DEFER_LOCK:
            _DEFER["depth"] -= 1
            pending = _DEFER["pending"] if not _DEFER["depth"] else None
            if pending is not None:
                _DEFER["pending"] = None
        if pending is not None:
            raise Interrupted(pending)


# ------------------------------------------------------------------------------------------------
# output sets
# ------------------------------------------------------------------------------------------------
def no_space_error(path: Path, nbytes: int | None) -> OSError:
    """The error of a write that ran out of space, naming the file and what it needed."""
    size = f" ({format_bytes(nbytes)})" if nbytes else ""
    return OSError(errno.ENOSPC, f"no space left on device writing {path.name}{size}", str(path))


class OutputSet:
    """Files written under ``folder`` as one set (see :func:`output_set`): each write goes to a temporary name
    beside its file, and every one is renamed into place by :meth:`commit`, or removed by :meth:`abort`."""

    def __init__(self, folder: str | os.PathLike) -> None:
        self.folder = Path(folder).absolute()
        self.pending: dict[Path, Path] = {}  # final path -> temporary file holding it
        self.removals: list[Path] = []  # files removed only when the set is in place (a sweep's journal)
        self.committed = False  # True once the set is in place (handed to an outer set, or switched)

    def covers(self, path: Path) -> bool:
        return Path(path).absolute().is_relative_to(self.folder)

    def add(self, path: Path, tmp: Path) -> None:
        old = self.pending.pop(Path(path).absolute(), None)
        if old is not None and old != tmp:
            with contextlib.suppress(OSError):
                old.unlink()
        self.pending[Path(path).absolute()] = tmp

    def commit(self) -> list[Path]:
        """Put every pending file in place and make the deferred removals, at once (an outer set takes them over
        instead): a commit record naming the renames is renamed into the folder (the commit point), the files
        are renamed, the record removed; interrupts wait meanwhile (:func:`interrupts_deferred`), and a process
        killed in between leaves the record for :func:`recover` to finish. Returns the paths put in place."""
        outer = _outer(self)
        done = list(self.pending)
        if outer is not None:
            for final, tmp in list(self.pending.items()):
                if outer.covers(final):
                    outer.add(final, tmp)
                    del self.pending[final]
            outer.removals += [p for p in self.removals if outer.covers(p)]
            self.removals = [p for p in self.removals if not outer.covers(p)]
        moves, removals = list(self.pending.items()), list(self.removals)
        self.pending.clear()
        self.removals.clear()
        if moves or removals:
            with interrupts_deferred():  # a signal meanwhile is raised once the set is whole (committed)
                _switch(self.folder, moves, removals)
                self.committed = True
        self.committed = True
        return done

    def abort(self) -> None:
        """Remove every pending temporary file: the files in place stay as they were."""
        for tmp in self.pending.values():
            with contextlib.suppress(OSError):
                tmp.unlink()
        self.pending.clear()
        self.removals.clear()


def _rel(folder: Path, p: Path) -> str:
    return os.path.relpath(p, folder)


def _switch(folder: Path, moves: list[tuple[Path, Path]], removals: list[Path]) -> None:
    """Commit a set: the record, then the renames and removals, then the record removed."""
    record = folder / COMMIT_RECORD
    body = {"version": 1, "moves": [[_rel(folder, tmp), _rel(folder, final)] for final, tmp in moves],
            "removals": [_rel(folder, p) for p in removals]}
    tmp = temp_path(record)
    try:
        with open(tmp, "w") as f:
            f.write(json.dumps(body) + "\n")
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, record)  # the commit point
    except OSError as e:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if e.errno in _NO_SPACE:
            raise no_space_error(record, None) from None
        raise
    _roll_forward(folder, body)
    record.unlink()


def _roll_forward(folder: Path, body: dict) -> None:
    for tmp, final in body["moves"]:
        with contextlib.suppress(FileNotFoundError):  # moved already (a recovery after a kill mid-way)
            os.replace(folder / tmp, folder / final)
    for p in body["removals"]:
        with contextlib.suppress(FileNotFoundError):
            (folder / p).unlink()


def recover(folder: str | os.PathLike, depth: int = 2) -> dict[str, list[str]]:
    """Make ``folder`` a whole set again after a process died writing it: finish a commit its record names
    (every rename it lists, then the record removed), and remove the temporaries (``.NAME.tmpPID-N.EXT``, in
    ``folder`` and ``depth - 1`` levels below) of processes that are gone. Returns ``{"committed": [files put in
    place], "removed": [temporaries removed]}`` (paths relative to ``folder``)."""
    root = Path(folder)
    done: dict[str, list[str]] = {"committed": [], "removed": []}
    if not root.is_dir():
        return done
    record = root / COMMIT_RECORD
    try:
        body = json.loads(record.read_text())
        body = {"moves": [(str(a), str(b)) for a, b in body["moves"]],
                "removals": [str(p) for p in body.get("removals", [])]}
    except (OSError, ValueError, KeyError, TypeError):  # none (a record is renamed into place whole, or not)
        body = None
    if body is not None:
        done["committed"] = [final for tmp, final in body["moves"] if (root / tmp).exists()]
        _roll_forward(root, body)
        record.unlink()
    level = [root]
    for _ in range(depth):
        found = [c for d in level for c in sorted(d.iterdir())]
        for f in found:
            m = TEMP_PATTERN.match(f.name)
            if m and f.is_file() and not f.is_symlink() and not _alive(int(m.group(1))):
                with contextlib.suppress(OSError):
                    f.unlink()
                    done["removed"].append(_rel(root, f))
        level = [c for c in found if c.is_dir() and not c.is_symlink()]
    return done


def _outer(s: OutputSet) -> OutputSet | None:
    with _SETS_LOCK:
        i = _SETS.index(s) if s in _SETS else len(_SETS)
        return next((o for o in reversed(_SETS[:i]) if o.covers(s.folder)), None)


def _set_for(path: Path) -> OutputSet | None:
    with _SETS_LOCK:
        return next((s for s in reversed(_SETS) if s.covers(path)), None)


@contextlib.contextmanager
def output_set(folder: str | os.PathLike) -> Iterator[OutputSet]:
    """Write a set of files under ``folder`` as a whole: inside the block, every write through
    :func:`atomic_path` (so every ``write_*`` here and :func:`save_figure`) to a path under ``folder`` goes to a
    temporary name, and all of them are committed at once when the block ends without an error
    (:meth:`OutputSet.commit`; into an enclosing set's care, when sets are nested). When it raises (an error, a
    full disk, Ctrl-C), the temporary files are removed and the files in ``folder`` are left as they were: the
    previous set stays whole and nothing new is left. What holds when a process is killed: the module
    docstring."""
    s = OutputSet(folder)
    with _SETS_LOCK:
        _SETS.append(s)
    try:
        yield s
    except BaseException:
        s.abort()
        raise
    else:
        s.commit()
    finally:
        with _SETS_LOCK:
            _SETS.remove(s)


def remove_when_written(path: str | os.PathLike) -> None:
    """Remove ``path`` now, or, inside an :func:`output_set` that covers it, once the set is in place (a sweep's
    journal goes only when its table is written, so an interrupted run can resume)."""
    p = Path(path)
    s = _set_for(p)
    if s is not None:
        s.removals.append(p)
    else:
        with contextlib.suppress(FileNotFoundError):
            p.unlink()


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, nbytes: int | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (same extension); rename it to ``path`` on success (inside an
    :func:`output_set` covering ``path``: when the set is written), remove it on failure. A write that runs out
    of space raises :func:`no_space_error` (``nbytes``: what it needed, when known)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path(p)
    s = _set_for(p)
    try:
        yield tmp
        if s is not None:
            s.add(p, tmp)
            tmp = None
        else:
            os.replace(tmp, p)
    except OSError as e:
        if e.errno in _NO_SPACE:
            raise no_space_error(p, nbytes) from None
        raise
    finally:
        # the cleanup never hides the real error (a read-only filesystem fails the unlink too)
        if tmp is not None:
            with contextlib.suppress(OSError):
                tmp.unlink()


def _out_of_space(p: Path, nbytes: int) -> bool:
    """After a library's write failed with no error number (OpenImageIO): is the folder out of space for it?"""
    try:
        return shutil.disk_usage(p.parent).free < nbytes
    except OSError:
        return False


def write_image(path: str | os.PathLike, a: np.ndarray) -> Path:
    """Write an (H, W) or (H, W, C) uint8, uint16 or float32 array through OpenImageIO; row 0 is the
    top of the image. EXR files are zip-compressed (lossless) float32. The file holds no timestamp: the
    same array gives the same bytes on every run."""
    import OpenImageIO as oiio  # lazy: heavy optional dependency

    p = Path(path)
    ext = p.suffix.lower()
    if ext not in _IMAGE_EXTS:
        raise ValueError(f"path: unsupported image extension {ext!r} (expected one of {sorted(_IMAGE_EXTS)})")
    fmts = {np.dtype(np.uint8): oiio.UINT8, np.dtype(np.uint16): oiio.UINT16,
            np.dtype(np.float32): oiio.FLOAT, np.dtype(np.int32): oiio.INT32}
    if a.dtype not in fmts:
        raise TypeError(f"a: expected uint8, uint16, int32 or float32 pixels, got {a.dtype}")
    nch = 1 if a.ndim == 2 else a.shape[2]
    spec = oiio.ImageSpec(a.shape[1], a.shape[0], nch, fmts[a.dtype])
    # OpenImageIO stamps EXR and TIFF files with the time of writing (a DateTime header); an empty value
    # leaves it out, so the same pixels always give the same bytes.
    spec.attribute("DateTime", "")
    if ext == ".exr":
        spec.attribute("compression", "zip")
    with atomic_path(p, a.nbytes) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise ValueError(f"path: cannot write {p}: {oiio.geterror()}")
        try:
            ok = out.open(str(tmp), spec) and out.write_image(np.ascontiguousarray(a).reshape(a.shape[0], a.shape[1],
                                                                                                nch))
            err = out.geterror()
        except BaseException:  # interrupted (Ctrl-C): libpng would complain of the unfinished file on stderr
            with native_stderr_silenced():
                out.close()
            raise
        closed = out.close()
        if not ok or not closed:
            if _out_of_space(p, a.nbytes):
                raise no_space_error(p, a.nbytes)
            raise OSError(errno.EIO, f"writing {p.name} failed: {err or out.geterror() or 'OpenImageIO error'}", str(p))
    return p


def write_json(path: str | os.PathLike, obj: object) -> Path:
    """Write ``obj`` as strict JSON (:func:`strict_json`: RFC 8259, no ``Infinity``/``NaN``), indented."""
    return write_text(path, dumps_strict(obj, indent=2) + "\n")


def dumps_strict(obj: object, **kw: Any) -> str:
    """``json.dumps`` of :func:`strict_json` ``(obj)``, refusing any non-finite number left (``allow_nan=False``)."""
    return json.dumps(strict_json(obj), allow_nan=False, **kw)


#: What a ``null`` stands for in strict JSON, by the key it sits at (an exact key, else the key's suffix, else
#: any key) and the value it replaces (``inf``, ``-inf``, ``nan``): the text of its ``<key>_reason`` sibling.
NULL_REASONS: dict[tuple[str, str], str] = {
    ("psnr_db", "inf"): "inf: the images are identical (PSNR is infinite)",
    ("_px", "inf"): "inf: unbounded (visible heightmap samples were left undrawn, or a point lay behind the eye)",
    ("cost", "inf"): "inf: no setting was measured to meet the budget",
    ("r2_heldout", "nan"): "nan: undefined (the held-out frames' times do not vary, or no frame was held out)",
    ("", "inf"): "inf: infinite",
    ("", "-inf"): "-inf: minus infinity",
    ("", "nan"): "nan: not measured or undefined (e.g. popping of a path's first frame, an empty mean)",
}


def _null_reason(key: str, kind: str) -> str:
    for k in (key, *(suffix for suffix in ("_px", "cost") if key.endswith(suffix)), ""):
        if (k, kind) in NULL_REASONS:
            return NULL_REASONS[(k, kind)]
    return kind  # pragma: no cover - every kind has a catch-all


def strict_json(obj: object) -> object:
    """``obj`` as plain JSON values (numpy scalars and arrays, paths, tuples converted) with every non-finite
    float replaced by ``None`` and its reason in a sibling field: in a dict, key ``k`` whose value is +-inf or
    NaN becomes ``null`` and gains ``k_reason`` (:data:`NULL_REASONS`: what it stood for); a list under key
    ``k`` with such entries gains ``k_reason`` naming them ("entries 0, 3: inf: ..."). What JSON parsers
    everywhere read (Node's ``JSON.parse``, jq, Go's ``encoding/json``)."""
    return _strict(obj, "")[0]


def _strict(o: object, key: str) -> tuple[object, str | None]:
    if isinstance(o, (np.generic, np.ndarray, Path)) and not isinstance(o, np.bool_):
        o = _json_default(o)
    if isinstance(o, float):
        if math.isfinite(o):
            return o, None
        kind = "nan" if math.isnan(o) else "inf" if o > 0 else "-inf"
        return None, _null_reason(key, kind)
    if isinstance(o, dict):
        out: dict = {}
        for k, v in o.items():
            out[k], why = _strict(v, str(k))
            if why is not None:
                out[f"{k}_reason"] = why
        return out, None
    if isinstance(o, (list, tuple)):
        items = [_strict(v, key) for v in o]
        bad: dict[str, list[int]] = {}
        for i, (_, why) in enumerate(items):
            if why is not None:
                bad.setdefault(why, []).append(i)
        why = "; ".join(f"entr{'y' if len(ix) == 1 else 'ies'} {', '.join(map(str, ix[:20]))}"
                        f"{' ...' if len(ix) > 20 else ''}: {w}" for w, ix in bad.items()) or None
        return [v for v, _ in items], why
    if isinstance(o, np.bool_):
        return bool(o), None
    return o, None


def write_text(path: str | os.PathLike, text: str) -> Path:
    p = Path(path)
    data = text.encode()
    with atomic_path(p, len(data)) as tmp:
        tmp.write_bytes(data)
    return p


def _json_default(o: object) -> object:
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def digest(*arrays: object) -> str:
    """The SHA-256 (hex) of arrays' dtypes, shapes and bytes: what determinism checks and golden tests
    compare across runs and thread counts. None is hashed as a marker."""
    h = hashlib.sha256()
    for a in arrays:
        if a is None:
            h.update(b"None")
            continue
        a = np.ascontiguousarray(a)
        h.update(str(a.dtype).encode() + str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def new_figure(nrows: int = 1, ncols: int = 1, *, squeeze: bool = True, **figure_kw: object) -> tuple[Figure, object]:
    """A matplotlib figure and its axes, as ``plt.subplots(nrows, ncols)`` gives them, made without pyplot: no
    backend is chosen or switched and nothing is registered with pyplot, so the caller's backend and figures are
    as they were (a notebook's inline plots keep working). ``squeeze`` as for ``plt.subplots``; ``figure_kw`` go to
    ``Figure`` (``figsize``, ...); :func:`save_figure` writes it."""
    from matplotlib.figure import Figure  # lazy: heavy optional dependency

    fig = Figure(**figure_kw)
    return fig, fig.subplots(nrows, ncols, squeeze=squeeze)


def save_figure(fig: Figure, path: str | os.PathLike, *, dpi: float = 100, **savefig_kw: object) -> Path:
    """Save a matplotlib figure atomically (format from the suffix, PNG by default) and release it from
    pyplot if pyplot made it. No timestamp is written: the same figure gives the same bytes. Returns the
    path."""
    import matplotlib  # lazy: heavy optional dependency

    p = Path(path)
    fmt = p.suffix.lstrip(".").lower() or "png"
    # No creation date in PDF/SVG/PS files and fixed SVG element ids: the same figure, the same bytes.
    undated = {"pdf": {"CreationDate": None}, "svg": {"Date": None}, "ps": {"CreationDate": None},
               "eps": {"CreationDate": None}}
    if fmt in undated:
        savefig_kw.setdefault("metadata", undated[fmt])
    with atomic_path(p) as tmp, matplotlib.rc_context({"svg.hashsalt": "terrainwarp"}):
        fig.savefig(tmp, format=fmt, dpi=dpi, **savefig_kw)  # (ENOSPC from savefig: named by atomic_path)
    if getattr(fig.canvas, "manager", None) is not None:  # made by pyplot: let pyplot forget it
        import matplotlib.pyplot as plt  # lazy: heavy optional dependency

        plt.close(fig)
    return p

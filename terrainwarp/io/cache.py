"""Cache folders that check themselves and that many threads and processes can share.

A :class:`CacheFolder` holds the files derived from one source file (a GeoTIFF's pyramids and overviews, its
height range) and a manifest, ``manifest.json``, that names each file with its size and its xxHash3 (64 bit)
digest, the source's fingerprint and small values; the manifest carries a digest of itself. So:

* **The cache sees every edit of its source**: the fingerprint is a SHA-256 of the source file's whole content
  (:func:`content_digest`), worked out once and kept beside the cache (``source.json``) with the file's size,
  modification time, change time (``ctime``, which no tool can set back) and inode; it is worked out again
  whenever one of those differs. An edit that keeps the size and sets the modification time back changes the
  change time, so the content is hashed again and the cache rebuilt.
* **A file is used only once it checks out**: its size and digest equal the manifest's (on first use in a
  process; again whenever the file on disk changes). A tiled file (:class:`TiledArray`: the overviews, the
  bulk of a cache) is checked **tile by tile as each tile is read**, against a digest per tile (its digest
  file is checked whole: 8 bytes a tile), never whole on open; a tile that fails its check is reported
  (:class:`CorruptTile`) and the file removed, so the next open rebuilds it. A missing, truncated or corrupt
  file, or a corrupt manifest, is rebuilt; where it cannot be (a read-only folder), the error names the file
  and what is wrong with it.
* **Builders never race**: a build holds the folder's lock, a thread lock per folder in this process and an
  exclusive ``fcntl.flock`` on ``<folder>/lock`` across processes, and checks again under it (another worker
  may have finished the same build meanwhile). Readers take the lock shared.
* **Nothing half-written is ever read**: a build writes each file under a temporary name and renames it into
  place (files in place are never rewritten, so a memory map of one stays valid while it is replaced), then
  writes the manifest the same way.

Everything here is about files; what the files hold is the caller's (:mod:`terrainwarp.lod.streaming`).
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import io
import itertools
import json
import os
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import xxhash

__all__ = ["CacheFolder", "CacheError", "CorruptTile", "TiledArray", "TiledWriter", "file_digest", "content_digest",
           "MANIFEST", "MANIFEST_VERSION", "SOURCE_RECORD"]

MANIFEST = "manifest.json"
MANIFEST_VERSION = 4  # 4: overviews end on the grid's clamped last row and column
SOURCE_RECORD = "source.json"  # the source file's content digest and the stat it was worked out for
_SEQ = itertools.count()
_CHUNK = 16 << 20  # bytes hashed at a time (the file is read, not mapped: a truncation cannot fault)

_THREAD_LOCKS: dict[str, threading.RLock] = {}
_THREAD_LOCKS_GUARD = threading.Lock()
_VERIFIED: dict[tuple, str] = {}  # (path, inode, size, mtime_ns) -> digest, checked once per process
_VERIFIED_GUARD = threading.Lock()


class CacheError(ValueError):
    """A cache file that fails its check and cannot be rebuilt (named in the message)."""


class CorruptTile(CacheError):
    """A tile of a :class:`TiledArray` whose bytes do not match its digest (the file is removed: the next open
    rebuilds it)."""


_CONTENT: dict[tuple, str] = {}  # (path, stat key) -> the content digest, worked out once per process
_CONTENT_GUARD = threading.Lock()


def _stat_key(st: os.stat_result) -> list[int]:
    return [st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino, st.st_dev]


def content_digest(path: str | os.PathLike, record_dir: str | os.PathLike | None = None) -> str:
    """The SHA-256 (hex) of a file's whole content, worked out once: kept in this process and in
    ``record_dir/source.json`` (when given and writable) with the file's size, modification and change times,
    inode and device, and used while all five are the same; worked out again (one read of the file) as soon as
    one differs. The change time moves on every write and every ``utime``, so an in-place edit that restores the
    size and the modification time is seen."""
    p = Path(path)
    key = _stat_key(p.stat())
    memo = (str(p.resolve()), *key)
    with _CONTENT_GUARD:
        got = _CONTENT.get(memo)
    if got is not None:
        return got
    record = Path(record_dir) / SOURCE_RECORD if record_dir is not None else None
    with contextlib.suppress(OSError, ValueError, TypeError, KeyError):
        doc = json.loads(record.read_text()) if record is not None else {}
        if doc.get("stat") == key and isinstance(doc.get("sha256"), str):
            got = doc["sha256"]
    if got is None:
        h, buf = hashlib.sha256(), bytearray(1 << 20)  # read 1 MiB at a time into one buffer
        view = memoryview(buf)
        with open(p, "rb", buffering=0) as f:
            while n := f.readinto(buf):
                h.update(view[:n])
        got = h.hexdigest()
        if key != _stat_key(p.stat()):  # changed while it was read: not a digest of any one version
            return content_digest(p, record_dir)
        if record is not None:
            with contextlib.suppress(OSError):
                record.parent.mkdir(parents=True, exist_ok=True)
                tmp = record.with_name(f".{record.stem}.tmp{os.getpid()}-{next(_SEQ)}{record.suffix}")
                tmp.write_text(json.dumps({"path": str(p.resolve()), "stat": key, "sha256": got}) + "\n")
                os.replace(tmp, record)
    with _CONTENT_GUARD:
        _CONTENT[memo] = got
    return got


def file_digest(path: str | os.PathLike) -> str:
    """The xxHash3 64-bit digest (hex) of a file's bytes."""
    h = xxhash.xxh3_64()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def _manifest_digest(body: dict) -> str:
    return xxhash.xxh3_64(json.dumps(body, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


class CacheFolder:
    """One cache folder (created on first build). ``fingerprint`` identifies the source's bytes: a manifest of
    another fingerprint (the file changed) is started afresh, its files removed."""

    def __init__(self, path: str | os.PathLike, fingerprint: str):
        self.path = Path(path)
        self.fingerprint = str(fingerprint)

    # -- locks ------------------------------------------------------------------------------------
    def _thread_lock(self) -> threading.RLock:
        key = str(self.path.absolute())
        with _THREAD_LOCKS_GUARD:
            return _THREAD_LOCKS.setdefault(key, threading.RLock())

    @contextlib.contextmanager
    def locked(self, exclusive: bool) -> Iterator[None]:
        """Hold the folder: this process's lock for it, and ``flock`` on ``<folder>/lock`` (exclusive to build,
        shared to read). A folder that does not exist yet is created for an exclusive hold; a shared hold of a
        missing folder, or of one where no lock file can be made (read-only), holds the thread lock only."""
        with self._thread_lock():
            fd = None
            try:
                if exclusive:
                    self.path.mkdir(parents=True, exist_ok=True)
                fd = os.open(self.path / "lock", os.O_RDWR | os.O_CREAT, 0o666)
            except OSError:
                if exclusive:
                    raise
            try:
                if fd is not None:
                    fcntl.flock(fd, fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH)
                yield
            finally:
                if fd is not None:
                    os.close(fd)  # closing the descriptor releases the flock

    # -- the manifest -----------------------------------------------------------------------------
    def manifest(self) -> dict[str, Any] | None:
        """The manifest if it is intact and of this fingerprint and version, else None."""
        try:
            doc = json.loads((self.path / MANIFEST).read_text())
            body, digest = doc["body"], doc["digest"]
        except (OSError, ValueError, KeyError, TypeError):
            return None
        if not isinstance(body, dict) or _manifest_digest(body) != digest:
            return None
        if body.get("version") != MANIFEST_VERSION or body.get("fingerprint") != self.fingerprint:
            return None
        if not isinstance(body.get("files"), dict) or not isinstance(body.get("values"), dict):
            return None
        return body

    def write_manifest(self, body: dict) -> None:
        """Write the manifest (a temporary file renamed into place)."""
        tmp = self.path / f".{MANIFEST}.tmp{os.getpid()}-{next(_SEQ)}"
        try:
            tmp.write_text(json.dumps({"body": body, "digest": _manifest_digest(body)}, indent=1, sort_keys=True)
                           + "\n")
            os.replace(tmp, self.path / MANIFEST)
        finally:
            with contextlib.suppress(OSError):
                tmp.unlink()

    def fresh_body(self) -> dict:
        return {"version": MANIFEST_VERSION, "fingerprint": self.fingerprint, "files": {}, "values": {}}

    # -- checking ---------------------------------------------------------------------------------
    def problem(self, name: str, body: dict | None) -> str | None:
        """What is wrong with file ``name`` against the manifest ``body`` (None: it checks out)."""
        if body is None:
            return "the cache's manifest is missing, corrupt or of another version of the source"
        entry = body["files"].get(name)
        if entry is None:
            return "not in the cache's manifest"
        p = self.path / name
        try:
            st = p.stat()
        except OSError:
            return "missing"
        if st.st_size != entry.get("bytes"):
            return f"{st.st_size} bytes, expected {entry.get('bytes')} (truncated or overwritten)"
        if "tiles" in entry:  # checked tile by tile as read; here its tiles' digests, whole
            digests = entry.get("digests")
            bad = self.problem(digests, body) if isinstance(digests, str) else "no tile digests"
            return None if bad is None else f"its tile digests ({digests}): {bad}"
        key = (str(p.absolute()), st.st_ino, st.st_size, st.st_mtime_ns)
        with _VERIFIED_GUARD:
            got = _VERIFIED.get(key)
        if got is None:
            try:
                got = file_digest(p)
            except OSError as e:
                return f"unreadable ({e.strerror or e})"
            with _VERIFIED_GUARD:
                _VERIFIED[key] = got
        if got != entry.get("xxh3"):
            return "its checksum does not match the manifest's (corrupt)"
        return None

    def check(self, names: list[str]) -> dict[str, str]:
        """``{name: problem}`` for each of ``names`` that does not check out (empty: all good), under a shared
        hold of the folder."""
        with self.locked(exclusive=False):
            body = self.manifest()
            return {n: p for n in names if (p := self.problem(n, body)) is not None}

    def tiled(self, name: str, body: dict | None = None) -> TiledArray:
        """The tiled file ``name`` (checked by :meth:`check` first), read tile by tile and checked as read."""
        body = self.manifest() if body is None else body
        entry = None if body is None else body["files"].get(name)
        if entry is None or "tiles" not in entry:
            raise CacheError(f"{self.path / name}: not a tiled file of the cache's manifest")
        digests = np.load(self.path / entry["digests"])
        return TiledArray(self.path / name, tuple(entry["tiles"]), tuple(entry["shape"]), digests)

    def value(self, key: str) -> Any:
        """A small value kept in the manifest (None when absent or the manifest does not check out)."""
        with self.locked(exclusive=False):
            body = self.manifest()
        return None if body is None else body["values"].get(key)

    # -- building ---------------------------------------------------------------------------------
    @contextlib.contextmanager
    def building(self) -> Iterator[_Build]:
        """An exclusive hold for a build: ``b.todo(names)`` says which files still need building (another
        worker may have built them while this one waited), ``b.path(name)`` gives a temporary path to write one
        to, ``b.set_value(key, v)`` keeps a small value; on leaving the block without an error the files are
        renamed into place and the manifest written, after every file is written. On an error nothing in
        place changes. An unwritable folder raises ``OSError`` naming it."""
        with self.locked(exclusive=True):
            b = _Build(self)
            try:
                yield b
                b.publish()
            finally:
                b.discard()


class _Build:
    """One build under an exclusive hold (see :meth:`CacheFolder.building`)."""

    def __init__(self, folder: CacheFolder):
        self.folder = folder
        body = folder.manifest()
        if body is None:  # another version of the source, or no manifest yet: nothing in the folder is valid
            body = folder.fresh_body()
            for f in folder.path.iterdir() if folder.path.is_dir() else ():
                if f.name not in ("lock", SOURCE_RECORD) and f.is_file():
                    with contextlib.suppress(OSError):
                        f.unlink()
        self.body = body
        self.written: dict[str, Path] = {}
        self.tiled_files: dict[str, TiledWriter] = {}

    def todo(self, names: list[str]) -> list[str]:
        """The files of ``names`` that do not check out now (to build)."""
        return [n for n in names if self.folder.problem(n, self.body) is not None]

    def path(self, name: str) -> Path:
        """A temporary path for file ``name`` in the folder (renamed into place when the build is published)."""
        tmp = self.folder.path / f".{name}.tmp{os.getpid()}-{next(_SEQ)}"
        self.written[name] = tmp
        return tmp

    def set_value(self, key: str, value: Any) -> None:
        self.body["values"][key] = value

    def tiled(self, name: str, shape: tuple[int, int], tile: int) -> TiledWriter:
        """A writer of the tiled file ``name`` (a float32 grid of ``shape`` as tiles of ``tile + 1`` samples a
        side, neighbours sharing an edge): tiles are written as they are made, with a digest each, and the file
        and its digests are put in place with the build."""
        w = TiledWriter(self.path(name), shape, tile)
        self.tiled_files[name] = w
        return w

    def publish(self) -> None:
        """Checksum every file written (a tiled file: its tiles' digests, kept in a file of their own), rename
        each into place, then write the manifest."""
        for name, w in self.tiled_files.items():
            digests = f"{name}.xxh3.npy"
            with open(self.path(digests), "wb") as f:
                np.save(f, w.finish())
            self.body["files"][name] = {"bytes": None, "tiles": list(w.grid), "shape": list(w.shape),
                                        "digests": digests}
        self.tiled_files.clear()
        for name, tmp in self.written.items():
            if "tiles" in self.body["files"].get(name, {}):
                self.body["files"][name]["bytes"] = tmp.stat().st_size
                continue
            self.body["files"][name] = {"bytes": tmp.stat().st_size, "xxh3": file_digest(tmp)}
        for name, tmp in self.written.items():
            os.replace(tmp, self.folder.path / name)
        self.written.clear()
        self.folder.write_manifest(self.body)

    def discard(self) -> None:
        for tmp in self.written.values():
            with contextlib.suppress(OSError):
                tmp.unlink()
        self.written.clear()


# ------------------------------------------------------------------------------------------------
# tiled files: written tile by tile, checked tile by tile
# ------------------------------------------------------------------------------------------------
class TiledWriter:
    """Writes a float32 (rows, cols) grid as tiles of ``tile + 1`` samples a side (tile (i, j) holds samples
    ``i * tile .. i * tile + tile`` x ``j * tile .. j * tile + tile``; neighbours share a row or column; NaN past
    the grid) into a ``.npy`` of shape (tile rows, tile columns, tile + 1, tile + 1), one tile at a time with
    ``os.pwrite`` (nothing of the file is mapped or held), recording each tile's xxHash3 digest."""

    def __init__(self, path: Path, shape: tuple[int, int], tile: int):
        self.shape, self.tile = (int(shape[0]), int(shape[1])), int(tile)
        self.grid = ((self.shape[0] - 2) // tile + 1 if self.shape[0] > 1 else 1,
                     (self.shape[1] - 2) // tile + 1 if self.shape[1] > 1 else 1)
        side = tile + 1
        header = io.BytesIO()
        np.lib.format.write_array_header_1_0(header, {"descr": "<f4", "fortran_order": False,
                                                      "shape": (*self.grid, side, side)})
        self.offset = len(header.getvalue())
        self.tile_bytes = side * side * 4
        self.digests = np.zeros(self.grid, np.uint64)
        self.done = np.zeros(self.grid, bool)
        self.fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o644)
        os.pwrite(self.fd, header.getvalue(), 0)
        os.ftruncate(self.fd, self.offset + self.grid[0] * self.grid[1] * self.tile_bytes)

    def write(self, ti: int, tj: int, samples: np.ndarray) -> None:
        """Tile (ti, tj) from ``samples``: the grid's samples from (ti * tile, tj * tile), at most tile + 1 a
        side (fewer at the grid's far edges; the rest of the tile is NaN)."""
        side = self.tile + 1
        t = np.full((side, side), np.nan, np.float32)
        t[:samples.shape[0], :samples.shape[1]] = samples
        data = t.tobytes()
        os.pwrite(self.fd, data, self.offset + (ti * self.grid[1] + tj) * self.tile_bytes)
        self.digests[ti, tj] = xxhash.xxh3_64_intdigest(data)
        self.done[ti, tj] = True

    def finish(self) -> np.ndarray:
        """Close the file; the tiles' digests (every tile must have been written)."""
        os.fsync(self.fd)
        os.close(self.fd)
        if not self.done.all():
            raise CacheError(f"tiled file: tiles {np.argwhere(~self.done)[:4].tolist()} were never written")
        return self.digests


class TiledArray:
    """A tiled file of a cache (:class:`TiledWriter`'s layout) read tile by tile with ``os.pread`` (nothing
    mapped) and checked as read: each tile's bytes against its digest, every read."""

    def __init__(self, path: Path, grid: tuple[int, int], shape: tuple[int, int], digests: np.ndarray):
        self.path, self.grid, self.shape, self.digests = Path(path), grid, shape, digests
        self.tile = None
        with open(self.path, "rb") as f:
            version = np.lib.format.read_magic(f)
            read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else \
                np.lib.format.read_array_header_2_0
            file_shape, _, dtype = read_header(f)
            self.offset = f.tell()
        if dtype != np.float32 or tuple(file_shape[:2]) != tuple(grid) or digests.shape != tuple(grid):
            raise CacheError(f"{self.path}: a {file_shape} {dtype} array, expected {grid} tiles of float32")
        self.side = int(file_shape[2])
        self.tile = self.side - 1
        self.tile_bytes = self.side * self.side * 4

    def read_tile(self, ti: int, tj: int) -> np.ndarray:
        """Tile (ti, tj): (tile + 1, tile + 1) float32, NaN past the grid. Raises :class:`CorruptTile` (and
        removes the file, for the next open to rebuild) when its bytes fail their digest."""
        with open(self.path, "rb") as f:
            data = os.pread(f.fileno(), self.tile_bytes, self.offset + (ti * self.grid[1] + tj) * self.tile_bytes)
        if len(data) != self.tile_bytes or xxhash.xxh3_64_intdigest(data) != int(self.digests[ti, tj]):
            with contextlib.suppress(OSError):
                self.path.unlink()
            raise CorruptTile(f"{self.path}: tile ({ti}, {tj}) does not match its digest (corrupt); the file is "
                              "removed and rebuilt on the next open")
        return np.frombuffer(data, np.float32).reshape(self.side, self.side)

    def window(self, r0: int, c0: int, rows: int, cols: int) -> np.ndarray:
        """(rows, cols) float32 samples of the grid from (r0, c0), assembled from the tiles under it."""
        out = np.empty((rows, cols), np.float32)
        t, (gi, gj) = self.tile, self.grid
        for ti in range(min(r0 // t, gi - 1), min(max(r0, r0 + rows - 2) // t, gi - 1) + 1):
            for tj in range(min(c0 // t, gj - 1), min(max(c0, c0 + cols - 2) // t, gj - 1) + 1):
                tile = self.read_tile(ti, tj)
                a0, b0 = max(r0, ti * t), max(c0, tj * t)
                a1, b1 = min(r0 + rows, ti * t + self.side), min(c0 + cols, tj * t + self.side)
                out[a0 - r0:a1 - r0, b0 - c0:b1 - c0] = tile[a0 - ti * t:a1 - ti * t, b0 - tj * t:b1 - tj * t]
        return out

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        """The whole grid (for small grids and tests: a frame reads windows)."""
        a = self.window(0, 0, *self.shape)
        return a if dtype is None else a.astype(dtype)

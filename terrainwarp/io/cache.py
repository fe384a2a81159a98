"""Cache folders that check themselves and that many threads and processes can share.

A :class:`CacheFolder` holds the files derived from one source file (a GeoTIFF's pyramids and overviews, its
height range) and a manifest, ``manifest.json``, that names each file with its size and its xxHash3 (64 bit)
digest, the source's fingerprint and small values; the manifest carries a digest of itself. So:

* **A file is used only once it checks out**: its size and digest equal the manifest's (every file of a
  layout, on first use in a process; again whenever the file on disk changes). A missing, truncated or
  corrupt file, or a corrupt manifest, is rebuilt; where it cannot be (a read-only folder), the error names
  the file and what is wrong with it.
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
import itertools
import json
import os
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import xxhash

__all__ = ["CacheFolder", "CacheError", "file_digest", "MANIFEST", "MANIFEST_VERSION"]

MANIFEST = "manifest.json"
MANIFEST_VERSION = 2
_SEQ = itertools.count()
_CHUNK = 16 << 20  # bytes hashed at a time (the file is read, not mapped: a truncation cannot fault)

_THREAD_LOCKS: dict[str, threading.RLock] = {}
_THREAD_LOCKS_GUARD = threading.Lock()
_VERIFIED: dict[tuple, str] = {}  # (path, inode, size, mtime_ns) -> digest, checked once per process
_VERIFIED_GUARD = threading.Lock()


class CacheError(ValueError):
    """A cache file that fails its check and cannot be rebuilt (named in the message)."""


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
                if f.name != "lock" and f.is_file():
                    with contextlib.suppress(OSError):
                        f.unlink()
        self.body = body
        self.written: dict[str, Path] = {}

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

    def publish(self) -> None:
        """Checksum every file written, rename each into place, then write the manifest."""
        for name, tmp in self.written.items():
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

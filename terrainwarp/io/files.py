"""File output helpers: every file is written to a temporary name in its folder and renamed into
place, so an interrupted or failed write never leaves a partial file behind. Also the one digest of
arrays that determinism checks compare, and the one way figures are saved."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from matplotlib.figure import Figure

_IMAGE_EXTS = {".png", ".tif", ".tiff", ".exr", ".jpg", ".jpeg", ".bmp"}


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (same extension); rename it to ``path`` on success,
    remove it on failure."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(f".{p.stem}.tmp{os.getpid()}{p.suffix}")
    try:
        yield tmp
        os.replace(tmp, p)
    finally:
        # the cleanup never hides the real error (a read-only filesystem fails the unlink too)
        with contextlib.suppress(OSError):
            tmp.unlink()


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
    with atomic_path(p) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise ValueError(f"path: cannot write {p}: {oiio.geterror()}")
        ok = out.open(str(tmp), spec) and out.write_image(np.ascontiguousarray(a).reshape(a.shape[0], a.shape[1], nch))
        err = out.geterror()
        out.close()
        if not ok:
            raise OSError(f"path: writing {p} failed: {err}")
    return p


def write_json(path: str | os.PathLike, obj: object) -> Path:
    p = Path(path)
    with atomic_path(p) as tmp:
        tmp.write_text(json.dumps(obj, indent=2, sort_keys=False, default=_json_default) + "\n")
    return p


def write_text(path: str | os.PathLike, text: str) -> Path:
    p = Path(path)
    with atomic_path(p) as tmp:
        tmp.write_text(text)
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


def save_figure(fig: Figure, path: str | os.PathLike, *, dpi: float = 100, **savefig_kw: object) -> Path:
    """Save a matplotlib figure atomically (format from the suffix, PNG by default) and release it from
    pyplot if pyplot made it. No timestamp is written: the same figure gives the same bytes. Returns the
    path."""
    import matplotlib.pyplot as plt  # lazy: heavy optional dependency

    p = Path(path)
    fmt = p.suffix.lstrip(".").lower() or "png"
    # No creation date in PDF/SVG/PS files and fixed SVG element ids: the same figure, the same bytes.
    undated = {"pdf": {"CreationDate": None}, "svg": {"Date": None}, "ps": {"CreationDate": None},
               "eps": {"CreationDate": None}}
    if fmt in undated:
        savefig_kw.setdefault("metadata", undated[fmt])
    with atomic_path(p) as tmp, plt.rc_context({"svg.hashsalt": "terrainwarp"}):
        fig.savefig(tmp, format=fmt, dpi=dpi, **savefig_kw)
    plt.close(fig)
    return p

"""What notebooks show: PNG bytes of an image (a frame's ``_repr_png_``), pictures of a depth or an id image, and
HTML tables (the ``_repr_html_`` of reports, errors and fits). Plain numpy and the standard library: showing a
frame in Jupyter imports nothing heavy."""

from __future__ import annotations

import html
import math
import struct
import zlib
from collections.abc import Iterable, Sequence

import numpy as np

__all__ = ["png_bytes", "depth_picture", "id_picture", "html_table"]

_BACKGROUND = np.array([24, 26, 32], np.uint8)  # pixels nothing was drawn on


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def png_bytes(image: np.ndarray) -> bytes:
    """An 8-bit PNG file, in memory, of an (H, W) grey or (H, W, 3) RGB uint8 image, row 0 at the top.

    Raises:
        ValueError: another shape or dtype, or an empty image.
    """
    a = np.asarray(image)
    if a.dtype != np.uint8 or a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] != 3) or 0 in a.shape[:2]:
        raise ValueError(f"image: expected a non-empty (H, W) or (H, W, 3) uint8 array, got {a.dtype} {a.shape}")
    h, w = a.shape[:2]
    rows = np.ascontiguousarray(a).reshape(h, -1)
    raw = np.concatenate([np.zeros((h, 1), np.uint8), rows], axis=1).tobytes()  # filter 0 on every row
    header = struct.pack(">IIBBBBB", w, h, 8, 2 if a.ndim == 3 else 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", header) + _chunk(b"IDAT", zlib.compress(raw, 6)) + \
        _chunk(b"IEND", b"")


def depth_picture(depth: np.ndarray, background: float = 1.0) -> np.ndarray:
    """(H, W, 3) uint8 of an (H, W) window-depth image: the drawn pixels from bright (near) to dark (far), spread
    over their own depth range; ``background`` pixels (depth 1.0: nothing drawn) a dark grey."""
    d = np.asarray(depth, dtype=np.float64)
    drawn = np.isfinite(d) & (d < background)
    out = np.broadcast_to(_BACKGROUND, (*d.shape, 3)).copy()
    if drawn.any():
        lo, hi = d[drawn].min(), d[drawn].max()
        t = (hi - d[drawn]) / (hi - lo) if hi > lo else np.ones(int(drawn.sum()))
        out[drawn] = np.round(60.0 + 195.0 * t)[:, None].astype(np.uint8)
    return out


def id_picture(ids: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 of an (H, W) int id image (triangle or patch ids): one colour per id, from a fixed integer
    hash (the same id, the same colour, in every frame); negative ids (background) a dark grey."""
    i = np.asarray(ids).astype(np.int64)
    h = (i * 2654435761) & 0xFFFFFF
    rgb = np.stack([(h >> 16) & 255, (h >> 8) & 255, h & 255], -1)
    out = (64 + (rgb * 191) // 255).astype(np.uint8)
    out[i < 0] = _BACKGROUND
    return out


def _cell(v: object) -> str:
    if isinstance(v, bool) or v is None:
        return html.escape(str(v))
    if isinstance(v, float | np.floating):
        return "nan" if math.isnan(v) else f"{v:.4g}"
    if isinstance(v, dict):
        return html.escape(", ".join(f"{k}={_plain(x)}" for k, x in v.items()))
    return html.escape(str(v))


def _plain(v: object) -> str:
    return f"{v:.4g}" if isinstance(v, float | np.floating) else str(v)


def html_table(header: Sequence[str], rows: Iterable[Sequence[object]], caption: str | None = None) -> str:
    """An HTML ``<table>`` with ``header`` and ``rows`` (floats to 4 significant digits, dicts as ``k=v`` lists,
    everything escaped), under an optional ``caption``."""
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{_cell(v)}</td>" for v in r) + "</tr>" for r in rows)
    cap = "" if caption is None else f"<caption>{html.escape(caption)}</caption>"
    return f"<table>{cap}<thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"

"""The one validation helper for scalar arguments, at the lowest layer so that every public boundary uses it.

One exception type per kind of error: a value of the wrong type (a string for a number, a bool or a float for
an integer) raises ``TypeError``; a value of the right type outside its range (NaN, a negative spacing, an
unknown name) raises ``ValueError``. Every message names the argument and says what was expected and what was
given: ``"lod.tolerance_px: expected a number, got '1.0'"``, ``"dx: expected a finite number > 0, got -30.0"``.

Arrays have their own checks with the same rule: a triangle list of the wrong shape or out-of-range indices
raises ``ValueError``, one of a non-integer dtype ``TypeError`` (:func:`check_triangles`); a viewport side that is
not an integer raises ``TypeError``, one outside ``1..MAX_VIEWPORT`` ``ValueError`` (:func:`check_viewport`).

Integers are Python or numpy integers (bool is not one); numbers are integers or Python/numpy floats. Each
check returns the value converted (``int`` or ``float``), so the caller keeps a plain Python scalar.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np
import warp as wp

from .device import start

__all__ = ["MAX_VIEWPORT", "is_int", "is_number", "check_int", "check_number", "check_bool", "check_choice",
           "check_optional", "check_pixels", "check_viewport", "check_triangle_shape", "check_triangles",
           "check_device"]

#: The largest viewport side, in pixels (a GPU's GL_MAX_VIEWPORT_DIMS; the renderer's own limit).
MAX_VIEWPORT = 16384


def is_int(v: object) -> bool:
    """True for a Python or numpy integer (not a bool)."""
    return not isinstance(v, bool | np.bool_) and isinstance(v, int | np.integer)


def is_number(v: object) -> bool:
    """True for a Python or numpy integer or float (not a bool, not a string, not complex)."""
    return not isinstance(v, bool | np.bool_) and isinstance(v, int | float | np.integer | np.floating)


def _bounds(lo: float | None, hi: float | None, lo_open: bool, hi_open: bool) -> str:
    parts = ([f"{'>' if lo_open else '>='} {lo}"] if lo is not None else []) + \
        ([f"{'<' if hi_open else '<='} {hi}"] if hi is not None else [])
    return " and ".join(parts)


def _in(v: float, lo: float | None, hi: float | None, lo_open: bool, hi_open: bool) -> bool:
    if lo is not None and (v <= lo if lo_open else v < lo):
        return False
    return not (hi is not None and (v >= hi if hi_open else v > hi))


def check_int(name: str, v: object, lo: int | None = None, hi: int | None = None) -> int:
    """``v`` as an ``int`` in ``[lo, hi]`` (a bound of None: none).

    Raises:
        TypeError: ``v`` is not an integer. ValueError: it lies outside the range.
    """
    if not is_int(v):
        raise TypeError(f"{name}: expected an integer, got {v!r}")
    i = int(v)
    if not _in(i, lo, hi, False, False):
        raise ValueError(f"{name}: expected an integer {_bounds(lo, hi, False, False)}, got {i}")
    return i


def check_number(name: str, v: object, lo: float | None = None, hi: float | None = None, *,
                 lo_open: bool = False, hi_open: bool = False, finite: bool = True) -> float:
    """``v`` as a ``float``: finite (unless ``finite=False``, which allows +-inf but never NaN) and in the range
    (``lo_open``/``hi_open``: the bound itself excluded).

    Raises:
        TypeError: ``v`` is not a number. ValueError: NaN, infinite, or outside the range.
    """
    if not is_number(v):
        raise TypeError(f"{name}: expected a number, got {v!r}")
    f = float(v)
    what = ("a finite number" if finite else "a number") + (f" {_bounds(lo, hi, lo_open, hi_open)}"
                                                             if lo is not None or hi is not None else "")
    if math.isnan(f) or (finite and math.isinf(f)) or not _in(f, lo, hi, lo_open, hi_open):
        raise ValueError(f"{name}: expected {what}, got {v!r}")
    return f


def check_bool(name: str, v: object) -> bool:
    """``v`` as a ``bool`` (Python or numpy); TypeError for anything else (0, 1 and "true" included)."""
    if not isinstance(v, bool | np.bool_):
        raise TypeError(f"{name}: expected true or false, got {v!r}")
    return bool(v)


def check_choice(name: str, v: object, choices: Iterable[str]) -> str:
    """``v``, one of ``choices`` (strings). TypeError for a non-string, ValueError for another string."""
    options = list(choices)
    if not isinstance(v, str):
        raise TypeError(f"{name}: expected one of {options}, got {v!r}")
    if v not in options:
        raise ValueError(f"{name}: expected one of {options}, got {v!r}")
    return v


def check_optional(check, name: str, v: object, *args, **kwargs):
    """``None``, or ``check(name, v, *args, **kwargs)``."""
    return None if v is None else check(name, v, *args, **kwargs)


def check_pixels(name: str, v: object) -> int:
    """``v``, one side of a viewport in pixels, as an ``int`` in ``1..MAX_VIEWPORT``.

    Raises:
        TypeError: ``v`` is not an integer. ValueError: it lies outside ``1..MAX_VIEWPORT``.
    """
    if not is_int(v):
        raise TypeError(f"{name}: expected a positive integer number of pixels, got {v!r}")
    if not 1 <= int(v) <= MAX_VIEWPORT:
        raise ValueError(f"{name}: expected 1..{MAX_VIEWPORT} pixels, got {v}")
    return int(v)


def check_viewport(width: object, height: object, names: tuple[str, str] = ("width", "height")) -> tuple[int, int]:
    """``(width, height)`` in pixels, each checked by :func:`check_pixels` under its name in ``names``."""
    return check_pixels(names[0], width), check_pixels(names[1], height)


def check_triangle_shape(name: str, shape: tuple[int, ...], dtype: object) -> None:
    """The shape and dtype rule of a triangle list, for arrays that cannot be read on the host (a traced JAX
    array): ``(m, 3)`` of an integer dtype (any dtype when ``m == 0``).

    Raises:
        ValueError: another shape. TypeError: a non-integer dtype.
    """
    shape = tuple(int(s) for s in shape)
    if len(shape) != 2 or shape[1] != 3:
        raise ValueError(f"{name}: expected shape (m, 3), got {shape}")
    if shape[0] and np.dtype(dtype).kind not in "iu":  # np.issubdtype(dtype, np.integer), without its Python
        raise TypeError(f"{name}: expected integer vertex indices, got dtype {np.dtype(dtype)}")


def check_triangles(name: str, triangles: object, n_vertices: int | None = None, scan: bool = True) -> np.ndarray:
    """``triangles`` as a C-contiguous ``(m, 3)`` int32 array of vertex indices, each in ``[0, n_vertices)``
    (``n_vertices`` None: only ``>= 0`` and below 2**31; ``scan`` False: the shape and dtype only, the values
    vouched for by the caller).

    Raises:
        ValueError: not ``(m, 3)``, or an index out of range. TypeError: a non-integer dtype.
    """
    tri = np.asarray(triangles)
    check_triangle_shape(name, tri.shape, tri.dtype)
    if tri.size and scan:
        top = np.iinfo(np.int32).max + 1 if n_vertices is None else int(n_vertices)
        # one pass: a negative index read as unsigned is at least 2**(bits - 1), past any valid one
        u = tri.view(f"u{tri.dtype.itemsize}") if tri.dtype.kind == "i" else tri
        if int(u.max()) >= top:
            lo, hi = int(tri.min()), int(tri.max())
            raise ValueError(f"{name}: expected indices in [0, {top}), got [{lo}, {hi}]")
    if tri.dtype == np.int32 and tri.flags.c_contiguous:  # already as asked (the shape is checked above)
        return tri
    return np.ascontiguousarray(tri, dtype=np.int32).reshape(-1, 3)


def check_device(name: str, device: object) -> wp.Device:
    """``device`` (a Warp device name such as ``"cpu"``, ``"cuda"``, ``"cuda:0"``, a ``warp.Device``, or None for
    Warp's default) as the ``warp.Device`` it names; Warp is started first (quietly: :func:`.device.start`).

    Raises:
        TypeError: not a string, a device or None. ValueError: a CUDA device on a machine where Warp finds no
            GPU (the message says so), or a name Warp does not know (the message lists the devices it has).
    """
    if isinstance(device, str) and device in _SEEN:  # a full name checked before names that device for good
        return _SEEN[device]
    start()
    if device is None or isinstance(device, wp.Device):
        return wp.get_device(device)
    if not isinstance(device, str):
        raise TypeError(f"{name}: expected a device name ('cpu', 'cuda:0', ...) or a warp.Device, got {device!r}")
    if device.startswith("cuda") and not wp.is_cuda_available():
        raise ValueError(f"{name}: {device!r} asks for an NVIDIA GPU, but Warp finds no CUDA device on this machine "
                         "(no GPU or no CUDA driver); use 'cpu'")
    try:
        dev = wp.get_device(device)
    except (ValueError, RuntimeError, KeyError):
        have = ", ".join(repr(d.alias) for d in wp.get_devices())
        raise ValueError(f"{name}: expected one of the devices Warp sees ({have}), got {device!r}") from None
    if device != "cuda":  # "cuda" names whichever CUDA device is current
        _SEEN[device] = dev
    return dev


_SEEN: dict[str, wp.Device] = {}  # device names check_device accepted, and their devices

"""Stiff and extreme cases: each a named :class:`Scene` builder with the failure it catches.

The catalogue of the stability issue: terrain that breaks naive arithmetic (a 1 km cliff over one
sample, one-sample spikes, a flat plane, relief of 1e-6 and 1e6 over spacing 1, spacing 1e-3 and 1e4,
an 8,848 m base with millimetre relief, terrains 100 km and 10,000 km from the origin), cameras that
break naive projection (on the surface, inside a patch's bounds, below the terrain, straight down,
0.01 degree grazing, near 1e-4 / far 1e7, field of view 0.1 and 179 degrees), data that breaks naive
loaders (NaN no-data holes; int16, uint16, float16 and float64 inputs; 1x1, 2x2, 3x3 and 1x4097
grids) and tessellation factors at and beyond the hardware's limits (0, 0.5, 1, 63.99, 64, 65, 1e30,
NaN, -inf).

::

    from terrainwarp.experiments.extreme import CASES, get_case
    c = get_case("everest")
    scene = c.build(33)          # a Scene on a 33 x 33 grid (size is ignored by fixed-shape cases)
    print(c.catches)

``build`` may itself raise a clear ``ValueError``/``TypeError``: that is the case's outcome (the
stability suite records it). Every terrain is deterministic (a fixed seed).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from ..heightmap import Heightmap
from ..kernels.checks import check_choice, check_int
from ..scene import Scene

__all__ = ["ExtremeCase", "CASES", "case_names", "get_case", "TESS_FACTORS"]

TESS_FACTORS = (0.0, 0.5, 1.0, 63.99, 64.0, 65.0, 1e30, float("nan"), float("-inf"))


@dataclass(frozen=True)
class ExtremeCase:
    """One extreme case.

    Attributes:
        name: short key (``get_case(name)``).
        group: ``"terrain"``, ``"camera"``, ``"data"`` or ``"tess"``.
        catches: the failure the case is there to catch.
        make: ``make(n) -> Scene`` for a grid of about n x n samples.
        factor: for ``"tess"`` cases, the tessellation factor given to every outer and inner level.
    """

    name: str
    group: str
    catches: str
    make: Callable[[int], Scene]
    factor: float | None = None

    def build(self, n: int = 33) -> Scene:
        return self.make(check_int("n", n, 2))


def _rough(n: int, amp: float = 100.0, seed: int = 7) -> np.ndarray:
    """Deterministic smooth-ish relief in [0, amp], float64 (n, n)."""
    a = Heightmap.fbm(n, n, seed=seed, max_height=1.0, dx=1.0, feature_size=max(n / 2.0, 2.0), octaves=4).heights
    return a.astype(np.float64) * amp


def _scene(name: str, h: np.ndarray, dx: float = 1.0, *, origin=(0.0, 0.0), camera=None, allow_nan=False,
           width: int = 96, height: int = 72) -> Scene:
    hm = Heightmap.from_array(h, dx, origin=origin, allow_nan=allow_nan, name=name)
    cam = camera(hm, width, height) if camera is not None else Camera.default_for(hm, width, height)
    return Scene(hm, camera=cam, outputs=("image", "depth", "report"), name=name)


def _look(pos, target, *, up=(0.0, 1.0, 0.0), fov=45.0, near=None, far=None):
    """Camera factory: positions given as functions of the heightmap's bounds."""

    def f(hm: Heightmap, w: int, h: int) -> Camera:
        p, t = pos(hm), target(hm)
        dist = float(np.linalg.norm(np.subtract(t, p)))
        (x0, z0), (x1, z1) = hm.bounds_xz
        ext = max(x1 - x0, z1 - z0, 1e-9)
        nr = near if near is not None else max(1e-4, 1e-3 * dist)
        fr = far if far is not None else 10.0 * (dist + ext) + 10.0
        return Camera(position=p, target=t, up=up, fov_y_deg=fov, width=w, height=h, near=nr, far=fr)

    return f


def _centre(hm: Heightmap, dy: float = 0.0, fx: float = 0.5, fz: float = 0.5):
    (x0, z0), (x1, z1) = hm.bounds_xz
    x, z = x0 + fx * (x1 - x0), z0 + fz * (z1 - z0)
    return (x, float(hm.sample(np.array([x]), np.array([z]))[0]) + dy, z)


def _ext(hm: Heightmap) -> float:
    (x0, z0), (x1, z1) = hm.bounds_xz
    return max(x1 - x0, z1 - z0, 1e-9)


# -- terrain cases --------------------------------------------------------------------------------
def _cliff(n):
    h = np.zeros((n, n))
    h[:, n // 2:] = 1000.0
    return _scene("cliff", h, 30.0)


def _spikes(n):
    h = _rough(n, 5.0)
    h[n // 3, n // 3] += 500.0
    h[2 * n // 3, n // 2] += 500.0
    h[n // 2, 2 * n // 3] -= 500.0
    return _scene("spikes", h, 30.0)


def _flat(n):
    return _scene("flat", np.zeros((n, n)))


def _relief(amp):
    return lambda n: _scene(f"relief_{amp:g}", _rough(n, amp))


def _spacing(dx):
    return lambda n: _scene(f"spacing_{dx:g}", _rough(n, 30.0 * dx), dx)


def _everest(n):
    return _scene("everest", 8848.0 + _rough(n, 0.005))


def _far(d):
    return lambda n: _scene(f"far_{d:g}", _rough(n, 50.0), 10.0, origin=(d, d))


# -- camera cases ---------------------------------------------------------------------------------
def _cam_case(name, camera, amp=50.0):
    return lambda n: _scene(name, _rough(n, amp), 10.0, camera=camera)


def _on_surface(hm):
    return _centre(hm, 0.0, 0.3, 0.3)


_CAMERAS = {
    "cam_on_surface": (_look(_on_surface, lambda hm: _centre(hm, 0.0, 0.8, 0.8)),
                       "eye exactly on the surface: near-plane clipping of the triangles under the eye, "
                       "division by w ~ 0"),
    "cam_in_patch_bounds": (_look(lambda hm: _centre(hm, 1.0, 0.5, 0.5), lambda hm: _centre(hm, 0.0, 0.9, 0.6)),
                            "eye inside a patch's bounding box: distance 0 to the node (LOD split by "
                            "division by zero), screen error infinite"),
    "cam_below": (_look(lambda hm: _centre(hm, -200.0, 0.5, 0.5), lambda hm: _centre(hm, 0.0, 0.5, 0.9)),
                  "eye below the terrain: back faces, culling assumptions, LOD distance to the box"),
    "cam_straight_down": (_look(lambda hm: _centre(hm, 0.5 * _ext(hm), 0.5, 0.5), lambda hm: _centre(hm, 0.0),
                                up=(0.0, 0.0, -1.0)),
                          "view direction parallel to +y: lookAt with up=+y is singular (needs another up)"),
    "cam_grazing": (_look(lambda hm: _centre(hm, 0.0, 0.5, 0.98),
                          lambda hm: (_centre(hm, 0.0, 0.5, 0.98)[0],
                                      _centre(hm, 0.0, 0.5, 0.98)[1] - _ext(hm) * math.tan(math.radians(0.01)),
                                      _centre(hm, 0.0, 0.5, 0.98)[2] - _ext(hm))),
                    "0.01 degree grazing view: depth and barycentrics of near-edge-on triangles"),
    "cam_near_far": (_look(lambda hm: _centre(hm, 30.0, 0.5, 1.2), lambda hm: _centre(hm, 0.0), near=1e-4, far=1e7),
                     "near 1e-4, far 1e7 (ratio 1e11): float32 window depth collapses to 1"),
    "cam_fov_0.1": (_look(lambda hm: _centre(hm, 0.5 * _ext(hm), 0.5, 2.0), lambda hm: _centre(hm), fov=0.1),
                    "0.1 degree field of view: focal length 1e3 x the viewport, ill-conditioned projection"),
    "cam_fov_179": (_look(lambda hm: _centre(hm, 0.3 * _ext(hm), 0.5, 1.0), lambda hm: _centre(hm), fov=179.0),
                    "179 degree field of view: tan(fov/2) = 115, huge screen-space triangles"),
}


# -- data cases -----------------------------------------------------------------------------------
def _nan_holes(n):
    h = _rough(n, 100.0)
    h[n // 4:n // 4 + max(n // 8, 1), n // 4:n // 2] = np.nan
    h[n // 2, n // 2] = np.nan
    h[-1, :n // 3] = np.nan
    return _scene("nan_holes", h, allow_nan=True)


def _dtype(dt):
    def f(n):
        a = _rough(n, 1000.0)
        if np.issubdtype(dt, np.integer):
            a = np.round(a).astype(dt)
        else:
            a = (a + 0.123).astype(dt)
        return _scene(f"dtype_{np.dtype(dt).name}", a)

    return f


def _grid(rows, cols):
    def f(n):
        a = _rough(max(rows, cols, 2), 50.0)[:rows, :cols] if min(rows, cols) > 1 else \
            np.linspace(0.0, 50.0, rows * cols).reshape(rows, cols) ** 1.5 / 50.0 ** 0.5
        # explicit camera: Camera.default_for cannot frame a zero-extent 1x1 grid (see the suite's note)
        cam = _look(lambda hm: _centre(hm, 20.0, 0.5, 0.5) if rows * cols > 1 else (0.5, 30.0, 40.0),
                    lambda hm: _centre(hm, 0.0, 0.5, 0.5) if rows * cols > 1 else (0.0, 0.0, 0.0), near=0.01)
        return _scene(f"grid_{rows}x{cols}", a, 1.0, camera=cam if rows * cols == 1 else None)

    return f


# -- tessellation cases ---------------------------------------------------------------------------
def _tess(n):
    return _scene("tess", _rough(n, 50.0), 1.0)


def _build() -> dict[str, ExtremeCase]:
    c: list[ExtremeCase] = [
        ExtremeCase("cliff", "terrain", "1 km step over one sample: normals/curvature overflow, LOD error "
                    "pyramid, stretched triangles", _cliff),
        ExtremeCase("spikes", "terrain", "one-sample spikes of +-500 m: min/max pyramid misses, bilinear "
                    "sampling overshoot, culling of thin geometry", _spikes),
        ExtremeCase("flat", "terrain", "a flat plane: curvature and screen error must be exactly 0", _flat),
        ExtremeCase("relief_1e-06", "terrain", "relief 1e-6 over spacing 1: slopes underflow, normals must "
                    "stay unit and up", _relief(1e-6)),
        ExtremeCase("relief_1e+06", "terrain", "relief 1e6 over spacing 1: near-vertical normals, float32 "
                    "depth and curvature range", _relief(1e6)),
        ExtremeCase("spacing_0.001", "terrain", "spacing 1e-3 m: tiny cells, dx in denominators", _spacing(1e-3)),
        ExtremeCase("spacing_1e+04", "terrain", "spacing 1e4 m: 10 km cells, large coordinates", _spacing(1e4)),
        ExtremeCase("everest", "terrain", "8,848 m base with millimetre relief: naive float32 differencing "
                    "(h1 - h0 after summing) loses the relief", _everest),
        ExtremeCase("far_1e+05", "terrain", "terrain 100 km from the origin: absolute float32 positions "
                    "lose centimetres", _far(1e5)),
        ExtremeCase("far_1e+07", "terrain", "terrain 10,000 km from the origin: absolute float32 positions "
                    "lose metres (ulp(1e7) = 1 m)", _far(1e7)),
    ]
    for name, (cam, why) in _CAMERAS.items():
        c.append(ExtremeCase(name, "camera", why, _cam_case(name, cam)))
    c += [
        ExtremeCase("nan_holes", "data", "NaN no-data holes: no triangle may touch one; normals, error and "
                    "LOD must not spread NaN", _nan_holes),
        ExtremeCase("dtype_int16", "data", "int16 input (SRTM): conversion and negative heights", _dtype(np.int16)),
        ExtremeCase("dtype_uint16", "data", "uint16 input (16-bit PNG)", _dtype(np.uint16)),
        ExtremeCase("dtype_float16", "data", "float16 input: 11-bit mantissa, coarse steps", _dtype(np.float16)),
        ExtremeCase("dtype_float64", "data", "float64 input: rounded once to float32", _dtype(np.float64)),
        ExtremeCase("grid_1x1", "data", "a 1x1 grid: no cell, no triangle, zero extent", _grid(1, 1)),
        ExtremeCase("grid_2x2", "data", "a 2x2 grid: one cell, no interior sample", _grid(2, 2)),
        ExtremeCase("grid_3x3", "data", "a 3x3 grid: one interior sample", _grid(3, 3)),
        ExtremeCase("grid_1x4097", "data", "a 1x4097 grid: zero-area strip, aspect 4096", _grid(1, 4097)),
    ]
    for f in TESS_FACTORS:
        c.append(ExtremeCase(f"tess_{f:g}", "tess", "tessellation factor at/beyond the limits: cull (<= 0, NaN), "
                             "clamp to [1, 64], round, fixed-point overflow (1e30)", _tess, factor=f))
    return {x.name: x for x in c}


CASES: dict[str, ExtremeCase] = _build()


def case_names(group: str | None = None) -> list[str]:
    """Case names in catalogue order (optionally one group)."""
    return [k for k, v in CASES.items() if group is None or v.group == group]


def get_case(name: str) -> ExtremeCase:
    check_choice("name", name, CASES)
    return CASES[name]

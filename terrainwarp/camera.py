"""Cameras and camera paths.

Conventions (the one place they are stated; nothing else in terrainwarp contradicts them):

* World space is right-handed with **y up** (OpenGL). Heights are along +y. Heightmap row ``i`` runs
  along +z and column ``j`` along +x: sample ``(i, j)`` sits at ``(x0 + j*dx, h[i, j], z0 + i*dz)``.
  For a north-up raster, +x is east and +z is south.
* The view matrix is OpenGL's ``lookAt``: eye space looks down -z, x right, y up.
* The projection matrix is OpenGL's ``gluPerspective``: clip z in [-w, w]; window depth
  ``(z_ndc + 1) / 2`` lies in [0, 1] (0 at the near plane).
* Window coordinates have their origin at the bottom-left, as OpenGL's; images everywhere in
  terrainwarp have row 0 at the **top** (as image files do), so image row = height - 1 - window y.
* Positions handed to the rasterizer are **camera-relative** float32 (world minus eye, subtracted in
  float64 on the host before the cast), which is how GPUs keep precision for terrains far from the
  origin; :meth:`Camera.view_matrix` with ``relative=True`` is the matching view matrix.
* Heading, pitch and roll (:func:`camera_from_angles`, the camera-path CSV): yaw is the compass heading in
  degrees, clockwise from north (-z) seen from above (90 looks east, +x); pitch is degrees above the
  horizon (-90 looks straight down); roll is degrees of bank to the right (the camera's up vector tilts
  toward its right, the horizon turns anticlockwise in the image).
* A pixel measure belongs to a :class:`Viewport` (width, height, vertical field of view): a length of
  ``e`` pixels is ``e / focal_px`` radians, ``focal_px = height / (2 tan(fov_y / 2))`` pixels per radian
  at the centre of the view (Cesium's ``sseDenominator`` rule).
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .heightmap import Heightmap, StreamedHeightmap
from .kernels.checks import check_number, check_pixels, check_viewport
from .kernels.lod import frustum_planes

__all__ = ["Camera", "Viewport", "orbit", "flyover", "relative_origin", "camera_from_angles", "read_camera_csv",
           "CSV_COLUMNS", "DepthPrecisionWarning", "check_depth_range", "DEPTH_STEPS"]

#: float32 window-depth steps (2^-24 each, near 1.0) that the farthest terrain must keep before the background
#: depth 1.0: a fragment closer to 1.0 than this is drawn as background (it rounds to 1.0, or ties with it)
DEPTH_STEPS = 2
#: ground samples along a flyover path that crosses a no-data hole, among which the hole's rims are found
HOLE_SAMPLES = 4096


class DepthPrecisionWarning(UserWarning):
    """A camera whose ``near`` leaves the far part of the terrain unresolved by float32 depth (the frame loses
    it to the background); the message gives the smallest safe ``near``."""


def _resolved_depth(near: float, far: float) -> float:
    """The view depth beyond which float32 window depth is within :data:`DEPTH_STEPS` steps of 1.0 (drawn as
    background): ``1 - d(w) = near (far - w) / (w (far - near))`` equals ``DEPTH_STEPS * 2^-24`` there."""
    k = DEPTH_STEPS * 2.0**-24
    return near * far / (near + k * (far - near))


def _safe_near(depth: float, far: float) -> float:
    """The smallest ``near`` that keeps view depth ``depth`` (< far) :data:`DEPTH_STEPS` float32 steps before 1.0,
    rounded up to two significant digits."""
    k = DEPTH_STEPS * 2.0**-24
    n = k * depth * far / (far - depth + k * depth)
    e = math.floor(math.log10(n)) - 1
    return math.ceil(n / 10.0**e) * 10.0**e


def check_depth_range(camera: Camera, box_min: tuple[float, float, float],
                      box_max: tuple[float, float, float]) -> str | None:
    """Whether float32 window depth resolves a terrain inside the box ``box_min``..``box_max`` (world x, y, z)
    seen by ``camera``: a fragment at view depth w has window depth ``d`` with ``1 - d = near (far - w) /
    (w (far - near))``; where that falls within :data:`DEPTH_STEPS` float32 steps of 1.0 (the background's
    depth), the fragment is lost to the background (a ``near`` of 1e-5 m blanks a 30 km terrain's frame).

    The terrain's reach is the farthest view depth of the box's corners, at most half the depth range (the
    fragments at the far plane itself are lost whatever ``near`` is). Raises ValueError (naming
    ``camera.near`` and the smallest safe value) when the point the camera looks at, or the nearer of it and
    the terrain's reach, is lost: the frame would be blank there. Returns a warning's text (the smallest
    safe value) when only the terrain beyond it is lost, else None."""
    eye, fwd = np.asarray(camera.position, np.float64), camera.forward
    corners = np.array([[x, y, z] for x in (box_min[0], box_max[0]) for y in (box_min[1], box_max[1])
                         for z in (box_min[2], box_max[2])], np.float64)
    reach = min(float(((corners - eye) @ fwd).max()), 0.5 * camera.far)
    resolved = _resolved_depth(camera.near, camera.far)
    if reach <= camera.near or resolved >= reach:
        return None
    focus = min(float(np.linalg.norm(np.subtract(camera.target, camera.position))), reach)
    what = (f"camera.near: {camera.near:g} m is too small for float32 depth (far {camera.far:g} m): fragments "
            f"farther than {resolved:.4g} m are drawn as background")
    if resolved < focus:
        raise ValueError(f"{what}, the point the camera looks at among them ({focus:.4g} m); use near >= "
                         f"{_safe_near(reach, camera.far):g} m (the smallest that resolves the terrain, "
                         f"{reach:.4g} m deep)")
    return (f"{what}, and the terrain reaches {reach:.4g} m; near >= {_safe_near(reach, camera.far):g} m "
            f"resolves it")


def relative_origin(origin_xz: tuple[float, float] | np.ndarray,
                    eye: tuple[float, float, float] | np.ndarray) -> tuple[float, float, float]:
    """Where a grid whose sample (0, 0) sits at world ``origin_xz`` = (x, z) lies seen from ``eye``:
    ``(x - eye_x, eye_y, z - eye_z)``, subtracted in float64 on the host.

    This is the one place the camera-relative rule lives (the GPU's remedy for large world coordinates):
    kernels add float32 offsets to it and subtract the returned ``eye_y`` from heights, so vertices near the
    camera keep their precision wherever the terrain sits in the world."""
    return (float(origin_xz[0]) - float(eye[0]), float(eye[1]), float(origin_xz[1]) - float(eye[2]))


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b of two float64 3-vectors: ``np.cross``'s products and differences, without its general-case cost."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _vec3(name: str, v: object) -> tuple[float, float, float]:
    try:
        a = np.asarray(v, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as e:
        raise TypeError(f"{name}: expected 3 finite numbers, got {v!r}") from e
    if a.shape != (3,):
        raise ValueError(f"{name}: expected 3 numbers, got {a.size}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: expected finite numbers, got {a.tolist()}")
    return (float(a[0]), float(a[1]), float(a[2]))


def _finite(name: str, v: object) -> float:
    return check_number(name, v)


def _fov(v: object) -> float:
    """The one field-of-view rule (the camera's and every camera maker's): degrees in (0, 180)."""
    f = _finite("fov_y_deg", v)
    if not 0.0 < f < 180.0:
        raise ValueError(f"fov_y_deg: expected a value in (0, 180) degrees, got {v}")
    return f


class Viewport(NamedTuple):
    """The viewport a pixel measure belongs to: ``width`` x ``height`` pixels and a vertical field of view of
    ``fov_y_deg`` degrees. :meth:`of` checks the numbers by the camera's rules."""

    width: int
    height: int
    fov_y_deg: float

    @classmethod
    def of(cls, width: object, height: object, fov_y_deg: object) -> Viewport:
        """A checked viewport (width and height 1..16384 pixels, the field of view in (0, 180) degrees)."""
        return cls(check_pixels("width", width), check_pixels("height", height), _fov(fov_y_deg))

    @property
    def focal_px(self) -> float:
        """Pixels per radian at the centre of the view: ``height / (2 tan(fov_y / 2))``."""
        return self.height / (2.0 * math.tan(math.radians(self.fov_y_deg) / 2.0))

    def to_radians(self, px: float) -> float:
        """``px`` pixels at this viewport as an angle (radians, at the centre of the view)."""
        return float(px) / self.focal_px

    def to_pixels(self, radians: float) -> float:
        """An angle (radians) as pixels at this viewport."""
        return float(radians) * self.focal_px

    @property
    def text(self) -> str:
        """``"960x540, 60 degree fov"``."""
        return f"{self.width}x{self.height}, {self.fov_y_deg:g} degree fov"


@dataclass(frozen=True)
class Camera:
    """A pinhole camera in OpenGL conventions (see the module docstring).

    Attributes:
        position: eye position in world metres (float64 on the host).
        target: the point looked at.
        up: approximate up direction (default +y).
        fov_y_deg: vertical field of view in degrees, in (0, 180).
        width, height: viewport size in pixels.
        near, far: clip plane distances in metres, 0 < near < far.
    """

    position: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    fov_y_deg: float = 45.0
    width: int = 640
    height: int = 480
    near: float = 1.0
    far: float = 1.0e5
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False, hash=False)

    def __post_init__(self) -> None:
        for name in ("position", "target", "up"):
            object.__setattr__(self, name, _vec3(name, getattr(self, name)))
        for name in ("width", "height"):
            object.__setattr__(self, name, check_pixels(name, getattr(self, name)))
        object.__setattr__(self, "fov_y_deg", _fov(self.fov_y_deg))
        for name in ("near", "far"):
            object.__setattr__(self, name, _finite(name, getattr(self, name)))
        if not self.near > 0.0:
            raise ValueError(f"near: expected > 0, got {self.near}")
        if not self.far > self.near:
            raise ValueError(f"far: expected > near ({self.near}), got {self.far}")
        d = np.subtract(self.target, self.position)
        if not np.linalg.norm(d) > 0.0:
            raise ValueError("target: must differ from position (the view direction is undefined)")
        u = np.asarray(self.up)
        if np.linalg.norm(np.cross(d / np.linalg.norm(d), u)) <= 1e-9 * max(np.linalg.norm(u), 1e-300):
            raise ValueError(f"up: must not be parallel to the view direction, got up={self.up}")

    # -- derived quantities -------------------------------------------------------------------------
    @property
    def aspect(self) -> float:
        return self.width / self.height

    @property
    def forward(self) -> np.ndarray:
        """Unit view direction (float64, shape (3,))."""
        d = np.subtract(self.target, self.position)
        return d / np.linalg.norm(d)

    @property
    def focal_px(self) -> float:
        """d = viewport_height / (2 tan(fovy/2)): pixels per unit of (size / distance)."""
        return self.height / (2.0 * math.tan(math.radians(self.fov_y_deg) / 2.0))

    @property
    def viewport(self) -> Viewport:
        """The camera's (width, height, fov_y_deg)."""
        return Viewport(self.width, self.height, self.fov_y_deg)

    def view_matrix(self, relative: bool = False) -> np.ndarray:
        """OpenGL lookAt view matrix, float64 (4, 4).

        Args:
            relative: if True, the translation is left out: the matrix for camera-relative positions
                (world - eye), which is what the pipeline feeds the rasterizer.
        """
        key = "_view_relative" if relative else "_view"
        m = self.__dict__.get(key)  # made once per camera (the fields are frozen): every stage of a frame asks
        if m is None:
            f = self.forward
            s = _cross(f, np.asarray(self.up, np.float64))
            s /= np.linalg.norm(s)
            u = _cross(s, f)
            m = np.eye(4)
            m[0, :3], m[1, :3], m[2, :3] = s, u, -f
            if not relative:
                m[:3, 3] = -m[:3, :3] @ np.asarray(self.position)
            object.__setattr__(self, key, m)
        return m.copy()

    def frustum_planes(self) -> np.ndarray:
        """The view frustum of camera-relative positions: the six planes of ``proj_matrix() @
        view_matrix(relative=True)`` (:func:`terrainwarp.kernels.lod.frustum_planes`: (a, b, c, d), inside where
        a x + b y + c z + d >= 0, normalised), float32 (6, 4): left, right, bottom, top, near, far."""
        pl = self.__dict__.get("_planes")  # made once per camera, as the view matrix: selection asks every frame
        if pl is None:
            pl = frustum_planes(self.proj_matrix() @ self.view_matrix(relative=True))
            object.__setattr__(self, "_planes", pl)
        return pl.copy()

    def proj_matrix(self) -> np.ndarray:
        """OpenGL gluPerspective projection matrix, float64 (4, 4); clip z in [-w, w]."""
        p = self.__dict__.get("_proj")  # made once per camera, as the view matrix
        if p is None:
            t = 1.0 / math.tan(math.radians(self.fov_y_deg) / 2.0)
            n, f = self.near, self.far
            p = np.zeros((4, 4))
            p[0, 0] = t / self.aspect
            p[1, 1] = t
            p[2, 2] = (f + n) / (n - f)
            p[2, 3] = 2.0 * f * n / (n - f)
            p[3, 2] = -1.0
            object.__setattr__(self, "_proj", p)
        return p.copy()

    def with_(self, **changes: object) -> Camera:
        """A copy with some fields replaced (validated again)."""
        kw = {k: getattr(self, k) for k in
              ("position", "target", "up", "fov_y_deg", "width", "height", "near", "far")}
        kw.update(changes)
        return Camera(**kw)  # type: ignore[arg-type]

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in
                (("position", self.position), ("target", self.target), ("up", self.up),
                 ("fov_y_deg", self.fov_y_deg), ("width", self.width), ("height", self.height),
                 ("near", self.near), ("far", self.far))}

    @classmethod
    def default_for(cls, heightmap: Heightmap, width: int = 640, height: int = 480,
                    fov_y_deg: float = 45.0) -> Camera:
        """A three-quarter view from the south (+z) side that frames the whole terrain."""
        if not isinstance(heightmap, Heightmap | StreamedHeightmap):
            raise TypeError(f"heightmap: expected a terrainwarp Heightmap or StreamedHeightmap, got "
                            f"{type(heightmap).__name__} {heightmap!r:.60}")
        fov_y_deg = _fov(fov_y_deg)  # before it divides the distance
        width, height = check_viewport(width, height)
        (x0, z0), (x1, z1) = heightmap.bounds_xz
        hmin, hmax = heightmap.height_range  # of the finite heights (a streamed heightmap: its overview's)
        if not (math.isfinite(hmin) and math.isfinite(hmax)):
            hmin = hmax = 0.0
        cx, cz = 0.5 * (x0 + x1), 0.5 * (z0 + z1)
        size = max(x1 - x0, z1 - z0, hmax - hmin, heightmap.dx, heightmap.dz)  # a 1x1 grid still has a size
        target = (cx, hmin + 0.25 * (hmax - hmin), cz)
        dist = 0.62 * size / math.tan(math.radians(fov_y_deg) / 2.0)
        el = math.radians(35.0)
        az = math.radians(20.0)
        pos = (cx - dist * math.cos(el) * math.sin(az), target[1] + dist * math.sin(el),
               cz + dist * math.cos(el) * math.cos(az))
        near = max(dist * 1e-3, 1e-4)
        far = dist * 4.0 + size * 2.0
        return cls(position=pos, target=target, fov_y_deg=fov_y_deg, width=width, height=height,
                   near=near, far=far)


# -- camera paths -----------------------------------------------------------------------------------
def orbit(center: object, radius: float, elevation: float, n: int, *, width: int = 640, height: int = 480,
          fov_y_deg: float = 45.0, near: float = 1.0, far: float = 1e5, turns: float = 1.0) -> list[Camera]:
    """``n`` cameras on a horizontal circle of ``radius`` around ``center``, ``elevation`` metres above it,
    all looking at ``center``."""
    c = _vec3("center", center)
    if not (radius > 0 and math.isfinite(radius)):
        raise ValueError(f"radius: expected a positive finite number, got {radius}")
    if int(n) < 1:
        raise ValueError(f"n: expected at least 1 camera, got {n}")
    cams = []
    for k in range(int(n)):
        a = 2.0 * math.pi * turns * k / int(n)
        p = (c[0] + radius * math.sin(a), c[1] + elevation, c[2] + radius * math.cos(a))
        cams.append(Camera(position=p, target=c, fov_y_deg=fov_y_deg, width=width, height=height,
                           near=near, far=far))
    return cams


def _on_terrain(eye: np.ndarray, target: np.ndarray, bounds: tuple[tuple[float, float], tuple[float, float]],
                ahead: float) -> np.ndarray:
    """The look-ahead point ``target`` (x, z) of a camera at ``eye``, kept over the terrain: a point past the
    terrain's border is replaced by the point ``ahead`` toward the terrain's centre (pulled back to the border).
    An eye outside the terrain keeps its target."""
    lo, hi = np.asarray(bounds[0], np.float64), np.asarray(bounds[1], np.float64)
    inside = lambda p: bool(np.all(p >= lo) and np.all(p <= hi))  # noqa: E731
    if not inside(eye) or inside(target):
        return target
    c = 0.5 * (lo + hi) - eye
    if float(np.linalg.norm(c)) < 1e-9:  # at the centre: nothing is nearer the middle
        return target
    c /= np.linalg.norm(c)
    with np.errstate(divide="ignore", invalid="ignore"):
        reach = np.where(c > 0, (hi - eye) / c, np.where(c < 0, (lo - eye) / c, np.inf))
    return eye + c * min(ahead, float(np.min(reach)))


def flyover(heightmap: Heightmap, waypoints_xz: object, clearance: float, n: int, *,
            look_ahead: float | None = None, width: int = 640, height: int = 480,
            fov_y_deg: float = 60.0, near: float = 1.0, far: float = 1e5) -> list[Camera]:
    """``n`` cameras evenly spaced along a polyline of (x, z) waypoints, each ``clearance`` metres above
    the terrain beneath it (deaconu2021, "Navigation": only x and z are tracked, y follows the height
    function), looking ``look_ahead`` metres further along the path and slightly down. A camera whose
    look-ahead point lies past the terrain's border (the end of a path at the edge) looks toward the terrain's
    centre instead, so that no camera looks off the terrain. Over a no-data hole the ground is the height along
    the path between the hole's rims (:func:`_ground`), and a target over a hole is ``0.25 clearance`` below the
    eye.
    """
    w = np.asarray(waypoints_xz, dtype=np.float64)
    if w.ndim != 2 or w.shape[1] != 2 or w.shape[0] < 2:
        raise ValueError(f"waypoints_xz: expected an (k, 2) array with k >= 2, got shape {w.shape}")
    if not np.all(np.isfinite(w)):
        raise ValueError("waypoints_xz: expected finite coordinates")
    if not (clearance > 0 and math.isfinite(clearance)):
        raise ValueError(f"clearance: expected a positive finite number of metres, got {clearance}")
    if int(n) < 1:
        raise ValueError(f"n: expected at least 1 camera, got {n}")
    seg = np.linalg.norm(np.diff(w, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    total = float(cum[-1])
    if total <= 0:
        raise ValueError("waypoints_xz: the path has zero length")
    ahead = look_ahead if look_ahead is not None else 0.1 * total

    def at(s: float) -> np.ndarray:
        s = min(max(s, 0.0), total)
        k = int(np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1))
        t = (s - cum[k]) / seg[k] if seg[k] > 0 else 0.0
        return w[k] + t * (w[k + 1] - w[k])

    ss = np.linspace(0.0, total, int(n)) if int(n) > 1 else np.array([0.0])
    eyes = np.array([at(s) for s in ss])
    tgts = []
    for s in ss:
        t = at(s + ahead)
        if np.linalg.norm(t - at(s)) < 1e-9:  # end of path: keep the last heading
            t = at(s) + (at(s) - at(s - ahead))
        tgts.append(_on_terrain(at(s), t, heightmap.bounds_xz, ahead))
    tgts = np.array(tgts)
    he = _ground(heightmap, eyes, w, cum, ss)
    ht = heightmap.sample(tgts[:, 0], tgts[:, 1])
    cams = []
    for k in range(len(ss)):
        y = float(he[k]) + clearance
        ty = min(float(ht[k]), y - 0.25 * clearance) if math.isfinite(ht[k]) else y - 0.25 * clearance
        cams.append(Camera(position=(eyes[k, 0], y, eyes[k, 1]), target=(tgts[k, 0], ty, tgts[k, 1]),
                           fov_y_deg=fov_y_deg, width=width, height=height, near=near, far=far))
    return cams


def _ground(heightmap: Heightmap, xz: np.ndarray, w: np.ndarray, cum: np.ndarray, ss: np.ndarray) -> np.ndarray:
    """Ground heights (float64) under the path's points ``xz`` at arc lengths ``ss`` (polyline ``w``, cumulative
    lengths ``cum``): the heightmap's bilinear heights; where one is no-data (over a hole or beside one), the
    height interpolated along the path, by arc length, between the nearest finite ground on either side (the
    path sampled about every sample spacing, at most :data:`HOLE_SAMPLES` points; past the last finite ground,
    its height). A path with no finite ground at all takes, for each point, the highest finite height on the
    nearest ring around it that has one (:func:`_around`)."""
    h = np.asarray(heightmap.sample(xz[:, 0], xz[:, 1]), np.float64)
    bad = ~np.isfinite(h)
    if not bad.any():
        return h
    total = float(cum[-1])
    m = int(min(HOLE_SAMPLES, math.ceil(total / min(heightmap.dx, heightmap.dz)))) + 1
    sd = np.linspace(0.0, total, max(m, 2))
    hd = np.asarray(heightmap.sample(np.interp(sd, cum, w[:, 0]), np.interp(sd, cum, w[:, 1])), np.float64)
    ok = np.isfinite(hd)
    if ok.any():
        h[bad] = np.interp(ss[bad], sd[ok], hd[ok])
    else:
        h[bad] = [_around(heightmap, float(x), float(z)) for x, z in xz[bad]]
    return h


def _around(heightmap: Heightmap, x: float, z: float) -> float:
    """The highest finite height among 16 points on a ring around (x, z), on the smallest ring of radius one
    sample spacing times a power of two that has one (up to the terrain's diagonal); else the highest height."""
    (x0, z0), (x1, z1) = heightmap.bounds_xz
    r, reach = min(heightmap.dx, heightmap.dz), 2.0 * math.hypot(x1 - x0, z1 - z0) + max(heightmap.dx, heightmap.dz)
    a = np.linspace(0.0, 2.0 * math.pi, 16, endpoint=False)
    while r <= reach:
        h = np.asarray(heightmap.sample(x + r * np.cos(a), z + r * np.sin(a)), np.float64)
        if np.isfinite(h).any():
            return float(np.nanmax(h))
        r *= 2.0
    return float(heightmap.height_range[1])


# -- cameras from angles and from files -------------------------------------------------------------
def camera_from_angles(position: object, yaw_deg: float, pitch_deg: float, roll_deg: float = 0.0,
                       **kw: object) -> Camera:
    """The camera at ``position`` looking along heading ``yaw_deg`` (clockwise from north, -z), ``pitch_deg`` above
    the horizon and banked ``roll_deg`` to the right (see the module docstring); ``kw``: the other
    :class:`Camera` fields (fov_y_deg, width, height, near, far). Its target lies 1 m ahead."""
    p = np.asarray(_vec3("position", position))
    y, pt, r = (math.radians(check_number(n, v)) for n, v in (("yaw_deg", yaw_deg), ("pitch_deg", pitch_deg),
                                                              ("roll_deg", roll_deg)))
    fwd = np.array([math.sin(y) * math.cos(pt), math.sin(pt), -math.cos(y) * math.cos(pt)])
    right = np.array([math.cos(y), 0.0, math.sin(y)])  # the heading's right, level (defined looking straight down)
    up = _cross(right, fwd)
    up = math.cos(r) * up + math.sin(r) * right
    return Camera(position=tuple(p), target=tuple(p + fwd), up=tuple(up), **kw)


#: The columns of a camera-path CSV (:func:`read_camera_csv`), each with the other names it is read by.
CSV_COLUMNS: dict[str, tuple[str, ...]] = {
    "time_s": ("time", "t"), "x": ("pos_x", "position_x"), "y": ("pos_y", "position_y"),
    "z": ("pos_z", "position_z"), "target_x": (), "target_y": (), "target_z": (), "yaw_deg": ("yaw", "heading"),
    "pitch_deg": ("pitch",), "roll_deg": ("roll",), "fov_y_deg": ("fov", "fovy"), "width": (), "height": (),
    "near": (), "far": (),
}
_TARGET = ("target_x", "target_y", "target_z")
_ANGLES = ("yaw_deg", "pitch_deg")


def _csv_header(path: Path, header: list[str]) -> dict[str, int]:
    """Column name (its CSV_COLUMNS name) -> index; ValueError naming a repeated, missing or unknown column."""
    names = {alias: name for name, aliases in CSV_COLUMNS.items() for alias in (name, *aliases)}
    where: dict[str, int] = {}
    for i, raw in enumerate(header):
        key = raw.strip().lower()
        if key not in names:
            raise ValueError(f"{path}: column {i + 1} {raw.strip()!r}: unknown; expected some of {list(CSV_COLUMNS)}")
        if names[key] in where:
            raise ValueError(f"{path}: column {i + 1} {raw.strip()!r}: {names[key]!r} is given twice")
        where[names[key]] = i
    for need in ("x", "y", "z"):
        if need not in where:
            raise ValueError(f"{path}: missing column {need!r} (the camera's position: x, y, z in metres); the "
                             f"header has {[h.strip() for h in header]}")
    has_t, has_a = [c for c in _TARGET if c in where], [c for c in _ANGLES if c in where]
    if len(has_t) not in (0, 3) or len(has_a) not in (0, 2) or bool(has_t) == bool(has_a) or \
            ("roll_deg" in where and not has_a):
        raise ValueError(f"{path}: expected either the columns target_x, target_y, target_z or the columns yaw_deg, "
                         f"pitch_deg (and optionally roll_deg); the header has {[h.strip() for h in header]}")
    return where


def _csv_number(path: Path, row: int, line: int, col: str, text: str) -> float:
    where = f"{path}: row {row} (line {line}), column {col!r}"
    text = text.strip()
    if not text:
        raise ValueError(f"{where}: expected a number, got an empty field")
    try:
        v = float(text)
    except ValueError:
        raise ValueError(f"{where}: expected a number, got {text!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{where}: expected a finite number, got {text!r}")
    return v


def read_camera_csv(path: str | Path, *, width: int = 640, height: int = 480, fov_y_deg: float = 60.0,
                    near: float = 1.0, far: float = 1.0e5) -> tuple[list[Camera], list[float] | None]:
    """The cameras of a recorded path: a CSV file with a header row, one camera per row.

    Columns (names are case-insensitive; :data:`CSV_COLUMNS` lists the other names each is read by):
    ``x, y, z`` the position (metres, this project's world: y up); then either ``target_x, target_y, target_z``
    (the point looked at) or ``yaw_deg, pitch_deg`` and optionally ``roll_deg`` (heading clockwise from north
    (-z), pitch above the horizon, bank to the right; see the module docstring); optionally ``time_s`` (seconds,
    increasing), ``fov_y_deg``, ``width``, ``height``, ``near``, ``far`` (each row's own; left out: the
    arguments).

    Returns:
        (cameras, times): the cameras in file order, and each row's time (None without a time column).

    Raises:
        ValueError: a missing file, a missing or unknown column, or a bad value, naming the row (1 = the first
            camera; with its line in the file) and the column.
    """
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"path: no such camera-path file: {p}")
    with p.open(newline="") as f:
        rows = [r for r in csv.reader(f)]
    rows = [(i + 1, r) for i, r in enumerate(rows) if any(c.strip() for c in r) and not r[0].lstrip().startswith("#")]
    if not rows:
        raise ValueError(f"{p}: empty file; expected a header row and one row per camera")
    where = _csv_header(p, rows[0][1])
    if len(rows) < 2:
        raise ValueError(f"{p}: no cameras; expected one row per camera below the header")
    defaults = {"fov_y_deg": fov_y_deg, "width": width, "height": height, "near": near, "far": far}
    cams, times = [], []
    for k, (line, r) in enumerate(rows[1:], start=1):
        if len(r) != len(rows[0][1]):
            raise ValueError(f"{p}: row {k} (line {line}): expected {len(rows[0][1])} fields, got {len(r)}")
        v = {c: _csv_number(p, k, line, c, r[i]) for c, i in where.items()}
        if "time_s" in v and times and v["time_s"] <= times[-1]:
            raise ValueError(f"{p}: row {k} (line {line}), column 'time_s': expected a time after the previous "
                             f"row's {times[-1]:g} s, got {v['time_s']:g}")
        times.append(v.get("time_s", math.nan))
        cams.append(_csv_camera(p, k, line, v, defaults))
    return cams, (times if "time_s" in where else None)


def _csv_camera(path: Path, row: int, line: int, v: dict[str, float], defaults: dict[str, float]) -> Camera:
    """One row's camera; a value the camera refuses names the row and its column."""
    kw = {c: v.get(c, d) for c, d in defaults.items()}
    for c in ("width", "height"):
        if float(kw[c]).is_integer():
            kw[c] = int(kw[c])
    try:
        if "target_x" in v:
            return Camera(position=(v["x"], v["y"], v["z"]), target=(v["target_x"], v["target_y"], v["target_z"]),
                          **kw)
        return camera_from_angles((v["x"], v["y"], v["z"]), v["yaw_deg"], v["pitch_deg"], v.get("roll_deg", 0.0),
                                  **kw)
    except (TypeError, ValueError) as e:
        name = str(e).partition(":")[0]
        col = {"target": "target_x", "position": "x", "up": "pitch_deg"}.get(name, name)
        raise ValueError(f"{path}: row {row} (line {line}), column {col!r}: {str(e).partition(': ')[2]}") from None

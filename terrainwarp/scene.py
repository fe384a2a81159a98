"""Scenes: what to render (heightmap, camera, mesh policy) and which outputs are asked for.

A scene file is TOML; every key given is applied or refused, and every value is checked by type and range
(:mod:`terrainwarp.kernels.checks`). Every table and key it may hold is in :data:`SCENE_FILE` (``[lod]``:
:class:`LodConfig`'s fields, ``[path]``: :class:`CameraPath`'s), the table the loader checks a file against and
the API reference's scene-file page is made from::

    [heightmap]
    example = "jacksboro"        # or: path = "dem.png" (with optional dx, dz, max_height),
                                 # or: fbm = { rows = 513, seed = 1 }; stream = true to stream it
    [camera]                      # optional; default: a three-quarter view framing the terrain
    position = [x, y, z]          # with target; without both, the default view with the keys given
    target = [x, y, z]
    fov_y_deg = 45
    width = 640
    height = 480
    near = 1.0
    far = 100000.0
    [render]
    outputs = ["image", "depth", "report"]
    mesh = "grid"                 # or "lod"
    [lod]                         # LodConfig's fields: policy, tolerance_px, k, target_px, level, ...
    policy = "sse"
    [path]                        # CameraPath's fields: kind, n, waypoints, preset or clearance, ...
    kind = "flyover"              # or "orbit"; or "cameras" with file = "flight.csv" or [[path.cameras]] tables
    [viewport]                    # optional: the viewport the [lod] table's pixel knobs are measured at
    width = 960                   # (a fit writes it; left out: the path's)
    height = 540
    fov_y_deg = 60
    [budget]                      # optional: what the setting was fitted to (terrainwarp evaluate's verdict)
    budget_px = 1.0
"""

from __future__ import annotations

import inspect
import json
import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import tomli_w

from .camera import Camera, Viewport, flyover, orbit, read_camera_csv
from .heightmap import EXAMPLES, Heightmap, StreamedHeightmap
from .io.files import write_text
from .io.geotiff import TIFF_EXTS, is_gdal_raster
from .io.tiles import ArraySource, FbmSource, GeoTiffSource
from .kernels.checks import check_bool, check_choice, check_int, check_number, is_int
from .kernels.shading import SHADING_MODES
from .kernels.tessellator import FILTER_CODES, SPACING_CODES
from .schemes import SCHEMES

__all__ = ["Scene", "LodConfig", "CameraPath", "Budget", "Viewport", "SceneKey", "SCENE_FILE", "PolicySpec",
           "POLICY_TABLE", "OUTPUTS", "MESH_POLICIES", "LOD_POLICIES", "SPACINGS", "FILTERS", "MAX_TESS",
           "QUADTREE_TESS", "check_policy_numbers",
           "check_tess", "check_roots", "MAX_LOG_SCALE", "PATH_PRESETS", "GROUND_CLEARANCE", "HIGH_CLEARANCE",
           "PATH_FOV_Y_DEG"]

OUTPUTS = ("image", "depth", "normals", "curvature", "report", "mesh", "patches", "error", "counters")
MESH_POLICIES = ("grid", "lod")
SHADINGS = SHADING_MODES  # the shader's modes (terrainwarp.kernels.shading), by their one list
SPACINGS = tuple(SPACING_CODES)  # the tessellator's spacing names, in its code order
FILTERS = tuple(FILTER_CODES)
MAX_TESS = 64  # the hardware's maximum tessellation level
# A quadtree doubles the factor on edges toward a finer neighbour. The hardware's fixed-point 1/L is exact
# only for powers of two, and 2L is even and must stay <= MAX_TESS: so a quadtree policy's level T is a
# power of two in 1..MAX_TESS/2 (crack-free only then; measured by the tessellator tests).
QUADTREE_TESS = tuple(2 ** i for i in range(MAX_TESS.bit_length() - 1))  # 1, 2, 4, ..., 32

# The default camera path's clearance above the ground, as a fraction of the terrain's extent: "ground"
# (2%: about 630 m over the bundled DEM, where users fly) is the default; "high" (10%) is the path the
# reports used while the grid-image error's triangulation floor made ground-level budgets unreachable.
GROUND_CLEARANCE = 0.02
HIGH_CLEARANCE = 0.10
PATH_PRESETS = {"ground": GROUND_CLEARANCE, "high": HIGH_CLEARANCE}
PATH_FOV_Y_DEG = 60.0  # every path's field of view unless its [path] table gives fov_y_deg
MAX_PATH_CAMERAS = 100_000  # a path's cameras at most (n = 2^31 would allocate for minutes, then fail)


# ------------------------------------------------------------------------------------------------
# the scene file's keys
# ------------------------------------------------------------------------------------------------
class SceneKey(NamedTuple):
    """One key of a scene file's table: its TOML type, its default (as the file would say it, or what happens
    when it is left out) and what it means."""

    type: str
    default: str
    doc: str


#: Every table of a scene file and its keys (``[lod]`` and ``[path]``: the fields of :class:`LodConfig` and
#: :class:`CameraPath`, with their docstrings' text). The loader refuses any other key, naming the table and the
#: keys it expects.
SCENE_FILE: dict[str, dict[str, SceneKey]] = {
    "heightmap": {
        "example": SceneKey("string", '"jacksboro" (no [heightmap] table)',
                            "a bundled DEM: " + ", ".join(f'``"{e}"``' for e in EXAMPLES)),
        "path": SceneKey("string", "-", "a heightmap file (image, .npy, GeoTIFF or any GDAL raster), relative to "
                                        "the scene file's folder"),
        "dx": SceneKey("number", "the file's spacing, else 1", "sample spacing along x (columns), metres"),
        "dz": SceneKey("number", "dx", "sample spacing along z (rows), metres"),
        "max_height": SceneKey("number", "-", "an 8/16-bit image's heights scaled to 0..max_height metres "
                                              "(left out: its integer values are metres)"),
        "fbm": SceneKey("table", "-", "procedural fBm terrain: the [heightmap.fbm] table"),
        "stream": SceneKey("boolean", "false", "read the terrain tile by tile (a GeoTIFF path, or the fBm "
                                               "generated window by window) instead of loading it; another "
                                               "path, an example, or a part of a raster is loaded, then read as "
                                               "tiles"),
        "channel": SceneKey("integer", "0", "a 'path' heightmap's image channel, or its raster band minus 1"),
        "allow_nan": SceneKey("boolean", "false", "an image or .npy 'path': NaN heights are no-data holes (a "
                                                  "GDAL raster's no-data always is)"),
        "window": SceneKey("array of 2 [start, stop] pairs", "the whole raster", "a GDAL raster 'path': read "
                           "only file rows [start, stop) and columns [start, stop) ([[r0, r1], [c0, c1]])"),
        "decimate": SceneKey("integer", "1", "a GDAL raster 'path': one sample per k x k block of the file"),
        "resampling": SceneKey("string", '"average"', "a GDAL raster 'path' read with decimate > 1: GDAL's "
                                                      "resampling of each block"),
    },
    "heightmap.fbm": {
        "rows": SceneKey("integer", "257", "samples along z"),
        "cols": SceneKey("integer", "rows", "samples along x"),
        "seed": SceneKey("integer", "0", "the noise's seed: the same seed, the same terrain"),
        "max_height": SceneKey("number", "1000", "heights lie in [0, max_height] metres"),
        "dx": SceneKey("number", "10", "sample spacing along x, metres"),
        "dz": SceneKey("number", "dx", "sample spacing along z, metres"),
        "feature_size": SceneKey("number", "256", "wavelength of the first octave, samples"),
        "octaves": SceneKey("integer", "8", "octaves of noise"),
        "gain": SceneKey("number", "0.5", "amplitude factor from one octave to the next"),
        "lacunarity": SceneKey("number", "2", "frequency factor from one octave to the next"),
        "ridged": SceneKey("boolean", "false", "ridged noise (1 - abs) instead of plain fBm"),
    },
    "camera": {
        "position": SceneKey("array of 3 numbers", "a three-quarter view framing the terrain",
                             "the eye (x, y, z), metres; give target with it (without both: the default view, "
                             "with the other keys given applied)"),
        "target": SceneKey("array of 3 numbers", "-", "the point looked at (x, y, z), metres"),
        "up": SceneKey("array of 3 numbers", "[0, 1, 0]", "the up direction (y up: OpenGL's convention)"),
        "fov_y_deg": SceneKey("number", "45", "vertical field of view, degrees"),
        "width": SceneKey("integer", "640", "viewport width, pixels"),
        "height": SceneKey("integer", "480", "viewport height, pixels"),
        "near": SceneKey("number", "1", "near clip distance, metres"),
        "far": SceneKey("number", "100000", "far clip distance, metres"),
    },
    "render": {
        "outputs": SceneKey("array of strings", '["image", "depth", "report"]',
                            "what to compute, a subset of " + ", ".join(f'``"{o}"``' for o in OUTPUTS)),
        "mesh": SceneKey("string", '"grid"', '``"grid"`` (the full-resolution grid) or ``"lod"`` (the [lod] '
                                             "policy's patches, tessellated)"),
        "light_azimuth_deg": SceneKey("number", "315", "the hillshade's sun, degrees clockwise from north"),
        "light_elevation_deg": SceneKey("number", "45", "the hillshade's sun above the horizon, degrees"),
        "cull_back": SceneKey("boolean", "false", "cull back-facing triangles"),
        "shading": SceneKey("string", '"hillshade"', "how the image is coloured: "
                                                     + ", ".join(f'``"{h}"``' for h in SHADINGS)),
    },
    "lod": {},  # LodConfig's fields: filled in below the class
    "path": {},  # CameraPath's fields: filled in below the class
    "path.cameras": {
        **{k: SceneKey(t, d, doc) for k, (t, d, doc) in (
            ("position", ("array of 3 numbers", "-", "the eye (x, y, z), metres")),
            ("target", ("array of 3 numbers", "-", "the point looked at (x, y, z), metres")),
            ("up", ("array of 3 numbers", "[0, 1, 0]", "the up direction")),
            ("fov_y_deg", ("number", "45", "vertical field of view, degrees")),
            ("width", ("integer", "640", "viewport width, pixels")),
            ("height", ("integer", "480", "viewport height, pixels")),
            ("near", ("number", "1", "near clip distance, metres")),
            ("far", ("number", "100000", "far clip distance, metres")),
            ("time_s", ("number", "-", "the camera's time on the path, seconds (all cameras or none)")))},
    },
    "viewport": {
        "width": SceneKey("integer", "the path's", "viewport width, pixels"),
        "height": SceneKey("integer", "the path's", "viewport height, pixels"),
        "fov_y_deg": SceneKey("number", "the path's", "vertical field of view, degrees: with the height, the pixels "
                                                      "per radian the [lod] table's pixel knobs are measured at "
                                                      "(height / (2 tan(fov_y / 2)))"),
    },
    "budget": {
        "budget_px": SceneKey("number", "-", "the p99 screen-error budget the setting was fitted to, pixels at "
                                             "the [viewport]"),
        "max_pop_px": SceneKey("number", "-", "the worst consecutive pair's pop p99 bound, pixels (none: left out)"),
        "cost": SceneKey("string or array of strings", '"triangles"', "what the fit minimised (triangles, a "
                         "counter, llvmpipe, gpu:<profile>, a weights file, or a list of models: the worst per frame)"),
    },
}


# ------------------------------------------------------------------------------------------------
# the LOD policy table
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PolicySpec:
    """One LOD policy: its one parameter and what a sweep or a fit needs to know about it.

    Attributes:
        name: the ``LodConfig.policy`` name.
        field: the :class:`LodConfig` field that holds the parameter (also the policy class's field of
            that name in :mod:`terrainwarp.lod.policies`, and ``"log_" + field`` in the fit's parameters).
        fit_range: (lowest, highest) value the fit and its grid search explore.
        coarser_up: True when a larger value gives a coarser mesh (cheaper, more error).
        allow_zero: whether 0 is a valid value (the parameter must be finite and > 0, or >= 0).
        expects: what a valid value is, for the error message.
        help: one line for the command line.
        spacing: the spacing the policy imposes (``with_policy``), or None: keep the configuration's,
            unless that is ``fractional_odd``, which cannot stitch a quadtree's doubled edges (then ``equal``).
        reads: the other ``LodConfig`` fields the policy object takes besides ``field`` and ``hysteresis``.
    """

    name: str
    field: str
    fit_range: tuple[float, float]
    coarser_up: bool
    allow_zero: bool
    expects: str
    help: str
    spacing: str | None = None
    reads: tuple[str, ...] = ()


POLICY_TABLE: dict[str, PolicySpec] = {s.name: s for s in (
    PolicySpec("sse", "tolerance_px", (0.05, 64.0), True, False, "a positive finite number of pixels",
               "screen-space error tolerance"),
    PolicySpec("distance", "k", (0.25, 32.0), False, True, "a finite number >= 0",
               "distance policy: split below k * node size"),
    PolicySpec("continuous", "target_px", (0.5, 64.0), True, False, "a positive number of pixels per edge",
               "continuous: pixels per edge segment", spacing="fractional_odd", reads=("level",)),
)}
LOD_POLICIES = tuple(POLICY_TABLE)


def check_policy_numbers(policy: str, value: float, hysteresis: float, level: int = 0) -> None:
    """Validate a LOD policy's numbers: its parameter ``value`` (the table's ``field``), the hysteresis
    band in [0, 1) and, for a policy that reads it, the level (>= 0). Used by :class:`LodConfig` and by
    the policy objects of :mod:`terrainwarp.lod.policies`."""
    spec = POLICY_TABLE[policy]
    if not (math.isfinite(hysteresis) and 0.0 <= hysteresis < 1.0):
        raise ValueError(f"hysteresis: expected a band in [0, 1), got {hysteresis}")
    if not (math.isfinite(value) and (value >= 0 if spec.allow_zero else value > 0)):
        raise ValueError(f"{spec.field}: expected {spec.expects}, got {value}")
    if "level" in spec.reads and level < 0:
        raise ValueError(f"level: expected >= 0, got {level}")


def check_tess(tess: object, policy: str | None = None) -> int:
    """The one rule for a tessellation level T: an integer in 1..``MAX_TESS``; for a quadtree policy
    (every policy of ``POLICY_TABLE`` but ``"continuous"``, whose uniform patch grid has no doubled edges)
    a power of two in ``QUADTREE_TESS``. ``policy=None``: the terrain's own rule (no policy yet; the
    quadtree refuses a doubled edge above ``MAX_TESS`` when it selects). Returns ``int(tess)``."""
    if not is_int(tess):
        raise TypeError(f"tess: expected an integer level in 1..{MAX_TESS}, got {tess!r}")
    if not 1 <= int(tess) <= MAX_TESS:
        raise ValueError(f"tess: expected an integer level in 1..{MAX_TESS}, got {tess!r}")
    if policy is not None and policy != "continuous" and int(tess) not in QUADTREE_TESS:
        raise ValueError(f"tess: expected a power of two in 1..{QUADTREE_TESS[-1]} for the quadtree policy "
                         f"{policy!r} (doubled edges are crack-free only then; any level in 1..{MAX_TESS} "
                         f"with policy 'continuous'), got {tess!r}")
    return int(tess)


def check_roots(roots: object) -> None:
    """The one rule for root nodes: an integer >= 1, or a pair (nx, nz) of integers >= 1."""
    if isinstance(roots, tuple | list):
        if len(roots) != 2 or not all(is_int(r) for r in roots):
            raise TypeError(f"roots: expected an int or (nx, nz), got {roots!r}")
        if min(int(r) for r in roots) < 1:
            raise ValueError(f"roots: expected positive counts, got {tuple(int(r) for r in roots)}")
    elif not is_int(roots):
        raise TypeError(f"roots: expected an int or (nx, nz), got {roots!r}")
    elif int(roots) < 1:
        raise ValueError(f"roots: expected >= 1 root nodes, got {int(roots)}")


@dataclass(frozen=True)
class LodConfig:
    """How a ``mesh = "lod"`` scene selects and tessellates patches.

    Attributes:
        policy: ``"sse"`` (screen-space error, malafeev2014), ``"distance"`` (deaconu2021) or
            ``"continuous"`` (a uniform patch grid with per-edge fractional factors); see ``POLICY_TABLE``.
            Or a registered scheme (:data:`terrainwarp.schemes.SCHEMES`: ``"cdlod"``, ``"clipmaps"``,
            ``"chunked"``, yours), drawn by its mesh source with its knob values in ``params``.
        tolerance_px: sse policy: split while the projected geometric error exceeds this.
        k: distance policy: split while the eye is within ``k`` node sizes of the node's box.
        target_px: continuous policy: target pixels per triangle edge.
        level: continuous policy: the level of the uniform patch grid.
        hysteresis: band for separate split/merge thresholds (malafeev2014), in [0, 1).
        roots: root nodes (deaconu2021 tests 4, 16, 32, 64), >= 1 (:func:`check_roots`).
        tess: tessellation level T of every patch (:func:`check_tess`): a power of two in 1..32 for a
            quadtree policy (edges double toward finer neighbours), any integer in 1..64 for "continuous".
        spacing: ``"equal"``, ``"fractional_even"`` or ``"fractional_odd"``.
        filter: ``"bilinear"`` or ``"bicubic"`` height sampling in the domain shader.
        level_log_scale: sse and distance policies: a natural-log multiplier of the split threshold per quadtree
            level (entry L for level L; levels past the end: 0), each in [-10, 10]: level L splits while the
            projected error exceeds ``tolerance_px * exp(m_L)`` (sse), or while the eye is within
            ``k * size * exp(m_L)`` (distance). Empty: one threshold for every level.
        params: a scheme's knob values by name (its main parameter, e.g. CDLOD's ``first_range``, and the
            knobs it declares: :class:`terrainwarp.schemes.SchemeKnob`), checked against their ranges; a knob
            left out takes its default. Empty for the quadtree policies. Kept as sorted (name, value) pairs; a
            dict is accepted.

    The policy object a configuration selects with is ``terrainwarp.lod.make_policy(config)``.
    """

    policy: str = "sse"
    tolerance_px: float = 1.0
    k: float = 2.0
    target_px: float = 8.0
    level: int = 3
    hysteresis: float = 0.0
    roots: int = 16
    tess: int = 16
    spacing: str = "equal"
    filter: str = "bilinear"
    level_log_scale: tuple[float, ...] = ()
    params: tuple[tuple[str, float], ...] = ()

    def __post_init__(self) -> None:
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 - frozen: the checked, converted values
        try:
            for k in ("tolerance_px", "k", "target_px", "hysteresis"):
                set_(k, check_number(k, getattr(self, k)))
            set_("level", check_int("level", self.level, 0))
            check_choice("policy", self.policy, (*LOD_POLICIES, *SCHEMES))
            check_choice("spacing", self.spacing, SPACINGS)
            check_choice("filter", self.filter, FILTERS)
            quadtree = self.policy in POLICY_TABLE
            if quadtree and self.policy != "continuous" and self.spacing == "fractional_odd":
                # doubled edges (2L) are even: see QUADTREE_TESS
                raise ValueError("spacing: fractional_odd cannot stitch doubled edges (2L is even); use "
                                 "'equal' or 'fractional_even' with a quadtree, or policy 'continuous'")
            set_("tess", check_tess(self.tess, self.policy if quadtree else None))
            check_roots(self.roots)
            if isinstance(self.roots, list | tuple):
                set_("roots", tuple(int(r) for r in self.roots))
            else:
                set_("roots", int(self.roots))
            set_("level_log_scale", _log_scales(self.level_log_scale))
            set_("params", _scheme_params(self.policy, self.params))
            if quadtree:
                check_policy_numbers(self.policy, float(self.value), float(self.hysteresis), int(self.level))
        except (TypeError, ValueError) as e:
            raise type(e)(f"lod.{e}") from None

    @property
    def spec(self) -> PolicySpec:
        """The policy's row of ``POLICY_TABLE`` (ValueError for a scheme: it has a :class:`SchemeSpec`)."""
        if self.policy not in POLICY_TABLE:
            raise ValueError(f"policy: {self.policy!r} is a scheme (terrainwarp.schemes.SCHEMES), not a row of "
                             f"POLICY_TABLE")
        return POLICY_TABLE[self.policy]

    @property
    def is_scheme(self) -> bool:
        """True when the policy is a registered scheme, drawn by its mesh source."""
        return self.policy not in POLICY_TABLE

    @property
    def value(self) -> float | None:
        """The policy's parameter (``tolerance_px``, ``k`` or ``target_px``; a scheme's main parameter from
        ``params``, None when left to its default)."""
        if self.is_scheme:
            return dict(self.params).get(SCHEMES[self.policy].parameter)
        return getattr(self, POLICY_TABLE[self.policy].field)

    def level_threshold_scale(self, level: int) -> float:
        """``exp(level_log_scale[level])``: the factor of level ``level``'s split threshold (1 past the end)."""
        return math.exp(self.level_log_scale[level]) if level < len(self.level_log_scale) else 1.0

    def with_policy(self, policy: str, value: float) -> LodConfig:
        """This configuration with one policy at one parameter value (the sweeps' and the fit's unit): the
        value goes to the policy's ``POLICY_TABLE`` field (``"sse"``: ``tolerance_px``, ``"distance"``:
        ``k``, ``"continuous"``: ``target_px``). Quadtree policies keep the spacing unless it is
        ``fractional_odd`` (which cannot stitch doubled edges: then ``equal``); the continuous policy uses
        ``fractional_odd``. A scheme's value goes to its main parameter in ``params``."""
        if policy in SCHEMES:  # the scheme's main parameter; its other knobs kept when the policy stays
            kept = dict(self.params) if policy == self.policy else {}
            return replace(self, policy=policy, params={**kept, SCHEMES[policy].parameter: value})
        if policy not in POLICY_TABLE:
            check_choice("policy", policy, [*LOD_POLICIES, *SCHEMES])
        spec = POLICY_TABLE[policy]
        spacing = spec.spacing or ("equal" if self.spacing == "fractional_odd" else self.spacing)
        return replace(self, policy=policy, spacing=spacing, **{spec.field: float(value)})


MAX_LOG_SCALE = 10.0  # |level_log_scale| at most: a factor of e^10 (22026) either way


def _log_scales(v: object) -> tuple[float, ...]:
    if not isinstance(v, list | tuple):
        raise TypeError(f"level_log_scale: expected a list of numbers (one per level), got {v!r}")
    return tuple(check_number(f"level_log_scale[{i}]", m, -MAX_LOG_SCALE, MAX_LOG_SCALE) for i, m in enumerate(v))


def _scheme_params(policy: str, v: object) -> tuple[tuple[str, float], ...]:
    """``params`` as sorted (name, value) pairs, checked against the scheme's knobs (empty for a quadtree policy)."""
    if isinstance(v, Mapping):
        items = list(v.items())
    elif isinstance(v, list | tuple) and all(isinstance(p, list | tuple) and len(p) == 2 for p in v):
        items = [tuple(p) for p in v]
    else:
        raise TypeError(f"params: expected a table of knob values, got {v!r}")
    if not all(isinstance(k, str) for k, _ in items) or len({k for k, _ in items}) != len(items):
        raise TypeError(f"params: expected distinct knob names, got {v!r}")
    if policy not in SCHEMES:
        if items:
            raise ValueError(f"params: the quadtree policy {policy!r} takes its numbers as LodConfig fields, got "
                             f"{sorted(k for k, _ in items)}")
        return ()
    return tuple(sorted(SCHEMES[policy].check_params(dict(items)).items()))


_DEFAULT_WAYPOINTS = ((0.15, 0.85), (0.5, 0.55), (0.85, 0.15))


@dataclass(frozen=True)
class CameraPath:
    """A scene's camera path (its ``[path]`` table), checked once when made.

    Attributes:
        kind: ``"flyover"`` (along ``waypoints``, ``clearance`` metres or a ``preset`` fraction of the extent
            above the ground, looking 25% of the extent ahead, or less where that would look off the terrain),
            ``"orbit"`` (a circle of ``radius`` around the terrain's centre, ``elevation`` above its highest
            point, looking at the centre) or ``"cameras"`` (the ``cameras`` given: a recorded path, or the cameras
            a fit was measured on).
        n: cameras (>= 1; for ``"cameras"``, how many there are).
        waypoints: flyover: (x, z) pairs, >= 2 of them; fractions of the extent in [0, 1] (``units =
            "fraction"``) or metres (``units = "m"``).
        preset: flyover: ``"ground"`` or ``"high"`` (``PATH_PRESETS``); None: ``clearance``, else ``"ground"``.
        clearance: flyover: metres above the ground (> 0), instead of a preset.
        radius, elevation: orbit: fractions of the extent, or metres (> 0 and >= 0).
        units: ``"fraction"`` or ``"m"``.
        fov_y_deg: the cameras' field of view, in (0, 180) (``"cameras"``: the first camera's).
        cameras: ``"cameras"``: the cameras, in path order (the ``[[path.cameras]]`` tables).
        times: ``"cameras"``: each camera's time (seconds, increasing), or empty.
        file: ``"cameras"``: the CSV file they were read from (:meth:`load`; a scene file names it instead of
            listing the cameras; relative to the scene file's folder).
    """

    kind: str = "flyover"
    n: int = 8
    waypoints: tuple[tuple[float, float], ...] = _DEFAULT_WAYPOINTS
    preset: str | None = None
    clearance: float | None = None
    radius: float = 0.9
    elevation: float = 0.5
    units: str = "fraction"
    fov_y_deg: float = PATH_FOV_Y_DEG
    cameras: tuple[Camera, ...] = ()
    times: tuple[float, ...] = ()
    file: str | None = None

    def __post_init__(self) -> None:
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 - frozen: the checked values
        check_choice("path.kind", self.kind, _PATH_KEYS)
        check_choice("path.units", self.units, ("fraction", "m"))
        if self.kind == "cameras":
            self._check_cameras()
            set_("n", len(self.cameras))
            set_("fov_y_deg", self.cameras[0].fov_y_deg)
        elif self.cameras or self.times or self.file is not None:
            raise ValueError(f"path.cameras: only a path of kind = 'cameras' lists cameras, got kind = {self.kind!r}")
        set_("n", check_int("path.n", self.n, 1, MAX_PATH_CAMERAS))
        set_("fov_y_deg", check_number("path.fov_y_deg", self.fov_y_deg, 0.0, 180.0, lo_open=True, hi_open=True))
        if self.preset is not None:
            check_choice("path.preset", self.preset, PATH_PRESETS)
        if self.clearance is not None:
            set_("clearance", check_number("path.clearance", self.clearance, 0.0, lo_open=True))
            if self.preset is not None:
                raise ValueError("path.clearance: give a clearance in metres or a preset, not both")
        set_("radius", check_number("path.radius", self.radius, 0.0, lo_open=True))
        set_("elevation", check_number("path.elevation", self.elevation, 0.0))
        set_("waypoints", _waypoints(self.waypoints, self.units))

    def _check_cameras(self) -> None:
        cams = tuple(self.cameras)
        if not cams or not all(isinstance(c, Camera) for c in cams):
            raise ValueError("path.cameras: expected at least one Camera for kind = 'cameras'")
        times = tuple(check_number(f"path.times[{i}]", t) for i, t in enumerate(self.times))
        if times and (len(times) != len(cams) or any(b <= a for a, b in zip(times, times[1:]))):
            raise ValueError(f"path.times: expected one increasing time per camera ({len(cams)}), got {list(times)}")
        if self.file is not None and not isinstance(self.file, str):
            raise TypeError(f"path.file: expected a file path string, got {self.file!r}")
        object.__setattr__(self, "cameras", cams)
        object.__setattr__(self, "times", times)

    @classmethod
    def of(cls, cameras: list[Camera] | tuple[Camera, ...], times: list[float] | None = None) -> CameraPath:
        """The path of exactly these cameras (kind ``"cameras"``): what a fit saves, so that the scene loads back
        to the frames it was fitted on."""
        return cls(kind="cameras", cameras=tuple(cameras), times=tuple(times or ()))

    @classmethod
    def load(cls, path: str | Path, *, width: int = 640, height: int = 480, fov_y_deg: float = PATH_FOV_Y_DEG,
             near: float = 1.0, far: float = 1.0e5) -> CameraPath:
        """A recorded path from a CSV file (:func:`terrainwarp.camera.read_camera_csv`: columns for time, position,
        target or yaw/pitch/roll, and fov; ``width`` ... ``far`` for the columns left out). A bad or missing
        column raises ValueError naming the row and the column."""
        cams, times = read_camera_csv(path, width=width, height=height, fov_y_deg=fov_y_deg, near=near, far=far)
        return cls(kind="cameras", cameras=tuple(cams), times=tuple(times or ()), file=str(Path(path).resolve()))

    @classmethod
    def from_table(cls, d: object, base_dir: str | Path = ".", camera: Camera | None = None) -> CameraPath:
        """A ``[path]`` table: every key is applied or refused (another kind's keys are refused too). A
        ``"cameras"`` path's ``file`` is read relative to ``base_dir``, with ``camera``'s viewport, near and far
        (and the table's ``fov_y_deg``) for the columns it leaves out."""
        _check_keys("path", d, set(SCENE_FILE["path"]))
        kind = check_choice("path.kind", d.get("kind", "flyover"), _PATH_KEYS)
        own = set(_PATH_KEYS[kind])
        wrong = sorted(({k for o, keys in _PATH_KEYS.items() if o != kind for k in keys} - own) & set(d))
        if wrong:
            raise ValueError(f"path.{wrong[0]}: does not apply to kind = {kind!r}")
        if kind != "cameras":
            return cls(**d)
        rest = {k: v for k, v in d.items() if k not in ("kind", "cameras", "file", "fov_y_deg", "n")}
        if rest:
            raise ValueError(f"path.{sorted(rest)[0]}: does not apply to kind = 'cameras'")
        if ("file" in d) == ("cameras" in d):
            raise ValueError("path: a path of kind = 'cameras' takes either file = \"flight.csv\" or [[path.cameras]] "
                             "tables")
        if "file" in d:
            if not isinstance(d["file"], str):
                raise TypeError(f"path.file: expected a file path string, got {d['file']!r}")
            f = Path(d["file"]) if Path(d["file"]).is_absolute() else Path(base_dir) / d["file"]
            cam = camera or Camera((0.0, 1.0, 0.0), (0.0, 0.0, -1.0))
            loaded = cls.load(f, width=cam.width, height=cam.height, fov_y_deg=d.get("fov_y_deg", PATH_FOV_Y_DEG),
                              near=cam.near, far=cam.far)
        else:
            loaded = cls.of(*_cameras_from(d["cameras"]))
        if "n" in d and d["n"] != loaded.n:
            raise ValueError(f"path.n: the path has {loaded.n} cameras, got n = {d['n']!r}")
        return loaded


# each kind of path and the keys that apply to it only
_PATH_KEYS = {"flyover": ("waypoints", "clearance", "preset", "units"), "orbit": ("radius", "elevation", "units"),
              "cameras": ("cameras", "times", "file")}


def _cameras_from(tables: object) -> tuple[list[Camera], list[float] | None]:
    """``[[path.cameras]]`` tables as cameras and their times (every table has ``time_s``, or none)."""
    if not isinstance(tables, list) or not tables:
        raise ValueError("path.cameras: expected a non-empty array of camera tables")
    cams, times = [], []
    for i, t in enumerate(tables):
        _check_keys(f"path.cameras[{i}]", t, set(SCENE_FILE["path.cameras"]))
        t = dict(t)
        if "time_s" in t:
            times.append(t.pop("time_s"))
        for k in ("position", "target"):
            if k not in t:
                raise ValueError(f"path.cameras[{i}].{k}: missing")
        try:
            cams.append(Camera(**t))
        except (TypeError, ValueError) as e:
            raise type(e)(f"path.cameras[{i}].{e}") from None
    if times and len(times) != len(cams):
        raise ValueError("path.cameras: give time_s for every camera or for none")
    return cams, times or None


def _waypoints(w: object, units: str) -> tuple[tuple[float, float], ...]:
    if not isinstance(w, list | tuple) or len(w) < 2 or not all(isinstance(p, list | tuple) and len(p) == 2
                                                                for p in w):
        raise ValueError(f"path.waypoints: expected at least 2 [x, z] pairs, got {w!r}")
    hi = 1.0 if units == "fraction" else None
    lo = 0.0 if units == "fraction" else None
    pts = tuple((check_number(f"path.waypoints[{i}][0]", a, lo, hi), check_number(f"path.waypoints[{i}][1]", b, lo,
                                                                                  hi)) for i, (a, b) in enumerate(w))
    if len(set(pts)) == 1:
        raise ValueError(f"path.waypoints: the path has zero length (every waypoint is {list(pts[0])})")
    return pts


def _attribute_docs(cls: type) -> dict[str, str]:
    """The ``Attributes:`` section of a Google-style class docstring: name -> text (names that share an entry,
    ``a, b: text``, share its text)."""
    out: dict[str, str] = {}
    names: list[str] = []
    inside = False
    for line in inspect.cleandoc(cls.__doc__ or "").splitlines():
        if line.strip() == "Attributes:":
            inside = True
        elif inside and line and not line.startswith(" "):
            break  # the section ends at the next unindented paragraph
        elif inside and line.startswith("    ") and not line.startswith("     ") and ": " in line:
            head, _, text = line.strip().partition(": ")
            names = [n.strip() for n in head.split(",")]
            out.update(dict.fromkeys(names, text))
        elif inside and line.strip():
            for n in names:
                out[n] += " " + line.strip()
    return out


_TOML_TYPES = {"bool": "boolean", "int": "integer", "float": "number", "str": "string", "str | None": "string",
               "float | None": "number", "tuple[tuple[float, float], ...]": "array of [x, z] pairs",
               "tuple[float, ...]": "array of numbers", "tuple[tuple[str, float], ...]": "table",
               "tuple[Camera, ...]": "array of camera tables ([[path.cameras]])"}


def _keys_of(cls: type) -> dict[str, SceneKey]:
    """A config dataclass's fields as a scene table's keys: TOML type, default (None: left out), docstring text."""
    docs = _attribute_docs(cls)
    return {f.name: SceneKey(_TOML_TYPES.get(f.type, f.type), "-" if f.default is None else json.dumps(f.default),
                             docs.get(f.name, "")) for f in fields(cls)}


SCENE_FILE["lod"] = _keys_of(LodConfig)
SCENE_FILE["path"] = {k: v for k, v in _keys_of(CameraPath).items() if k != "times"}  # times: each camera's time_s


@dataclass(frozen=True)
class Budget:
    """What a setting was fitted to (a scene file's ``[budget]`` table): the verdict of ``terrainwarp evaluate``.

    Attributes:
        budget_px: the p99 screen-error budget, pixels at the scene's viewport (> 0).
        max_pop_px: the worst consecutive pair's pop p99 bound, pixels (None: no bound).
        cost: what the fit minimised (``"triangles"``, a counter name, ``"llvmpipe"``, a GPU profile
            ``"gpu:<name>"``, a weights file, or a list of models: the worst of them per frame).
    """

    budget_px: float
    max_pop_px: float | None = None
    cost: str | tuple[str, ...] = "triangles"

    def __post_init__(self) -> None:
        object.__setattr__(self, "budget_px", check_number("budget.budget_px", self.budget_px, 0.0, lo_open=True))
        if self.max_pop_px is not None:
            object.__setattr__(self, "max_pop_px", check_number("budget.max_pop_px", self.max_pop_px, 0.0))
        if isinstance(self.cost, list | tuple) and self.cost and all(isinstance(c, str) for c in self.cost):
            object.__setattr__(self, "cost", tuple(self.cost))
        elif not isinstance(self.cost, str):
            raise TypeError(f"budget.cost: expected a cost name, a weights file path or a list of models, got "
                            f"{self.cost!r}")


@dataclass(frozen=True, eq=False)
class Scene:
    """A heightmap, a camera, a mesh policy and the outputs asked for.

    Attributes:
        heightmap: the terrain.
        camera: the camera (default: :meth:`Camera.default_for` the heightmap).
        outputs: subset of ``OUTPUTS``; :func:`terrainwarp.render` runs only the stages they need.
        mesh: ``"grid"``, the full-resolution grid (two triangles per cell), or ``"lod"``: patches selected
            by the quadtree policy in ``lod`` and tessellated as the GPU does.
        lod: the :class:`LodConfig` of a ``"lod"`` scene.
        light_azimuth_deg, light_elevation_deg: the hillshade's sun.
        cull_back: cull back-facing triangles in the rasterizer.
        shading: how the image is coloured, one of ``SHADINGS``: ``"hillshade"`` (default),
            ``"level"`` / ``"patch"`` (LOD level / patch colours), ``"wireframe"`` (triangle edges over
            the hillshade), ``"splat"`` (splat-map multi-texturing, deaconu2021), ``"cracks"`` (background
            seen through the terrain in magenta).
        name: the scene's name (a scene file's stem).
        path: the :class:`CameraPath` that :meth:`camera_path` flies (a scene file's ``[path]`` table).
        viewport: the :class:`terrainwarp.camera.Viewport` the ``lod`` setting's pixel knobs are measured at (a
            scene file's ``[viewport]`` table; a fit and :func:`terrainwarp.fit.rescale` set it); None: the path's
            (:attr:`path_viewport`).
        budget: the :class:`Budget` the setting was fitted to (a scene file's ``[budget]`` table), or None.
    """

    heightmap: Heightmap
    camera: Camera | None = None
    outputs: tuple[str, ...] = ("image", "depth", "report")
    mesh: str = "grid"
    lod: LodConfig = field(default_factory=LodConfig)
    light_azimuth_deg: float = 315.0
    light_elevation_deg: float = 45.0
    cull_back: bool = False
    shading: str = "hillshade"
    name: str = "scene"
    path: CameraPath = field(default_factory=CameraPath)
    viewport: Viewport | None = None
    budget: Budget | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.heightmap, Heightmap | StreamedHeightmap):
            raise TypeError(f"heightmap: expected a Heightmap or StreamedHeightmap, got "
                            f"{type(self.heightmap).__name__}")
        if self.camera is None:
            object.__setattr__(self, "camera", Camera.default_for(self.heightmap))
        elif not isinstance(self.camera, Camera):
            raise TypeError(f"camera: expected a Camera, got {type(self.camera).__name__}")
        outs = (self.outputs,) if isinstance(self.outputs, str) else tuple(self.outputs)
        bad = [o for o in outs if o not in OUTPUTS]
        if bad:
            raise ValueError(f"outputs: unknown {bad}; expected a subset of {list(OUTPUTS)}")
        object.__setattr__(self, "outputs", tuple(dict.fromkeys(outs)))
        check_choice("shading", self.shading, SHADINGS)
        check_choice("mesh", self.mesh, MESH_POLICIES)
        if isinstance(self.lod, dict):
            object.__setattr__(self, "lod", LodConfig(**self.lod))
        if not isinstance(self.lod, LodConfig):
            raise TypeError(f"lod: expected a LodConfig, got {type(self.lod).__name__}")
        for k in ("light_azimuth_deg", "light_elevation_deg"):
            object.__setattr__(self, k, check_number(k, getattr(self, k)))
        object.__setattr__(self, "cull_back", check_bool("cull_back", self.cull_back))
        if not isinstance(self.name, str):
            raise TypeError(f"name: expected a string, got {self.name!r}")
        if isinstance(self.path, dict):
            object.__setattr__(self, "path", CameraPath.from_table(self.path))
        if not isinstance(self.path, CameraPath):
            raise TypeError(f"path: expected a CameraPath, got {type(self.path).__name__}")
        if self.viewport is not None:
            vp = self.viewport
            if not isinstance(vp, tuple | list) or len(vp) != 3:
                raise TypeError(f"viewport: expected a Viewport (width, height, fov_y_deg), got {vp!r}")
            object.__setattr__(self, "viewport", Viewport.of(*vp))
        if self.budget is not None and not isinstance(self.budget, Budget):
            raise TypeError(f"budget: expected a Budget, got {type(self.budget).__name__}")

    @property
    def path_viewport(self) -> Viewport:
        """The viewport the camera path is drawn at: a ``"cameras"`` path's first camera's, else the scene camera's
        width and height with the path's field of view."""
        if self.path.kind == "cameras":
            return self.path.cameras[0].viewport
        return Viewport(self.camera.width, self.camera.height, self.path.fov_y_deg)

    @property
    def pixel_viewport(self) -> Viewport:
        """The viewport the setting's pixel knobs are measured at: :attr:`viewport`, else :attr:`path_viewport`."""
        return self.viewport if self.viewport is not None else self.path_viewport

    def with_(self, **changes: Any) -> Scene:
        return replace(self, **changes)

    def camera_path(self, n: int | None = None, *, preset: str | None = None) -> list[Camera]:
        """The scene's camera path: its ``[path]`` table if the scene file has one, else a default
        flyover diagonally across the terrain: 8 cameras at ``GROUND_CLEARANCE`` (2% of the terrain's
        extent) above the ground, looking 25% of the path ahead, ``PATH_FOV_Y_DEG`` (60 degree) field of
        view, at the scene camera's viewport.

        Args:
            n: cameras (default: the table's ``n``, or 8).
            preset: ``"ground"`` (2% of the extent) or ``"high"`` (10%), a key of ``PATH_PRESETS``: the
                flyover's clearance, over the table's ``preset`` and ``clearance`` (the command line's
                ``--path``). None: the table's ``clearance`` (m), else its ``preset``, else ``"ground"``.

        ``[path]`` keys: ``kind = "flyover"`` with ``waypoints`` (pairs of fractions of the extent, or
        metres with ``units = "m"``), ``preset`` (``"ground"`` or ``"high"``) or ``clearance`` (m), ``n``;
        or ``kind = "orbit"`` with ``radius`` and ``elevation`` (fractions of the extent, or metres with
        units = "m") and ``n``. ``fov_y_deg`` (default 60, with or without a table). ``kind = "cameras"``: its
        cameras as they are (``n`` of them evenly spaced along the list when ``n`` is given).
        """
        if self.path.kind == "cameras":
            return self._recorded(n)
        info = self.path_info(n, preset=preset)
        hm, cam = self.heightmap, self.camera
        (x0, z0), (x1, z1) = hm.bounds_xz
        lo, hi = hm.height_range
        ext = info["extent_m"]
        far = 4.0 * ext + (hi - lo) * 4.0
        k, fov = info["n"], info["fov_y_deg"]
        if info["kind"] == "orbit":
            r, el = info["radius_m"], info["elevation_m"]
            c = (0.5 * (x0 + x1), lo, 0.5 * (z0 + z1))
            return orbit(c, r, el + (hi - lo), k, width=cam.width, height=cam.height, fov_y_deg=fov,
                         near=max(1e-3 * r, 1e-4), far=far + r)
        clearance = info["clearance_m"]
        return flyover(hm, info["waypoints_m"], clearance, k, look_ahead=0.25 * ext, width=cam.width,
                       height=cam.height, fov_y_deg=fov, near=max(clearance * 1e-2, 1e-4), far=far)

    def _recorded(self, n: int | None) -> list[Camera]:
        cams = list(self.path.cameras)
        if n is None or n == len(cams):
            return cams
        n = check_int("n", n, 1, len(cams))
        return [cams[int(i)] for i in np.round(np.linspace(0, len(cams) - 1, n)).astype(int)]

    def path_info(self, n: int | None = None, *, preset: str | None = None) -> dict[str, Any]:
        """What :meth:`camera_path` flies, for reports: ``kind``, ``n``, ``fov_y_deg``, ``extent_m`` and, for a
        flyover, ``preset`` (the preset used, or ``"custom"`` for a clearance in metres),
        ``clearance_m``, ``clearance_fraction`` (of the extent) and ``waypoints_m``; for an orbit
        ``radius_m`` and ``elevation_m``; and ``text``, one line describing it."""
        d = self.path
        n = d.n if n is None else check_int("n", n, 1, MAX_PATH_CAMERAS)
        if preset is not None:
            check_choice("preset", preset, PATH_PRESETS)
        hm = self.heightmap
        (x0, z0), (x1, z1) = hm.bounds_xz
        ext = max(x1 - x0, z1 - z0, 1e-9)
        metres = d.units == "m"
        info: dict[str, Any] = {"kind": d.kind, "n": n, "fov_y_deg": d.fov_y_deg, "extent_m": ext}
        if d.kind == "cameras":
            vp = {c.viewport for c in self._recorded(n)}
            info["n"] = len(self._recorded(n))
            info["viewports"] = [list(v) for v in sorted(vp)]
            info["text"] = (f"{info['n']} recorded cameras" + (f" of {d.n}" if info["n"] != d.n else "")
                            + (f" from {Path(d.file).name}" if d.file else "") + " at "
                            + "; ".join(Viewport(*v).text for v in sorted(vp)))
            return info
        if info["kind"] == "orbit":
            info["radius_m"] = d.radius * (1.0 if metres else ext)
            info["elevation_m"] = d.elevation * (1.0 if metres else ext)
            info["text"] = (f"orbit of {info['n']} cameras, radius {info['radius_m']:.0f} m, "
                            f"{info['elevation_m']:.0f} m above the highest point, {info['fov_y_deg']:g} degree fov")
            return info
        info["waypoints_m"] = [(a, b) if metres else (x0 + a * (x1 - x0), z0 + b * (z1 - z0)) for a, b in d.waypoints]
        if preset is None and d.clearance is not None:
            info["preset"], info["clearance_m"] = "custom", d.clearance
        else:
            info["preset"] = preset or d.preset or "ground"
            info["clearance_m"] = PATH_PRESETS[info["preset"]] * ext
        info["clearance_fraction"] = info["clearance_m"] / ext
        info["text"] = (f"flyover of {info['n']} cameras at {info['clearance_m']:.0f} m above the ground "
                        f"({info['clearance_fraction']:.1%} of the {ext:.0f} m extent; path preset "
                        f"{info['preset']!r}), looking 25% of the extent ahead, {info['fov_y_deg']:g} degree fov")
        return info

    # -- files -------------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """The scene as a scene file's tables (:data:`SCENE_FILE`): what :meth:`save` writes, and what
        :meth:`from_dict` reads back into a scene that renders the same frames. Every field is written, defaults
        included, so the file does not depend on this version's defaults.

        Raises:
            ValueError: a heightmap a scene file cannot name (made from an array, or read with a window): save
                it to a file (``np.save``) and load that.
        """
        cam = self.camera
        return {"heightmap": _heightmap_table(self.heightmap),
                "camera": {"position": list(cam.position), "target": list(cam.target), "up": list(cam.up),
                           "fov_y_deg": cam.fov_y_deg, "width": cam.width, "height": cam.height, "near": cam.near,
                           "far": cam.far},
                "render": {"outputs": list(self.outputs), "mesh": self.mesh,
                           "light_azimuth_deg": self.light_azimuth_deg,
                           "light_elevation_deg": self.light_elevation_deg, "cull_back": self.cull_back,
                           "shading": self.shading},
                "lod": _table_of(self.lod), "path": _table_of(self.path),
                **({} if self.viewport is None else {"viewport": dict(self.viewport._asdict())}),
                **({} if self.budget is None else {"budget": _table_of(self.budget)})}

    def save(self, path: str | Path) -> Path:
        """Write the scene as a TOML scene file (:meth:`to_dict`; atomically: a failed write leaves no file and
        an earlier file whole). :meth:`load` reads it back into a scene that renders the same frames."""
        return write_text(Path(path), tomli_w.dumps(self.to_dict()))

    @classmethod
    def load(cls, path: str | Path) -> Scene:
        """Read a TOML scene file (see the module docstring)."""
        p = Path(path)
        if not p.exists():
            raise FileNotFoundError(f"scene: no such file: {p}")
        if p.is_dir():
            raise ValueError(f"scene: {p} is a directory, expected a TOML file")
        try:
            data = tomllib.loads(p.read_text())
        except OSError as e:
            raise ValueError(f"scene: cannot read {p}: {e.strerror or e}") from None
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
            raise ValueError(f"scene: {p} is not valid TOML: {e}") from e
        return cls.from_dict(data, base_dir=p.parent, name=p.stem)

    @classmethod
    def from_dict(cls, data: dict, base_dir: str | Path = ".", name: str = "scene") -> Scene:
        _check_keys("scene", data, {t for t in SCENE_FILE if "." not in t})
        hm_d = data.get("heightmap", {"example": "jacksboro"})
        _check_keys("heightmap", hm_d, set(SCENE_FILE["heightmap"]))
        hm = _heightmap_from(hm_d, Path(base_dir))
        cam = _camera_from(data.get("camera"), hm)
        r = data.get("render", {})
        _check_keys("render", r, set(SCENE_FILE["render"]))
        kw = {k: r[k] for k in ("mesh", "light_azimuth_deg", "light_elevation_deg", "cull_back", "shading")
              if k in r}
        if "outputs" in r:
            if not isinstance(r["outputs"], list) or not all(isinstance(o, str) for o in r["outputs"]):
                raise TypeError(f"render.outputs: expected a list of output names, got {r['outputs']!r}")
            kw["outputs"] = tuple(r["outputs"])
        if "lod" in data:
            _check_keys("lod", data["lod"], set(SCENE_FILE["lod"]))
            kw["lod"] = LodConfig(**data["lod"])
        if "path" in data:
            kw["path"] = CameraPath.from_table(data["path"], base_dir, cam)
        if "viewport" in data:
            vp = data["viewport"]
            _check_keys("viewport", vp, set(SCENE_FILE["viewport"]))
            if set(vp) != set(SCENE_FILE["viewport"]):
                raise ValueError(f"viewport: expected the keys width, height and fov_y_deg, got {sorted(vp)}")
            kw["viewport"] = Viewport.of(*(vp[k] for k in Viewport._fields))
        if "budget" in data:
            _check_keys("budget", data["budget"], set(SCENE_FILE["budget"]))
            kw["budget"] = Budget(**data["budget"])
        return cls(heightmap=hm, camera=cam, name=name, **kw)


def _table_of(config: LodConfig | CameraPath | Budget) -> dict[str, Any]:
    """A config dataclass as its scene-file table: every field but those left None (and a path's keys of the
    other kinds), tuples as lists; a ``"cameras"`` path's cameras as ``[[path.cameras]]`` tables (or its
    ``file``)."""
    out: dict[str, Any] = {}
    skip: set[str] = set()
    if isinstance(config, CameraPath):
        skip = {k for o, keys in _PATH_KEYS.items() if o != config.kind for k in keys} - set(_PATH_KEYS[config.kind])
        if config.kind == "cameras":
            skip |= {"n", "waypoints", "clearance", "preset", "radius", "elevation", "units", "times"}
            skip |= {"cameras"} if config.file is not None else {"fov_y_deg", "file"}  # a file's: its columns' fov
    for f in fields(config):
        v = getattr(config, f.name)
        if v is None or f.name in skip:
            continue
        if f.name == "params":
            v = dict(v)
        elif f.name == "cameras":
            v = [{**c.to_dict(), **({"time_s": t} if config.times else {})}
                 for c, t in zip(v, config.times or [None] * len(v), strict=True)]
        elif isinstance(v, tuple):
            v = [list(x) if isinstance(x, tuple) else x for x in v]
        out[f.name] = v
    return out


def _heightmap_table(hm: Heightmap | StreamedHeightmap) -> dict[str, Any]:
    """The ``[heightmap]`` table that makes ``hm`` again, streamed or not: a bundled example, an fBm, or a file
    (absolute path, with the spacing it was given, and the part of a raster, the channel and the holes it was
    read with)."""
    meta = hm.meta or {}
    stream = isinstance(hm, StreamedHeightmap)
    src = hm.source if stream else None
    streamed = {"stream": True} if stream else {}
    if "designed" in meta or (stream and not isinstance(src, FbmSource | GeoTiffSource | ArraySource)):
        raise ValueError(f"heightmap: {hm.name!r} was made in memory (designed, or from your own tile source), so "
                         f"a scene file cannot name it; save its heights (Heightmap.save) and load that file")
    if meta.get("source") == "fbm" or isinstance(src, FbmSource):
        keys = ("seed", "max_height", "feature_size", "octaves", "gain", "lacunarity", "ridged")
        fbm = {k: getattr(src, k) if src is not None else meta[k] for k in keys}
        return {"fbm": {"rows": hm.shape[0], "cols": hm.shape[1], "dx": hm.dx, "dz": hm.dz, **fbm}, **streamed}
    if isinstance(src, GeoTiffSource):
        return {"path": str(Path(src.path).resolve()), "dx": hm.dx, "dz": hm.dz, "stream": True,
                **({"channel": src.band - 1} if src.band != 1 else {})}
    if hm.name in EXAMPLES and str(meta.get("source", "")).startswith("matplotlib sample data"):
        return {"example": hm.name, **streamed}
    source = meta.get("source")
    if isinstance(source, str) and Path(source).is_file():
        return {"path": str(Path(source).resolve()), "dx": hm.dx, "dz": hm.dz, **_file_keys(meta, hm), **streamed}
    raise ValueError(f"heightmap: {hm.name!r} was not read from a file, an example or fBm settings, so a scene "
                     f"file cannot name it; save its heights (Heightmap.save) and load that file")


def _file_keys(meta: dict, hm: Heightmap | StreamedHeightmap) -> dict[str, Any]:
    """The ``[heightmap]`` keys besides path and spacing that read a file as ``hm`` was read: a raster's band,
    window and decimation (a whole raster's window is no key), an image's channel, scale and holes."""
    if "raster_shape" not in meta:  # an image or .npy (Heightmap.load's own readers)
        holes = isinstance(hm, Heightmap) and hm.has_nodata
        return {**({"max_height": meta["max_height"]} if "max_height" in meta else {}),
                **({"channel": meta["channel"]} if meta.get("channel") else {}),
                **({"allow_nan": True} if holes else {})}
    (r0, c0, rows, cols), (hh, ww) = meta["window"], meta["raster_shape"]
    k = int(meta.get("decimate") or 1)
    keys: dict[str, Any] = {"channel": int(meta["band"]) - 1} if meta.get("band", 1) != 1 else {}
    if (r0, c0, rows, cols) != (0, 0, hh, ww):
        keys["window"] = [[int(r0), int(r0 + rows)], [int(c0), int(c0 + cols)]]
    if k != 1:
        keys.update(decimate=k, resampling=meta.get("resampling") or "average")
    return keys


def _camera_from(cam_d: object, hm: Heightmap | StreamedHeightmap) -> Camera | None:
    """A scene file's ``[camera]`` table: a camera at ``position`` looking at ``target``, or, with neither, the
    default three-quarter view of the terrain; either way with every other key given applied."""
    if cam_d is None:
        return None
    _check_keys("camera", cam_d, set(SCENE_FILE["camera"]))
    if "position" in cam_d or "target" in cam_d:
        if not ("position" in cam_d and "target" in cam_d):
            raise ValueError("camera: give both 'position' and 'target', or neither")
        return Camera(**cam_d)
    cam = Camera.default_for(hm, cam_d.get("width", 640), cam_d.get("height", 480), cam_d.get("fov_y_deg", 45.0))
    rest = {k: cam_d[k] for k in ("up", "near", "far") if k in cam_d}
    return cam.with_(**rest) if rest else cam


def _heightmap_from(hm_d: dict, base_dir: Path) -> Heightmap | StreamedHeightmap:
    """A scene file's ``[heightmap]`` table: one of ``example``, ``path`` or ``fbm``; ``stream = true`` opens a
    GeoTIFF path (:meth:`Heightmap.open`) or generates the fBm (:meth:`StreamedHeightmap.fbm`) tile by tile.
    ``dx``, ``dz`` and ``max_height`` go with ``path`` only (an example has its own; the fBm takes its own in its
    table): a key that would not be applied is refused."""
    stream = check_bool("heightmap.stream", hm_d.get("stream", False))
    kinds = [k for k in ("example", "path", "fbm") if k in hm_d]
    if len(kinds) != 1:
        raise ValueError("heightmap: expected one of the keys 'example', 'path' or 'fbm'" +
                         (f", got {kinds}" if kinds else ""))
    for k in ("dx", "dz", "max_height"):
        if k in hm_d and kinds[0] != "path":
            where = "its own spacing and heights" if kinds[0] == "example" else f"it in its own table (fbm.{k})"
            raise ValueError(f"heightmap.{k}: applies to a 'path' heightmap only; an {kinds[0]} takes {where}")
        if k in hm_d:
            check_number(f"heightmap.{k}", hm_d[k], 0.0, lo_open=True)
    for k in ("channel", "allow_nan", "window", "decimate", "resampling"):
        if k in hm_d and kinds[0] != "path":
            raise ValueError(f"heightmap.{k}: applies to a 'path' heightmap only")
    if kinds[0] == "example":
        hm = Heightmap.example(check_choice("heightmap.example", hm_d["example"], EXAMPLES))
        return StreamedHeightmap.of(hm) if stream else hm
    if kinds[0] == "path":
        return _heightmap_file(hm_d, base_dir, stream)
    f = hm_d["fbm"]
    _check_keys("heightmap.fbm", f, set(SCENE_FILE["heightmap.fbm"]))
    f = dict(f)
    rows = f.pop("rows", 257)
    return StreamedHeightmap.fbm(rows, **f) if stream else Heightmap.fbm(rows, **f)


def _heightmap_file(hm_d: dict, base_dir: Path, stream: bool) -> Heightmap | StreamedHeightmap:
    """A ``path`` heightmap: a GDAL raster streamed (:meth:`Heightmap.open`), else loaded (a part of a raster, an
    image, a .npy), and read as tiles when ``stream``."""
    if not isinstance(hm_d["path"], str):
        raise TypeError(f"heightmap.path: expected a file path string, got {hm_d['path']!r}")
    hp = Path(hm_d["path"])
    if not hp.is_absolute():
        hp = base_dir / hp
    channel = check_int("heightmap.channel", hm_d.get("channel", 0), 0)
    allow_nan = check_bool("heightmap.allow_nan", hm_d.get("allow_nan", False))
    raster = {k: hm_d[k] for k in ("window", "decimate", "resampling") if k in hm_d}
    if "decimate" in raster:
        check_int("heightmap.decimate", raster["decimate"], 1)
    if "resampling" in raster and not isinstance(raster["resampling"], str):
        raise TypeError(f"heightmap.resampling: expected a string, got {raster['resampling']!r}")
    gdal = hp.is_file() and is_gdal_raster(hp)
    if raster and hp.is_file() and not gdal:
        raise ValueError(f"heightmap.{sorted(raster)[0]}: applies to a GDAL raster (a GeoTIFF, .vrt, .hgt...); "
                         f"{hp.name} is read as an image or array")
    if stream and (gdal or hp.suffix.lower() in TIFF_EXTS) and not raster:  # read by windows through GDAL
        if hm_d.get("max_height") is not None:
            raise ValueError("heightmap.max_height: a streamed GeoTIFF's heights come from the file")
        return Heightmap.open(hp, hm_d.get("dx"), hm_d.get("dz"), band=channel + 1)
    try:
        hm = Heightmap.load(hp, hm_d.get("dx"), hm_d.get("dz"), max_height=hm_d.get("max_height"), channel=channel,
                            allow_nan=allow_nan, **raster)
    except (TypeError, ValueError) as e:  # name the scene key: "window: ..." -> "heightmap.window: ..."
        k = str(e).partition(":")[0]
        if k in raster:
            raise type(e)(f"heightmap.{e}") from None
        raise
    return StreamedHeightmap.of(hm) if stream else hm


def _check_keys(where: str, d: object, allowed: set[str]) -> None:
    if not isinstance(d, dict):
        raise ValueError(f"{where}: expected a table, got {type(d).__name__}")
    unknown = sorted(set(d) - allowed)
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {unknown}; expected some of {sorted(allowed)}")

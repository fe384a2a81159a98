"""Scenes: what to render (heightmap, camera, mesh policy) and which outputs are asked for.

A scene file is TOML::

    [heightmap]
    example = "jacksboro"        # or: path = "dem.png", with optional dx, dz, max_height
    [camera]                      # optional; default: a three-quarter view framing the terrain
    position = [x, y, z]
    target = [x, y, z]
    fov_y_deg = 45
    width = 640
    height = 480
    near = 1.0
    far = 100000.0
    [render]
    outputs = ["image", "depth", "report"]
    mesh = "grid"
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from .camera import Camera
from .heightmap import EXAMPLES, Heightmap

__all__ = ["Scene", "OUTPUTS", "MESH_POLICIES"]

OUTPUTS = ("image", "depth", "normals", "curvature", "report", "mesh")
MESH_POLICIES = ("grid",)


@dataclass(frozen=True, eq=False)
class Scene:
    """A heightmap, a camera, a mesh policy and the outputs asked for.

    Attributes:
        heightmap: the terrain.
        camera: the camera (default: :meth:`Camera.default_for` the heightmap).
        outputs: subset of ``OUTPUTS``; :func:`terrainwarp.render` runs only the stages they need.
        mesh: mesh policy; ``"grid"`` is the full-resolution grid (two triangles per cell).
        light_azimuth_deg, light_elevation_deg: the hillshade's sun.
        cull_back: cull back-facing triangles in the rasterizer.
    """

    heightmap: Heightmap
    camera: Camera | None = None
    outputs: tuple[str, ...] = ("image", "depth", "report")
    mesh: str = "grid"
    light_azimuth_deg: float = 315.0
    light_elevation_deg: float = 45.0
    cull_back: bool = False
    name: str = "scene"
    source: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.heightmap, Heightmap):
            raise TypeError(f"heightmap: expected a Heightmap, got {type(self.heightmap).__name__}")
        if self.camera is None:
            object.__setattr__(self, "camera", Camera.default_for(self.heightmap))
        elif not isinstance(self.camera, Camera):
            raise TypeError(f"camera: expected a Camera, got {type(self.camera).__name__}")
        outs = (self.outputs,) if isinstance(self.outputs, str) else tuple(self.outputs)
        bad = [o for o in outs if o not in OUTPUTS]
        if bad:
            raise ValueError(f"outputs: unknown {bad}; expected a subset of {list(OUTPUTS)}")
        object.__setattr__(self, "outputs", tuple(dict.fromkeys(outs)))
        if self.mesh not in MESH_POLICIES:
            raise ValueError(f"mesh: expected one of {list(MESH_POLICIES)}, got {self.mesh!r}")

    def with_(self, **changes: Any) -> Scene:
        return replace(self, **changes)

    # -- files -------------------------------------------------------------------------------------
    @classmethod
    def load(cls, path: str | Path) -> Scene:
        """Read a TOML scene file (see the module docstring)."""
        p = Path(path)
        if not p.exists():
            raise FileNotFoundError(f"scene: no such file: {p}")
        try:
            data = tomllib.loads(p.read_text())
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
            raise ValueError(f"scene: {p} is not valid TOML: {e}") from e
        return cls.from_dict(data, base_dir=p.parent, name=p.stem)

    @classmethod
    def from_dict(cls, data: dict, base_dir: str | Path = ".", name: str = "scene") -> Scene:
        _check_keys("scene", data, {"heightmap", "camera", "render"})
        hm_d = data.get("heightmap", {"example": "jacksboro"})
        _check_keys("heightmap", hm_d, {"example", "path", "dx", "dz", "max_height", "fbm"})
        if "example" in hm_d:
            if hm_d["example"] not in EXAMPLES:
                raise ValueError(f"heightmap.example: expected one of {list(EXAMPLES)}, got {hm_d['example']!r}")
            hm = Heightmap.example(hm_d["example"])
        elif "path" in hm_d:
            hp = Path(hm_d["path"])
            if not hp.is_absolute():
                hp = Path(base_dir) / hp
            hm = Heightmap.load(hp, hm_d.get("dx"), hm_d.get("dz"), max_height=hm_d.get("max_height"))
        elif "fbm" in hm_d:
            f = dict(hm_d["fbm"])
            _check_keys("heightmap.fbm", f, {"rows", "cols", "seed", "max_height", "dx", "dz", "feature_size",
                                             "octaves", "gain", "lacunarity", "ridged"})
            rows = f.pop("rows", 257)
            hm = Heightmap.fbm(rows, **f)
        else:
            raise ValueError("heightmap: expected one of the keys 'example', 'path' or 'fbm'")
        cam_d = data.get("camera")
        cam = None
        if cam_d is not None:
            _check_keys("camera", cam_d, {"position", "target", "up", "fov_y_deg", "width", "height", "near", "far"})
            if "position" in cam_d or "target" in cam_d:
                if not ("position" in cam_d and "target" in cam_d):
                    raise ValueError("camera: give both 'position' and 'target', or neither")
                cam = Camera(**cam_d)
            else:
                cam = Camera.default_for(hm, cam_d.get("width", 640), cam_d.get("height", 480),
                                         cam_d.get("fov_y_deg", 45.0))
        r = data.get("render", {})
        _check_keys("render", r, {"outputs", "mesh", "light_azimuth_deg", "light_elevation_deg", "cull_back"})
        kw = {k: r[k] for k in ("mesh", "light_azimuth_deg", "light_elevation_deg", "cull_back") if k in r}
        if "outputs" in r:
            kw["outputs"] = tuple(r["outputs"])
        return cls(heightmap=hm, camera=cam, name=name, source=data, **kw)


def _check_keys(where: str, d: object, allowed: set[str]) -> None:
    if not isinstance(d, dict):
        raise ValueError(f"{where}: expected a table, got {type(d).__name__}")
    unknown = sorted(set(d) - allowed)
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {unknown}; expected some of {sorted(allowed)}")

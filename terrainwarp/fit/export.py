"""A setting in the terms an engine takes it: :func:`export` (``terrainwarp export SCENE.toml --as FORMAT``) and
:func:`read_export`, which reads an export back into a :class:`Scene` from its engine fields alone.

Each export is one JSON file (strict: no NaN or Infinity; an unbounded range is ``null`` with the reason in
``notes``) with:

* ``format``: ``"cdlod"``, ``"cesium"`` or ``"json"``; ``exporter``: this layout's version (:data:`EXPORT_VERSION`);
* the engine's section (``cdlod`` / ``cesium`` / ``setting``), in the engine's own names and units;
* ``viewport``: the viewport its pixels hold at (``width``, ``height``, ``fov_y_deg``, ``focal_px`` = pixels per
  radian), ``pixel_knobs``: each pixel threshold as an angle, ``budget``: what it was fitted to;
* ``rule``: where each field's rule comes from; ``notes``: what to set in the engine for the same frames;
* ``scene``: the scene file's tables (heightmap, cameras, ...) so the export can be read back and drawn.

**CDLOD** (Strugar 2010, "Continuous Distance-Dependent Level of Detail for Rendering Heightmaps"; the reference
implementation ``fstrugar/CDLOD``: ``CDLODQuadTree::LODSelect`` builds the ranges, ``CDLODTerrain.vsh`` morphs;
its ``.ini`` names the settings):

* ``LODLevelCount`` (levels): LOD levels, 0 the finest; the last covers the rest of the terrain.
* ``LeafQuadTreeNodeSize`` (heightmap samples): the side of the finest quadtree node.
* ``RenderGridResolutionMult`` (1): render-grid quads per leaf-node cell (1: one vertex per sample at LOD 0).
* ``RenderGridResolution`` (quads): the grid mesh every node is drawn with (leaf size x mult a side).
* ``LODLevelDistanceRatio``: each level's band is this many times the previous one's.
* ``MorphStartRatio``: where in its band a level starts morphing toward the next.
* ``ViewRange`` (m): the reference's visibility distance, the last level's range (``LODNear`` = 0);
  terrainwarp draws the last level to the horizon.
* ``levels[i].range`` (m): LOD i is drawn where its node's box is within this of the eye.
* ``levels[i].morph_start``, ``levels[i].morph_end`` (m): the vertex morph toward LOD i+1 runs between these
  eye distances (of the unmorphed vertex); the end pulled 1% toward the start (the reference's float guard);
  null for the last level, which does not morph.
* ``levels[i].node_size`` (m): the side of LOD i's nodes along x and z.

**Cesium** (CesiumJS: ``Globe.maximumScreenSpaceError``; ``QuadtreePrimitive`` tests ``geometricError *
drawingBufferHeight / (distance * 2 tan(fovy / 2))`` against it, ``TerrainProvider.
getEstimatedLevelZeroGeometricErrorForAHeightmap`` gives the errors): ``maximumScreenSpaceError`` (px at
``viewport``), ``drawingBufferHeight`` (px), ``fovy`` (radians), ``tileSamples`` (65), ``levelZeroTiles`` (x,
z), ``levelZeroTileWidth`` (m), ``levelMaximumGeometricError`` (m per level), ``heightmapTerrainQuality``
(0.25). Only a ``cesium`` setting exports to Cesium: ``chunked`` measures its chunks' errors, Cesium estimates
them from the tiling, so the same number selects other tiles.

**json**: the family, its knobs (``values``), the ``[lod]`` table, and, for a CDLOD or Cesium setting, the
engine section as well.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from ..camera import Viewport
from ..io.files import write_json
from ..lod.cdlod import Cdlod, cdlod_ranges
from ..lod.cesium import CesiumTerrain, cesium_roots
from ..lod.policies import CESIUM_HEIGHTMAP_QUALITY, CESIUM_TILE_SAMPLES
from ..rendering.sources import scene_source
from ..scene import LodConfig, Scene
from .knobs import knobs, values_of
from .viewport import RULES, pixel_knobs

__all__ = ["export", "export_dict", "read_export", "FORMATS", "EXPORT_VERSION", "CDLOD_SOURCE", "CESIUM_SOURCE"]

FORMATS = ("cdlod", "cesium", "json")
EXPORT_VERSION = 1  # the layout of an export file
CDLOD_SOURCE = ("Strugar 2010, Continuous Distance-Dependent Level of Detail for Rendering Heightmaps; reference "
                "implementation fstrugar/CDLOD (CDLODQuadTree::LODSelect, CDLODTerrain.vsh)")
CESIUM_SOURCE = ("CesiumJS: Globe.maximumScreenSpaceError; QuadtreePrimitive screenSpaceError and visitTile; "
                 "TerrainProvider.getEstimatedLevelZeroGeometricErrorForAHeightmap; HeightmapTerrainData skirts")


def _viewport_table(vp: Viewport) -> dict[str, Any]:
    return {"width": vp.width, "height": vp.height, "fov_y_deg": vp.fov_y_deg, "focal_px": vp.focal_px}


def _cdlod(scene: Scene) -> dict[str, Any]:
    """The CDLOD section of a cdlod setting (see the module docstring)."""
    src = scene_source(scene)
    c: Cdlod = src.scheme
    rng, start, end = cdlod_ranges(c.first_range, c.ratio, c.morph_start_ratio, c.levels)
    t = c.terrain
    fin = lambda v: float(v) if math.isfinite(v) else None  # noqa: E731
    view_range = c.first_range * sum(c.ratio ** i for i in range(c.levels))
    levels = [{"lod": i, "range": fin(rng[i]), "morph_start": fin(start[i]), "morph_end": fin(end[i]),
               "node_size": list(t.node_size_world(t.depth - i))} for i in range(c.levels)]
    return {"LODLevelCount": c.levels, "LeafQuadTreeNodeSize": c.grid, "RenderGridResolutionMult": 1,
            "RenderGridResolution": c.grid, "LODLevelDistanceRatio": c.ratio, "MorphStartRatio": c.morph_start_ratio,
            "ViewRange": view_range, "levels": levels,
            "units": {"LeafQuadTreeNodeSize": "heightmap samples", "RenderGridResolution": "quads per node side",
                      "ViewRange": "m", "range": "m", "morph_start": "m", "morph_end": "m", "node_size": "m"}}


def _cesium(scene: Scene, vp: Viewport) -> dict[str, Any]:
    """The Cesium section of a cesium setting (see the module docstring)."""
    src = scene_source(scene)
    c: CesiumTerrain = src.scheme
    return {"maximumScreenSpaceError": float(c.max_sse_px), "drawingBufferHeight": vp.height,
            "drawingBufferWidth": vp.width, "fovy": math.radians(vp.fov_y_deg), "tileSamples": CESIUM_TILE_SAMPLES,
            "heightmapTerrainQuality": CESIUM_HEIGHTMAP_QUALITY, "levelZeroTiles": list(c.terrain.roots),
            "levelZeroTileWidth": c.level0_width_m,
            "levelMaximumGeometricError": [float(c.level_error(L)) for L in range(c.terrain.depth + 1)],
            "apply": f"viewer.scene.globe.maximumScreenSpaceError = {float(c.max_sse_px):.6g};",
            "units": {"maximumScreenSpaceError": "px", "drawingBufferHeight": "px", "fovy": "rad",
                      "levelZeroTileWidth": "m", "levelMaximumGeometricError": "m"}}


def export_dict(scene: Scene, fmt: str) -> dict[str, Any]:
    """The export of ``scene`` (a LOD setting) as ``fmt`` (:data:`FORMATS`), as a dict (see the module docstring).

    Raises:
        ValueError: an unknown format, a grid scene, or a setting of another family than the format's.
    """
    if fmt not in FORMATS:
        raise ValueError(f"as: expected one of {list(FORMATS)}, got {fmt!r}")
    if scene.mesh != "lod":
        raise ValueError("scene: expected a LOD setting (render.mesh = 'lod'), got a grid scene")
    policy = scene.lod.policy
    if fmt in ("cdlod", "cesium") and policy != fmt:
        hint = " (a chunked setting's max_sse_px uses measured chunk errors, not Cesium's: fit policy 'cesium')" \
            if fmt == "cesium" and policy == "chunked" else ""
        raise ValueError(f"as: a {fmt} export takes a {fmt!r} setting, got policy {policy!r}{hint}")
    vp = scene.pixel_viewport
    names = [k.name for k in knobs(policy, scene.heightmap, None if scene.lod.is_scheme else scene.lod)]
    out: dict[str, Any] = {"format": fmt, "exporter": EXPORT_VERSION, "policy": policy,
                           "viewport": _viewport_table(vp),
                           "pixel_knobs": pixel_knobs(scene, scene.budget.budget_px if scene.budget else None),
                           "budget": None if scene.budget is None else dict(scene.budget.__dict__),
                           "rule": {"rescale": f"{RULES[policy].knob}: {RULES[policy].text}" if policy in RULES
                                    else None}}
    if policy == "cdlod":
        out["cdlod"] = _cdlod(scene)
        out["rule"]["cdlod"] = CDLOD_SOURCE
        out["notes"] = ["terrainwarp draws the last LOD level to the horizon; the reference stops at ViewRange",
                        "morph_end is pulled 1% toward morph_start, as the reference guards float rounding"]
    if policy == "cesium":
        out["cesium"] = _cesium(scene, vp)
        out["rule"]["cesium"] = CESIUM_SOURCE
        out["notes"] = ["Cesium's fog lowers far tiles' error: scene.fog.enabled = false for the same selection",
                        "pixelRatio 1 (resolutionScale 1 on a display scale of 1): Cesium divides the error by it",
                        f"the viewport is {vp.text}; another viewport: terrainwarp.fit.rescale, or export --viewport"]
    if fmt == "json":
        vals = {n: v for n, v in values_of(scene, policy, names).items() if not math.isnan(v)}
        out["setting"] = {"values": vals, "lod": scene.to_dict()["lod"]}
    out["scene"] = {k: v for k, v in scene.to_dict().items() if k != "lod"}
    return out


def export(scene: Scene, fmt: str, path: str | Path) -> Path:
    """Write :func:`export_dict` of ``scene`` as ``fmt`` to ``path`` (strict JSON, atomically); returns the path."""
    return write_json(Path(path), export_dict(scene, fmt))


def read_export(data: dict | str | Path, base_dir: str | Path = ".") -> Scene:
    """The scene an export describes: its ``scene`` tables, with the LOD setting made from the engine's fields
    alone (a CDLOD export's ranges, ratio, morph start and grid; a Cesium export's maximumScreenSpaceError; a json
    export's ``setting.lod``), checked against what terrainwarp's family can draw.

    Raises:
        ValueError: a file that is not an export, or engine fields terrainwarp's family cannot reproduce (ranges
            that are not ``first_range * (1 + ratio + ...)``, another level count or tile size), named.
    """
    if not isinstance(data, dict):
        p = Path(data)
        base_dir = p.parent
        data = _read_strict(p)
    fmt = data.get("format") if isinstance(data, dict) else None
    if fmt not in FORMATS or "scene" not in data:
        raise ValueError(f"export: expected a terrainwarp export (format one of {list(FORMATS)} and a scene), got "
                         f"{fmt!r}")
    base = Scene.from_dict({**data["scene"]}, base_dir=base_dir)
    if fmt == "json":
        lod = LodConfig(**data["setting"]["lod"])
    elif fmt == "cdlod":
        lod = _cdlod_config(data["cdlod"])
    else:
        lod = _cesium_config(data["cesium"])
    scene = base.with_(mesh="lod", lod=lod)
    if fmt == "cdlod":
        got = scene_source(scene).scheme.levels
        if got != data["cdlod"]["LODLevelCount"]:
            raise ValueError(f"cdlod.LODLevelCount: terrainwarp's CDLOD of this heightmap and grid has {got} levels, "
                             f"the export {data['cdlod']['LODLevelCount']}")
    if fmt == "cesium":
        roots = list(cesium_roots(scene.heightmap.shape))
        if roots != list(data["cesium"]["levelZeroTiles"]):
            raise ValueError(f"cesium.levelZeroTiles: this heightmap has {roots}, the export "
                             f"{data['cesium']['levelZeroTiles']}")
    return scene


def _read_strict(p: Path) -> dict:
    """A JSON file, refusing NaN and Infinity tokens (an export never writes them)."""
    if not p.is_file():
        raise ValueError(f"export: no such file: {p}")

    def refuse(token: str) -> None:
        raise ValueError(f"export: {p} holds {token}, which strict JSON has not")

    try:
        data = json.loads(p.read_text(), parse_constant=refuse)
    except json.JSONDecodeError as e:
        raise ValueError(f"export: {p} is not JSON: {e}") from None
    if not isinstance(data, dict):
        raise ValueError(f"export: {p} is not a terrainwarp export (a JSON object)")
    return data


def _cdlod_config(c: dict[str, Any]) -> LodConfig:
    """CDLOD's engine fields as terrainwarp's cdlod knobs, checked: the ranges must be the ratio's."""
    levels = c["levels"]
    first, ratio, msr = float(levels[0]["range"]), float(c["LODLevelDistanceRatio"]), float(c["MorphStartRatio"])
    if c.get("RenderGridResolutionMult", 1) != 1 or c["RenderGridResolution"] != c["LeafQuadTreeNodeSize"]:
        raise ValueError("cdlod.RenderGridResolutionMult: terrainwarp's CDLOD draws one vertex per sample at LOD 0 "
                         f"(1), got {c.get('RenderGridResolutionMult')}")
    rng, start, end = cdlod_ranges(first, ratio, msr, len(levels))
    for i, lv in enumerate(levels[:-1]):
        for name, want in (("range", rng[i]), ("morph_start", start[i]), ("morph_end", end[i])):
            if not math.isclose(float(lv[name]), float(want), rel_tol=1e-9):
                raise ValueError(f"cdlod.levels[{i}].{name}: {lv[name]} is not the rule's {want:.6g} (first range "
                                 f"{first:g}, ratio {ratio:g}, morph start ratio {msr:g})")
    return LodConfig(policy="cdlod", params={"first_range": first, "ratio": ratio, "morph_start_ratio": msr,
                                             "grid": int(c["RenderGridResolution"])})


def _cesium_config(c: dict[str, Any]) -> LodConfig:
    if c.get("tileSamples") != CESIUM_TILE_SAMPLES:
        raise ValueError(f"cesium.tileSamples: Cesium's heightmap tiles have {CESIUM_TILE_SAMPLES} samples a side, "
                         f"got {c.get('tileSamples')}")
    return LodConfig(policy="cesium", params={"max_sse_px": float(c["maximumScreenSpaceError"])})


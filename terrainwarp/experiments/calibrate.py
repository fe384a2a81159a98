"""Fit a cost model's weights to a real driver's frame times: ``terrainwarp calibrate --gl``.

Every family is drawn as a GPU would draw it, by a real OpenGL driver through EGL (:mod:`.gl`; Mesa's llvmpipe
on this project's machines): the quadtree policies (``sse``, ``distance``, ``continuous``) as one patch draw
through tessellation shaders (batched under llvmpipe's 65,536-vertex limit), every other family (the
full-resolution ``grid``, CDLOD, geometry clipmaps, Chunked LOD, Martini, Delatin, the polytree and the
bintree) as indexed triangles of the same clip-space vertices, one ``glDrawElements`` per draw call the family
issues (:class:`terrainwarp.mesh.Draws`). The same frame is rendered by terrainwarp with ``"counters"``
(``Report.counters``).

Frames: per family ``frames_per_family`` (default 50) of its settings (fine to coarse) crossed with cameras
(the scene's flyover at the ground and high presets, an orbit, the whole terrain in view) and viewports (640x360,
1280x720, 1920x1080), drawn in a seeded order. Each frame's time is the least of ``reps`` draws after a warm-up,
on the clock :func:`time_column` picks for the driver: on Mesa's llvmpipe (a CPU renderer) the CPU time of the
driver's draws and ``glFinish`` (``time.process_time``: every thread of the process, the work done, which a loaded
machine disturbs far less than wall time; ``terrainwarp calibrate`` runs llvmpipe single-threaded,
``LP_NUM_THREADS=0`` unless set, so the time adds up over the frame's work); on any other driver (a GPU) the
GPU's own clock, a ``GL_TIME_ELAPSED`` query around the draws. Every clock is in ``calibration.csv``
(``gl_cpu_ms``, ``gl_wall_ms``, ``gl_gpu_ms``); the weights file names the driver, its threads and the clock.

Fit: non-negative least squares of the frame times (ms) on an intercept and :data:`terrainwarp.measure.cost.
MODEL_FEATURES`, on a seeded 75% of each family's frames; R^2 is reported on the other 25% (held out), overall
and per family. The weights file (:class:`terrainwarp.measure.cost.CostModel`), the frames (``calibration.csv``)
and a summary (``calibration.md``) are written as one set (:func:`terrainwarp.io.files.output_set`).
"""

from __future__ import annotations

import math
import os
import re
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..heightmap import Heightmap
from ..io.files import output_set, write_text
from ..kernels.checks import check_choice, check_int
from ..kernels.counters import PIPELINE_COUNTERS
from ..lod.bintree import Bintree
from ..lod.peers import delatin_mesh, martini_mesh
from ..lod.polytree import build_polytree, default_tolerances
from ..lod.quadtree import Terrain
from ..measure.cost import MODEL_FEATURES, CostModel
from ..rendering.pipeline import Frame, MeshSource, render
from ..rendering.sources import BintreeSource, PeerSource, PolytreeSource
from ..scene import CameraPath, LodConfig, Scene
from ..schemes import scheme_range, scheme_source
from .gl import FrameDriver
from .pareto import rows_to_csv

__all__ = ["calibrate", "calibration_frames", "fit_cost_model", "time_column", "model_name", "FAMILIES", "VIEWPORTS",
           "CalibrationFrame", "CLOCKS"]

VIEWPORTS = ((640, 360), (1280, 720), (1920, 1080))
_QUADTREE = ("sse", "distance", "continuous")
FAMILIES = (*_QUADTREE, "grid", "cdlod", "clipmaps", "chunked", "martini", "delatin", "polytree", "bintree")
HOLDOUT = 0.25
#: what each time column of calibration.csv measures
CLOCKS = {"gl_cpu_ms": "CPU time of the process (time.process_time) over the draws and glFinish",
          "gl_wall_ms": "wall time over the draws and glFinish",
          "gl_gpu_ms": "the GPU's own clock: a GL_TIME_ELAPSED query around the draws"}


def time_column(renderer: str) -> str:
    """The time a driver is fitted to: llvmpipe (Mesa's CPU renderer) its process CPU time, any other driver (a
    GPU) its GPU timer."""
    return "gl_cpu_ms" if "llvmpipe" in renderer.lower() else "gl_gpu_ms"


def model_name(renderer: str) -> str:
    """A weights file's model name from the driver's GL_RENDERER: ``"llvmpipe"``, else its words in lower case
    joined by dashes up to the first ``/`` or ``(`` (``"NVIDIA GeForce RTX 3080/PCIe/SSE2"`` ->
    ``"nvidia-geforce-rtx-3080"``)."""
    if "llvmpipe" in renderer.lower():
        return "llvmpipe"
    head = re.split(r"[/(]", renderer, maxsplit=1)[0]
    return "-".join(re.findall(r"[a-z0-9]+", head.lower())) or "gl"


@dataclass(frozen=True)
class CalibrationFrame:
    """One frame to measure: a family at a setting, a camera (with its viewport)."""

    family: str
    param: float
    camera: Camera


def _settings(family: str, hm: Heightmap, cache: dict) -> list[float]:
    """A family's settings, fine to coarse."""
    lo, hi = hm.height_range
    relief = max(hi - lo, 1e-6)
    rows, cols = hm.shape
    table = {"sse": [0.25, 0.5, 1.0, 2.0, 4.0, 8.0], "distance": [16.0, 8.0, 4.0, 2.0, 1.0],
             "continuous": [1.0, 2.0, 4.0, 8.0, 16.0], "grid": [0.0], "clipmaps": [31.0, 63.0, 127.0, 255.0],
             "chunked": [0.5, 1.0, 2.0, 4.0, 8.0], "polytree": [1.0, 2.0, 4.0, 8.0, 12.0],
             "martini": [relief * f for f in (0.0005, 0.002, 0.008, 0.03)],
             "delatin": [relief * f for f in (0.0005, 0.002, 0.008, 0.03)]}
    if family == "cdlod":
        first, _ = scheme_range("cdlod", hm, cache=cache)
        return [first * f for f in (8.0, 4.0, 2.0, 1.0)]
    if family == "bintree":
        m_full = 2 * max(1, math.ceil(math.log2(max(rows, cols, 2) - 1))) + 1
        return [float(m_full), float(m_full + 2)]
    return table[family]


def _cameras(hm: Heightmap) -> list[Camera]:
    """Viewpoints at 1920x1080 (a frame takes its viewport from :data:`VIEWPORTS`)."""
    base = Scene(hm, camera=Camera.default_for(hm, 1920, 1080))
    cams = [base.camera] + base.camera_path(6, preset="ground") + base.camera_path(6, preset="high")
    orbit = Scene(hm, camera=base.camera, path=CameraPath(kind="orbit", n=4)).camera_path()
    return cams + orbit


def calibration_frames(hm: Heightmap, frames_per_family: int = 50, seed: int = 0,
                       families: tuple[str, ...] = FAMILIES) -> list[CalibrationFrame]:
    """``frames_per_family`` frames of each family (its settings crossed with the cameras and viewports, a seeded
    choice when there are more), in a seeded order."""
    rng = np.random.default_rng(seed)
    cams = _cameras(hm)
    cache: dict = {}
    out = []
    for fam in families:
        combos = [(p, c, v) for p in _settings(fam, hm, cache) for c in range(len(cams)) for v in range(len(VIEWPORTS))]
        pick = rng.choice(len(combos), size=min(frames_per_family, len(combos)), replace=False)
        for k in sorted(pick.tolist()):
            p, c, v = combos[k]
            w, h = VIEWPORTS[v]
            out.append(CalibrationFrame(fam, float(p), cams[c].with_(width=w, height=h)))
    order = rng.permutation(len(out))
    return [out[i] for i in order]


class _Sources:
    """The mesh sources and terrain of one heightmap, built once per family setting."""

    def __init__(self, hm: Heightmap):
        self.hm, self.cache, self.built = hm, {}, {}
        self.terrain = Terrain.prepare(hm)

    def get(self, family: str, param: float) -> MeshSource | None:
        if family in (*_QUADTREE, "grid"):
            return None
        key = (family, param)
        if key not in self.built:
            hm = self.hm
            if family in ("cdlod", "clipmaps", "chunked"):
                src = scheme_source(family, hm, param, cache=self.cache)
            elif family in ("martini", "delatin"):
                mesher = martini_mesh if family == "martini" else delatin_mesh
                src = PeerSource(mesher(hm, param), hm, cache=self.cache)
            elif family == "polytree":
                if "tree" not in self.cache:
                    self.cache["tree"] = build_polytree(hm, default_tolerances(hm, 64))
                src = PolytreeSource(self.cache["tree"], int(param), cache=self.cache)
            else:
                src = BintreeSource(Bintree.build(hm, int(param)), cache=self.cache)
            self.built[key] = src
        return self.built[key]


def _ours(spec: CalibrationFrame, sources: _Sources) -> Frame:
    hm = sources.hm
    outputs = ("depth", "counters", "mesh", "patches")
    if spec.family in _QUADTREE:
        lod = LodConfig().with_policy(spec.family, spec.param)
        return render(Scene(hm, camera=spec.camera, mesh="lod", lod=lod, outputs=outputs), terrain=sources.terrain)
    src = sources.get(spec.family, spec.param)
    return render(Scene(hm, camera=spec.camera, outputs=outputs), source=src)


def _time(driver: FrameDriver, f: Frame, reps: int) -> tuple[float, float, float, dict]:
    """(least CPU ms, least wall ms, least GPU-timer ms, the driver's counters) of drawing frame ``f`` as its
    family does, ``reps`` times after a warm-up (the warm-up counted)."""
    draw, release = driver.draws(f)
    try:
        got = draw(True)[4]
        runs = []
        for _ in range(reps):
            wall, cpu = draw()[2:4]
            runs.append((wall, cpu, driver.last.last_gpu_ms))
    finally:
        release()
    return 1e3 * min(r[1] for r in runs), 1e3 * min(r[0] for r in runs), min(r[2] for r in runs), got


def measure(frames: list[CalibrationFrame], hm: Heightmap, reps: int = 3, progress: bool = True) -> list[dict]:
    """One row per frame: family, setting, viewport, triangles, our counters, the driver's CPU and wall ms and its
    own counters (``gl_`` + name)."""
    bar = None
    if progress:
        from tqdm import tqdm  # lazy: heavy optional dependency

        bar = tqdm(total=len(frames), desc="calibrate", unit="frame", leave=False, file=sys.stderr)
    sources, driver = _Sources(hm), FrameDriver()
    rows = []
    try:
        for k, spec in enumerate(frames):
            f = _ours(spec, sources)
            cpu_ms, wall_ms, gpu_ms, got = _time(driver, f, reps)
            rows.append({"frame": k, "family": spec.family, "param": spec.param, "width": spec.camera.width,
                         "height": spec.camera.height, "triangles": f.mesh.n_triangles,
                         **{c: f.report.counters[c] for c in PIPELINE_COUNTERS}, "gl_cpu_ms": cpu_ms,
                         "gl_wall_ms": wall_ms, "gl_gpu_ms": gpu_ms, **{f"gl_{c}": v for c, v in got.items()}})
            if bar is not None:
                bar.update(1)
    finally:
        driver.close()
        if bar is not None:
            bar.close()
    for r in rows:
        r["driver"] = driver.renderer
    return rows


def _split(rows: list[dict], seed: int) -> np.ndarray:
    """True for the held-out rows: a seeded ``HOLDOUT`` of each family's."""
    rng = np.random.default_rng(seed + 1)
    held = np.zeros(len(rows), bool)
    for fam in dict.fromkeys(r["family"] for r in rows):
        idx = [i for i, r in enumerate(rows) if r["family"] == fam]
        n = max(1, round(HOLDOUT * len(idx))) if len(idx) > 1 else 0
        held[rng.choice(idx, size=n, replace=False)] = True
    return held


def _r2(y: np.ndarray, p: np.ndarray) -> float:
    ss = float(((y - y.mean()) ** 2).sum())
    return 1.0 - float(((y - p) ** 2).sum()) / ss if ss > 0 else math.nan


def fit_cost_model(rows: list[dict], *, seed: int = 0, target: str = "gl_cpu_ms", name: str = "llvmpipe",
                   command: str = "") -> tuple[CostModel, dict]:
    """Non-negative least squares of ``target`` on an intercept and :data:`MODEL_FEATURES` over the rows not held
    out (:func:`_split`); returns the model and its fit: R^2 held out overall and per family, and the rows'
    predictions (``predicted``) and held-out flags (``held_out``)."""
    from scipy.optimize import nnls  # lazy: heavy optional dependency

    if len(rows) < len(MODEL_FEATURES) + 2:
        raise ValueError(f"rows: expected at least {len(MODEL_FEATURES) + 2} frames to fit, got {len(rows)}")
    x = np.array([[float(r[c]) for c in MODEL_FEATURES] for r in rows])
    y = np.array([float(r[target]) for r in rows])
    held = _split(rows, seed)
    scale = np.maximum(x[~held].std(axis=0), 1e-12)  # conditioning: the weights come back in ms per unit
    a = np.concatenate([np.ones((len(rows), 1)), x / scale], axis=1)
    coef, _ = nnls(a[~held], y[~held])
    pred = a @ coef
    weights = {c: float(coef[1 + i] / scale[i]) for i, c in enumerate(MODEL_FEATURES)}
    fams = dict.fromkeys(r["family"] for r in rows)
    per_family = {f: _r2(y[held & m], pred[held & m]) for f in fams
                  if (held & (m := np.array([r["family"] == f for r in rows]))).sum() >= 2}
    model = CostModel(name=name, weights=weights, intercept_ms=float(coef[0]),
                      driver=rows[0].get("driver", "") + f" (LP_NUM_THREADS={os.environ.get('LP_NUM_THREADS', '')})"
                      + ("" if target == "gl_cpu_ms" else f"; timed by {CLOCKS.get(target, target)}"),
                      r2_heldout=_r2(y[held], pred[held]), frames=len(rows),
                      families={f: sum(r["family"] == f for r in rows) for f in fams}, command=command)
    return model, {"r2_heldout": model.r2_heldout, "r2_fit": _r2(y[~held], pred[~held]), "per_family": per_family,
                   "predicted": pred, "held_out": held}


def calibrate(out_dir: str | Path, *, frames_per_family: int = 50, seed: int = 0, reps: int = 3,
              families: tuple[str, ...] = FAMILIES, heightmap: Heightmap | None = None, progress: bool = True,
              command: str = "") -> tuple[CostModel, list[Path]]:
    """Measure the driver's frame times (:func:`calibration_frames`, :func:`measure`), fit the weights
    (:func:`fit_cost_model`) and write ``weights.json`` (the model), ``calibration.csv`` (every frame: our
    counters, the driver's times and counters, the prediction, held out or not) and ``calibration.md``."""
    check_int("frames_per_family", frames_per_family, 2)
    check_int("reps", reps, 1)
    for k, f in enumerate(families):
        check_choice(f"families[{k}]", f, FAMILIES)
    hm = heightmap if heightmap is not None else Heightmap.example()
    t0 = time.perf_counter()
    rows = measure(calibration_frames(hm, frames_per_family, seed, families), hm, reps=reps, progress=progress)
    renderer = rows[0].get("driver", "") if rows else ""
    target = time_column(renderer)
    model, fit = fit_cost_model(rows, seed=seed, target=target, name=model_name(renderer), command=command)
    for r, p, h in zip(rows, fit["predicted"], fit["held_out"], strict=True):
        r["predicted_ms"], r["held_out"] = float(p), bool(h)
    out = Path(out_dir)
    texts = {"weights.json": model.to_json(), "calibration.csv": rows_to_csv(rows),
             "calibration.md": _summary(model, fit, rows, time.perf_counter() - t0)}
    out.mkdir(parents=True, exist_ok=True)
    with output_set(out):  # the set is whole: every file written, then all renamed into place
        paths = [write_text(out / n, t) for n, t in texts.items()]
    return model, paths


def _summary(model: CostModel, fit: dict, rows: list[dict], seconds: float) -> str:
    fams = list(dict.fromkeys(r["family"] for r in rows))
    lines = [f"# Cost model calibration: {model.name}", "", f"Driver: {model.driver}.", "",
             f"Command: `{model.command}`" if model.command else "", "",
             f"{len(rows)} frames ({', '.join(f'{f} {model.families[f]}' for f in fams)}), {seconds:.0f} s; fit on "
             f"{int((~fit['held_out']).sum())}, held out {int(fit['held_out'].sum())}.", "",
             f"R^2 held out: **{fit['r2_heldout']:.3f}** (on the fitted frames {fit['r2_fit']:.3f}).", "",
             "| weight | ms per unit |", "|---|---|", f"| intercept | {model.intercept_ms:.4g} |"]
    lines += [f"| {k} | {w:.4g} |" for k, w in model.weights.items()]
    col = time_column(rows[0].get("driver", "")) if rows else "gl_cpu_ms"
    lines += ["", f"Driver ms: `{col}`, {CLOCKS[col]}.", "",
              "| family | frames | R^2 held out | mean driver ms | mean modelled ms |", "|---|---|---|---|---|"]
    for f in fams:
        rs = [r for r in rows if r["family"] == f]
        lines.append(f"| {f} | {len(rs)} | {fit['per_family'].get(f, math.nan):.3f} | "
                     f"{np.mean([r[col] for r in rs]):.2f} | {np.mean([r['predicted_ms'] for r in rs]):.2f} |")
    return "\n".join(lines) + "\n"

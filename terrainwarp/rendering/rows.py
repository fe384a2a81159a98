"""One row per frame, from one schema: what sweeps write to ``frames.csv``, reports summarise and fits read.

A row is a frame's report (stage times, the mesh drawn), its error (:class:`terrainwarp.measure.error.FrameError`'s
numbers, in its field order), its pipeline statistics (:data:`terrainwarp.kernels.counters.PIPELINE_COUNTERS`,
when the frame counted them) and what the caller adds of :data:`EXTRA_COLUMNS` (popping, a prebuilt source's
build time and error, the modelled cost). :func:`frame_row` builds it; :data:`ROW_COLUMNS` is its order.

Timings (:data:`TIMING_COLUMNS`) are this simulator's CPU milliseconds: they differ from run to run. Everything
else, ``cost_ms`` (a cost model of the counters) included, is the same on every run, thread count and machine.
"""

from __future__ import annotations

import math
from dataclasses import fields
from typing import Any

from ..kernels.counters import PIPELINE_COUNTERS
from ..measure.error import FrameError
from .pipeline import Frame

__all__ = ["ROW_COLUMNS", "ERROR_COLUMNS", "STAGE_COLUMNS", "MESH_COLUMNS", "EXTRA_COLUMNS", "TIMING_COLUMNS",
           "COUNTER_COLUMNS", "frame_row"]

STAGE_COLUMNS = ("select_ms", "mesh_ms", "raster_ms", "frame_ms")
MESH_COLUMNS = ("patches", "vertices", "triangles")
_MAPS = ("error_map", "image_error_map", "see_through_mask")  # FrameError's images: not numbers of a row
ERROR_COLUMNS = tuple(f.name for f in fields(FrameError) if f.name not in _MAPS)
COUNTER_COLUMNS = PIPELINE_COUNTERS
#: what the caller of :func:`frame_row` adds (NaN when it does not)
EXTRA_COLUMNS = ("peer_mesh_ms", "peer_error_m", "pop_p99_px", "pop_max_px", "popped_samples", "cost_ms",
                 "prepare_ms")
ROW_COLUMNS = (*STAGE_COLUMNS, *MESH_COLUMNS, "peer_mesh_ms", "peer_error_m", *ERROR_COLUMNS, "pop_p99_px",
               "pop_max_px", "popped_samples", "cost_ms", *COUNTER_COLUMNS, "prepare_ms")
TIMING_COLUMNS = (*STAGE_COLUMNS, "peer_mesh_ms", "prepare_ms")


def frame_row(frame: Frame, **extra: Any) -> dict[str, Any]:
    """The row of ``frame`` (:data:`ROW_COLUMNS`, in order): stage times and mesh size from its report, the error
    when it measured one, the counters when it counted them (NaN otherwise), and ``extra`` (names of
    :data:`EXTRA_COLUMNS`)."""
    bad = sorted(set(extra) - set(EXTRA_COLUMNS))
    if bad:
        raise ValueError(f"extra: expected names among {list(EXTRA_COLUMNS)}, got {bad}")
    rep, err, mesh = frame.report, frame.error, frame.mesh
    mesh_stage = rep.stage("mesh")
    row: dict[str, Any] = {"select_ms": rep.stage_ms("select"), "mesh_ms": rep.stage_ms("mesh"),
                           "raster_ms": rep.stage_ms("raster"), "frame_ms": rep.frame_ms,
                           "patches": mesh_stage.counters.get("patches", 0) if mesh_stage is not None else 0,
                           "vertices": mesh.n_vertices if mesh is not None else 0,
                           "triangles": mesh.n_triangles if mesh is not None else 0}
    numbers = err.row() if err is not None else {}
    row.update({k: math.nan if numbers.get(k) is None else numbers[k] for k in ERROR_COLUMNS})
    counters = rep.counters or {}
    row.update({k: counters.get(k, math.nan) for k in COUNTER_COLUMNS})
    row.update({k: extra.get(k, math.nan) for k in EXTRA_COLUMNS})
    return {k: row[k] for k in ROW_COLUMNS}

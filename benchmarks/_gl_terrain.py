"""A tessellated terrain frame drawn by Mesa's llvmpipe with real OpenGL 4.5 tessellation shaders, in a child
process: :class:`terrainwarp.experiments.gl.GLTerrain` (its docstring says how the patches are drawn) run on a
frame the benchmark saved, so that ``LP_NUM_THREADS`` can differ from the parent's.

    python benchmarks/_gl_terrain.py FRAME.npz REPS   # prints the best wall and CPU seconds
"""

from __future__ import annotations

import sys

import numpy as np

from terrainwarp.experiments.gl import BATCH_VERTICES, GLTerrain, batches, patch_records

__all__ = ["BATCH_VERTICES", "GLTerrain", "batches", "patch_records", "run_saved"]


def run_saved(path: str, reps: int) -> tuple[float, float]:
    """Best draw wall and CPU seconds of ``reps`` after a warm-up, for a frame saved by the benchmark (child
    processes)."""
    d = np.load(path)
    g = GLTerrain(int(d["width"]), int(d["height"]), d["heights"], float(d["dx"]), float(d["dz"]),
                  str(d["spacing"]))
    try:
        g.set_camera(d["eye"], d["grid_origin"], d["view"], d["proj"])
        ranges = [tuple(r) for r in d["ranges"].tolist()]
        g.draw(d["records"], ranges)
        runs = [g.draw(d["records"], ranges)[2:4] for _ in range(reps)]
        return min(r[0] for r in runs), min(r[1] for r in runs)
    finally:
        g.close()


if __name__ == "__main__":
    print(*run_saved(sys.argv[1], int(sys.argv[2])))

"""The GPU-cost model (terrainwarp.experiments.calibrate, `terrainwarp calibrate --gl`) calibrated on this
machine's OpenGL: the same frames and counters, fitted twice, to the driver's CPU milliseconds (what
`calibrate` fits: llvmpipe's cost is its CPU time) and to the wall milliseconds up to `glFinish` (a real GPU's
frame time: its driver's CPU time is only the submission). Families whose mesher is not installed (Martini,
Delatin: pymartini, pydelatin) are left out. Writes one calibration.md: both fits' weights, R^2 on the
held-out frames, and the wall-time model's weights.json.

    python benchmarks/gpu_calibrate.py --out OUT [--frames-per-family 20]
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time
from pathlib import Path

from _common import md_table, write_result

NEEDS = {"martini": "pymartini", "delatin": "pydelatin"}


def importable(name: str) -> bool:
    try:
        importlib.import_module(name)
    except ImportError:
        return False
    return True


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None, help="folder for calibration.md (default benchmarks/results)")
    ap.add_argument("--frames-per-family", type=int, default=20)
    ap.add_argument("--reps", type=int, default=3)
    args = ap.parse_args(argv)
    try:
        from terrainwarp.experiments import calibrate as cal  # lazy: only where the GPU-cost issue has landed
    except ImportError as e:
        print(f"gpu_calibrate: no calibration in this checkout ({e})")
        return 3
    from terrainwarp import Heightmap

    fams = tuple(f for f in cal.FAMILIES if f not in NEEDS or importable(NEEDS[f]))
    t0 = time.perf_counter()
    hm = Heightmap.example()
    rows = cal.measure(cal.calibration_frames(hm, args.frames_per_family, 0, fams), hm, reps=args.reps,
                       progress=False)
    fits = {t: cal.fit_cost_model(rows, seed=0, target=t, name=f"gpu-{t}") for t in ("gl_wall_ms", "gl_cpu_ms")}
    names = list(fits["gl_wall_ms"][0].weights)
    body = (f"Driver: {rows[0]['driver']}. {len(rows)} frames ({', '.join(fams)}; {args.frames_per_family} a "
            f"family, {args.reps} timed draws each, the least counts), {time.perf_counter() - t0:.0f} s.\n\n"
            + md_table(["fit target", "R^2 held out", "R^2 fitted", "intercept ms"],
                       [[t, m.r2_heldout, f["r2_fit"], m.intercept_ms] for t, (m, f) in fits.items()])
            + "\n\n" + md_table(["weight (ms per unit)", *fits], [[n, *(m.weights[n] for m, _ in fits.values())]
                                                                 for n in names])
            + "\n\nPer family, R^2 held out: " + "; ".join(
                f"{t}: " + ", ".join(f"{fam} {v:.3f}" for fam, v in f["per_family"].items()) for t, (_, f) in
                fits.items())
            + "\n\nThe wall-time model's weights.json:\n\n```json\n" + fits["gl_wall_ms"][0].to_json() + "\n```\n")
    write_result("calibration_gpu", "Cost model calibrated on this machine's OpenGL (gpu_calibrate.py)", body,
                 out_dir=args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The cost model that ships: weights fitted to Mesa llvmpipe's frame times on this machine
(``terrainwarp.experiments.calibrate``, as ``terrainwarp calibrate --gl`` runs it: 50 frames of every family,
seed 0, 3 timed draws per frame, llvmpipe on one thread), its R^2 on the held-out frames, per family.

    .venv/bin/python benchmarks/bench_calibrate.py          # ~2 min on 2 cores: results/calibration.md
    .venv/bin/python benchmarks/bench_calibrate.py --ship   # also writes terrainwarp/measure/llvmpipe.json
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
from pathlib import Path

from _common import write_result

os.environ.setdefault("LP_NUM_THREADS", "0")  # llvmpipe reads it when its first context is made (this script's)

from terrainwarp.experiments.calibrate import calibrate  # noqa: E402

SHIPPED = Path(__file__).resolve().parents[1] / "terrainwarp" / "measure" / "llvmpipe.json"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames-per-family", type=int, default=50)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--ship", action="store_true", help="write the weights into the package (llvmpipe.json)")
    args = ap.parse_args(argv)
    command = "python " + " ".join(["benchmarks/bench_calibrate.py", *(argv if argv is not None else sys.argv[1:])])
    with tempfile.TemporaryDirectory() as d:
        model, paths = calibrate(d, frames_per_family=args.frames_per_family, seed=args.seed, reps=args.reps,
                                 progress=False, command=command)
        md = Path(d, "calibration.md").read_text()
        if args.ship:
            shutil.copyfile(Path(d, "weights.json"), SHIPPED)
    body = md.split("\n", 2)[2]  # calibration.md without its title
    body += ("\n" + ("The weights ship with the package (`terrainwarp/measure/llvmpipe.json`), the default cost of "
                     "`terrainwarp report` and `terrainwarp.measure.cost.cost()`." if args.ship else
                     "Not shipped (no --ship): the package's weights are from an earlier run."))
    write_result("calibration", "Cost model calibration on llvmpipe (bench_calibrate.py)", body)


if __name__ == "__main__":
    main()

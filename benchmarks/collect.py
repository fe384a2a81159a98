"""Rebuild BENCHMARKS.md at the repository root from benchmarks/results/*.md."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ORDER = ["frame", "warmup", "terrain_frame", "raster46", "select", "counters", "calibration", "gpu_check",
         "cuda_parity", "cuda_parity_nofma", "gpu_frame", "calibration_gpu", "threads", "targets", "lod", "tessellate",
         "raster", "normals_curvature",
         "yardstick", "error_vs_time_jacksboro", "error_vs_time_fbm4097", "fit", "fit_640x360", "fit_fbm4097",
         "fit_fbm4097_640x360", "fit_knobs", "fit_knobs_cont1080_dem", "fit_knobs_41", "fit_knobs_41_fresh",
         "fit_knobs_41b_fbm4097", "popping", "schemes", "gpu_whitepaper", "gpu_clipmap", "gpu_fits", "rescale",
         "stability", "fuzz", "sweep", "bintree", "polytree", "outofcore", "outofcore_cache",
         "diff", "make_test"]
# a link in a results file is relative to benchmarks/results/; at the root it needs that prefix
_LINK = re.compile(r"\]\((?!https?:|/|#|benchmarks/)([^)]+)\)")


def main() -> None:
    res = ROOT / "benchmarks" / "results"
    files = sorted(res.glob("*.md"), key=lambda p: (ORDER.index(p.stem) if p.stem in ORDER else 99, p.stem))
    parts = ["# Benchmarks\n",
             "Latest figures, one section per benchmark, each with the command that made it. Timings are wall "
             "clock on the machine named in the section; comparisons are ratios against a baseline run in the "
             "same process. Regenerate everything with `make bench` (or one file with the command shown), then "
             "`python benchmarks/collect.py`.\n"]
    parts += [_LINK.sub(r"](benchmarks/results/\1)", p.read_text().strip()) + "\n" for p in files]
    (ROOT / "BENCHMARKS.md").write_text("\n".join(parts))
    print(f"BENCHMARKS.md: {len(files)} sections")


if __name__ == "__main__":
    main()

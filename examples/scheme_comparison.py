"""Which scheme meets my budget at the lowest cost? CDLOD, geometry clipmaps, Chunked LOD and the quadtree's
screen-space-error policy, a few settings each, rendered from the same cameras and measured against the same
full-resolution frames; then, per budget, each scheme's cheapest setting that meets it. Writes frames.csv,
pareto.png, report.md.

    python examples/scheme_comparison.py --out out/scheme_comparison [--frames 6 --width 640 --height 360]
"""

from __future__ import annotations

import argparse

import terrainwarp as tw
from terrainwarp.experiments.pareto import budget_table, default_settings, summarise, sweep, write_report


def main(argv: list[str] | None = None) -> list[list]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/scheme_comparison")
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=360)
    ap.add_argument("--workers", type=int, default=None, help="worker processes (default: one per core; 0: here)")
    a = ap.parse_args(argv)
    hm = tw.Heightmap.example()
    scene = tw.Scene(hm, camera=tw.Camera.default_for(hm, a.width, a.height))
    cams = scene.camera_path(a.frames)
    settings = [s for s in default_settings(hm, quick=True) if s.policy in ("sse", "cdlod", "clipmaps", "chunked")]
    rows = sweep(scene, cams, settings, progress=False, images=False, workers=a.workers)
    write_report(scene, cams, rows, a.out)
    table = budget_table(summarise(rows), budgets=(0.5, 1.0, 2.0))  # rows: budget, scheme, setting, p99, cost, tris
    print(f"{'budget px':>9}  {'scheme':>9}  {'cheapest setting':>18}  {'p99 px':>7}  {'cost':>9}  {'triangles':>9}")
    for budget, scheme, setting, p99, cost, tris, *_ in table:
        print(f"{budget:>9g}  {scheme:>9}  {setting:>18}  {p99!s:>7}  {cost!s:>9}  {tris!s:>9}")
    return table


if __name__ == "__main__":
    main()

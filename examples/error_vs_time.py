"""Error against cost on the bundled SRTM DEM: sweep the LOD policies and the peers Martini and Delatin over a
flyover, measure every frame against the full-resolution reference and count its pipeline statistics, draw the
Pareto front of error against the modelled GPU cost (the shipped llvmpipe cost model) and triangles.

    python examples/error_vs_time.py --out out/error_vs_time [--frames 8 --width 1280 --height 720 --quick]
        [--policies grid,sse,martini] [--workers N]
"""

from __future__ import annotations

import argparse

import terrainwarp as tw
from terrainwarp.experiments.pareto import default_settings, summarise, sweep, write_report


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="out/error_vs_time")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=720)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--policies", default=None, help="comma-separated subset of the policies (default: all)")
    ap.add_argument("--workers", type=int, default=None, help="worker processes (default: one per core; 0: here)")
    a = ap.parse_args(argv)
    hm = tw.Heightmap.example()
    scene = tw.Scene(hm, camera=tw.Camera.default_for(hm, a.width, a.height), lod=tw.LodConfig(roots=16, tess=16))
    cams = scene.camera_path(a.frames)
    keep = None if a.policies is None else a.policies.split(",")
    settings = [s for s in default_settings(hm, quick=a.quick) if keep is None or s.policy in keep]
    rows = sweep(scene, cams, settings, workers=a.workers)
    write_report(scene, cams, rows, a.out)
    summ = summarise(rows)
    for r in summ:
        print(f"{r['setting']:>18}  p99 {r['p99_px']:8.3f} px  {r['cost']:8.2f} modelled GPU ms  "
              f"{int(r['triangles']):>8} tris  {r['frame_ms']:8.2f} CPU ms")
    return summ


if __name__ == "__main__":
    main()

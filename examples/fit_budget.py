"""Fit a LOD threshold to a screen-space error budget: the cheapest setting of a policy (the quadtree's ``sse``
by default, or a scheme: ``cdlod``, ``clipmaps``, ``chunked``) whose worst frame along the camera path keeps its
p99 error within the budget, found with JAX on a relaxed model and validated on the exact pipeline, beside a
grid search over the same parameter. Writes fit.json and fit.png.

    python examples/fit_budget.py --out out/fit_budget [--budget-px 1 --policy sse --frames 6 --grid-points 8]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import terrainwarp as tw
from terrainwarp.io.files import write_json


def main(argv: list[str] | None = None) -> tw.fit.FitResult:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/fit_budget")
    ap.add_argument("--budget-px", type=float, default=1.0)
    ap.add_argument("--policy", default="sse")
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=360)
    ap.add_argument("--grid-points", type=int, default=8)
    a = ap.parse_args(argv)
    hm = tw.Heightmap.example()
    scene = tw.Scene(hm, camera=tw.Camera.default_for(hm, a.width, a.height), lod=tw.LodConfig(roots=16, tess=16))
    res = tw.fit_lod(scene, a.budget_px, policy=a.policy, cameras=scene.camera_path(a.frames),
                     grid_points=a.grid_points, progress=True)
    print(res.message)
    print(f"fit: {res.evaluations} exact frames; grid search: {res.grid['evaluations'] if res.grid else 0}")
    write_json(Path(a.out) / "fit.json", res.to_dict())
    tw.fit.plot_fit(res, Path(a.out) / "fit.png")
    return res


if __name__ == "__main__":
    main()

"""Your own LOD scheme beside CDLOD, fitted to a budget: distance-banded grids. Tiles of 32 cells keep every sample
within ``near_m`` of the eye, each doubling of the distance halves their sample rate (no skirts: the report counts
the pixels seen through the cracks where bands meet). Registered, "bands" is a policy name:

    python examples/custom_scheme.py --out out/custom_scheme      # report beside CDLOD, then fit 2 px
    terrainwarp report --plugin examples/custom_scheme.py --policies bands,cdlod --quick
    terrainwarp fit --plugin examples/custom_scheme.py --policy bands --budget-px 2
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import numpy as np

import terrainwarp as tw
from terrainwarp.experiments.pareto import Setting, summarise, sweep, write_report

TILE = 32  # cells per tile side: a tile's sample step is a power of two up to TILE


@dataclass(eq=False)
class BandsSource(tw.rendering.SourceBase):
    heightmap: tw.Heightmap
    near_m: float

    def mesh_for(self, camera: tw.Camera) -> tuple[tw.mesh.Mesh, float]:
        t0, hm, eye = time.perf_counter(), self.heightmap, np.asarray(camera.position)
        (rows, cols), (x0, z0) = hm.shape, hm.origin
        r0, c0 = np.mgrid[0:rows - 1:TILE, 0:cols - 1:TILE].reshape(2, -1)  # each tile's first sample
        dist = np.hypot(x0 + (c0 + TILE / 2) * hm.dx - eye[0], z0 + (r0 + TILE / 2) * hm.dz - eye[2])
        band = np.clip(np.floor(np.log2(np.maximum(dist, self.near_m) / self.near_m)), 0, np.log2(TILE))
        step, select_ms = (2 ** band).astype(np.int64), (time.perf_counter() - t0) * 1e3
        pos, tri, level, n = [], [], [], 0
        for s in np.unique(step):  # one vectorised grid per band
            k = TILE // s + 1
            i, j = np.mgrid[0:k, 0:k].reshape(2, -1) * s
            rr, cc = np.minimum(r0[step == s, None] + i, rows - 1), np.minimum(c0[step == s, None] + j, cols - 1)
            pos.append(np.stack([x0 + cc * hm.dx, hm.heights[rr, cc], z0 + rr * hm.dz], -1).reshape(-1, 3) - eye)
            a = (np.arange(k - 1)[:, None] * k + np.arange(k - 1)).ravel()  # each quad's corner (i, j)
            quads = np.concatenate([np.stack([a, a + k, a + 1], 1), np.stack([a + 1, a + k, a + k + 1], 1)])
            tri.append((quads[None] + (n + k * k * np.arange(len(rr)))[:, None, None]).reshape(-1, 3))
            level.append(np.full(rr.size, np.log2(TILE / s), np.int32))
            n += rr.size
        level = np.concatenate(level)
        return tw.mesh.Mesh(positions=np.concatenate(pos).astype(np.float32), eye=camera.position, uv=None,
                            triangles=np.concatenate(tri).astype(np.int32), level=level, patch_id=level), select_ms


def fit_range(hm: tw.Heightmap, cache: dict, params: dict) -> tuple[float, float]:  # one sample to 2 diagonals
    return min(hm.dx, hm.dz), 2.0 * float(np.hypot(hm.dx * hm.shape[1], hm.dz * hm.shape[0]))


tw.schemes.register_scheme("bands", lambda hm, near_m, *, cache, **params: BandsSource(hm, near_m, cache=cache),
                           parameter="near_m", lo=1e-3, hi=1e9, larger_is_finer=True, fit_range=fit_range,
                           replace=True, doc="distance-banded uniform grids; full-detail range, m")


def main(argv: list[str] | None = None) -> tuple[list[dict], object]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    for flag, kind, default in (("--out", str, "out/custom_scheme"), ("--frames", int, 4), ("--width", int, 320),
                                ("--height", int, 180), ("--budget-px", float, 2.0), ("--workers", int, None)):
        ap.add_argument(flag, type=kind, default=default)
    a, hm = ap.parse_args(argv), tw.Heightmap.example()
    scene = tw.Scene(hm, camera=tw.Camera.default_for(hm, a.width, a.height))
    cams = scene.camera_path(a.frames)
    settings = [Setting(p, v) for p in ("bands", "cdlod") for v in tw.schemes.sweep_values(p, hm, quick=True)]
    rows = sweep(scene, cams, settings, progress=False, images=False, workers=a.workers)
    write_report(scene, cams, rows, a.out)
    for r in summarise(rows):  # see-through: background pixels seen through the cracks
        print(f"{r['setting']:>18}  p99 {r['p99_px']:7.3f} px  {r['triangles']:9.0f} tris  {r['see_through_px']} px")
    fit = tw.fit_lod(scene, a.budget_px, policy="bands", cameras=cams)
    print(fit.message)
    return rows, fit


if __name__ == "__main__":
    main()

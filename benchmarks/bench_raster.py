"""Rasterizer benchmark: terrain frames of 1e4..1e7 triangles at 640x480 and 1920x1080.

For each frame, in the same process: our visibility pass (``rasterize``: vertex transform, clipping,
coverage, depth, binning, id/depth/barycentric resolve; Warp CPU backend on ``--threads`` threads,
by default every core this process may use), Mesa's
llvmpipe through raw moderngl (clip coordinates uploaded beforehand; the timed part is the draw and
``glFinish``) and pyvista/VTK off-screen (also llvmpipe here; mesh uploaded by a first render, then
the timed re-renders with ``WaitForCompletion``). Ratios are "their time / our time" (> 1: we are
faster). Agreement: pixels whose triangle id differs from llvmpipe's, coverage pixels that differ, max
|depth difference|; against VTK, which renders from float64 world positions with its own matrices
and a 24-bit depth buffer: coverage pixels that differ, how many of those lie on a silhouette (within
one pixel of a coverage or depth edge), max depth difference off the silhouettes.

    .venv/bin/python benchmarks/bench_raster.py            # full table (~4-6 min on 2 cores)
    .venv/bin/python benchmarks/bench_raster.py --quick    # 1e4..1e5 only, printed (not written)
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

import terrainwarp as tw  # noqa: E402
from terrainwarp.io.files import write_text  # noqa: E402
from terrainwarp.kernels import parallel  # noqa: E402
from terrainwarp.kernels.displacement import grid_mesh  # noqa: E402
from terrainwarp.kernels.raster import clip_coordinates, rasterize  # noqa: E402
from terrainwarp.runtime import configure_from_env  # noqa: E402

configure_from_env()  # as the terrainwarp command runs: quiet Warp, freed frame memory kept mapped

RESOLUTIONS = [(640, 480), (1920, 1080)]
# grid sizes: 2 (s - 1)^2 triangles
SIZES = {"1e4": 72, "1e5": 225, "1e6": 708, "1e7": 2237}


def terrain(rows: int):
    hm = tw.Heightmap.fbm(rows, rows, seed=7, dx=10.0, max_height=800.0)
    return hm


def frame_mesh(hm, cam):
    eye = cam.position
    pos, _, tri = grid_mesh(hm.heights, hm.dx, hm.dz, (hm.origin[0] - eye[0], eye[1], hm.origin[1] - eye[2]))
    return pos, tri


def best_of(fn, reps):
    ts, out = [], None
    for _ in range(reps):
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return min(ts), out


def silhouettes(ids: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Pixels within one pixel of a coverage edge or a depth discontinuity (> 1e-3 window depth)."""
    cov = ids >= 0
    edge = np.zeros_like(cov)
    for ax in (0, 1):
        d = np.diff(cov, axis=ax) | (np.abs(np.diff(depth, axis=ax)) > 1e-3)
        if ax == 0:
            edge[1:] |= d
            edge[:-1] |= d
        else:
            edge[:, 1:] |= d
            edge[:, :-1] |= d
    grow = edge.copy()
    grow[1:] |= edge[:-1]
    grow[:-1] |= edge[1:]
    grow[:, 1:] |= edge[:, :-1]
    grow[:, :-1] |= edge[:, 1:]
    return grow


_GL1_SCRIPT = """
import sys, numpy as np
sys.path.insert(0, {tests!r})
import gl_raster_oracle as gl
clip = np.load({clip!r}); tri = np.load({tri!r})
g = gl.GLRaster({w}, {h}); up = g.upload(clip, tri); g.draw(up)
print(min(g.draw(up)[2] for _ in range({reps})))
"""


def gl_one_thread(clip, tri, w, h, reps) -> float:
    """llvmpipe's draw time with LP_NUM_THREADS=1 (one core, like ours), in a child process: llvmpipe
    reads the variable when its first context is made."""
    with tempfile.TemporaryDirectory() as d:
        np.save(f"{d}/clip.npy", clip)
        np.save(f"{d}/tri.npy", tri)
        code = _GL1_SCRIPT.format(tests=str(ROOT / "tests"), clip=f"{d}/clip.npy", tri=f"{d}/tri.npy", w=w, h=h,
                                  reps=reps)
        out = subprocess.run([sys.executable, "-c", code], env={**os.environ, "LP_NUM_THREADS": "1"},
                             capture_output=True, text=True, check=True)
    return float(out.stdout.strip().splitlines()[-1])


class VTKFrame:
    def __init__(self, width, height):
        import pyvista as pv  # lazy: heavy optional dependency

        self.pv = pv
        self.p = pv.Plotter(off_screen=True, window_size=(width, height), lighting=None)
        try:
            self.p.disable_anti_aliasing()
        except Exception:  # noqa: BLE001 -- older pyvista: nothing to disable
            pass
        self.w, self.h = width, height

    def load(self, hm, cam, pos, tri):
        self.p.clear()
        mesh = tw.mesh.Mesh(positions=pos, eye=cam.position, triangles=tri, uv=np.zeros((len(pos), 2), np.float32),
                       level=np.zeros(len(pos), np.int32), patch_id=np.zeros(len(pos), np.int32)).to_pyvista()
        self.p.add_mesh(mesh, color="white", lighting=False, show_scalar_bar=False)
        c = self.p.camera
        c.position = cam.position
        c.focal_point = cam.target
        c.up = cam.up
        c.view_angle = cam.fov_y_deg
        c.clipping_range = (cam.near, cam.far)
        self.p.render()

    def render(self):
        rw = self.p.ren_win
        self.p.renderer.GetActiveCamera().SetClippingRange(self._near_far)
        rw.Render()
        rw.WaitForCompletion()

    def depth(self):
        import vtk  # lazy: heavy optional dependency (with pyvista)
        from vtk.util.numpy_support import vtk_to_numpy

        arr = vtk.vtkFloatArray()
        self.p.ren_win.GetZbufferData(0, 0, self.w - 1, self.h - 1, arr)

        return vtk_to_numpy(arr).reshape(self.h, self.w)[::-1].copy()

    def close(self):
        self.p.close()


def run(sizes, reps_tiny=7, reps_small=3, reps_big=2, out_md=None):
    import gl_raster_oracle as gl  # lazy: needs moderngl and an OpenGL context

    rows = []
    load = os.getloadavg()[0]  # other processes share the cores: times and ratios vary with it
    glinfo = gl.renderer()
    hms = {k: terrain(SIZES[k]) for k in sizes}
    for (w, h) in RESOLUTIONS:
        vt = VTKFrame(w, h)
        for k in sizes:
            hm = hms[k]
            cam = tw.Camera.default_for(hm, width=w, height=h)
            pos, tri = frame_mesh(hm, cam)
            view, proj = cam.view_matrix(relative=True), cam.proj_matrix()
            # fast frames get more runs: on a busy 2-core machine a best of 3 of a 20 ms frame is mostly noise
            reps = reps_tiny if len(tri) <= 2e5 else reps_small if len(tri) <= 2e6 else reps_big
            _ = rasterize(pos, tri, view, proj, w, h).barycentrics  # warm-up (compiles on the very first call)
            del _
            clip = clip_coordinates(pos, view, proj)  # llvmpipe draws our exact clip coordinates
            vt._near_far = (cam.near, cam.far)
            vt.load(hm, cam, pos, tri)
            t_vtk, _ = best_of(vt.render, reps)
            vdep = vt.depth()
            # a fresh moderngl context, created after VTK's last use of its own (see GLRaster)
            glr = gl.GLRaster(w, h)
            up = glr.upload(clip, tri)
            glr.draw(up)
            t_ours = t_bary = t_gl = 1e9
            for _ in range(reps):  # ours and llvmpipe in turn: both see the same load from other processes
                t0 = time.perf_counter()
                f = rasterize(pos, tri, view, proj, w, h)
                t1 = time.perf_counter()
                _ = f.barycentrics  # the resolve half: computed on first access
                t2 = time.perf_counter()
                gid, gdep, dt = glr.draw(up)
                t_ours, t_bary, t_gl = min(t_ours, t1 - t0), min(t_bary, t2 - t1), min(t_gl, dt)
            glr.release(up)
            glr.close()
            t_gl1 = gl_one_thread(clip, tri, w, h, reps)
            # agreement with llvmpipe (moderngl): same clip coordinates
            ours_cov = f.triangle_id >= 0
            id_diff = int((f.triangle_id != gid).sum())
            cov_diff = int((ours_cov != (gid >= 0)).sum())
            same = (f.triangle_id == gid) & ours_cov
            dmax_gl = float(np.abs(f.depth[same] - gdep[same]).max()) if same.any() else 0.0
            # agreement with VTK
            vcov = vdep < 1.0
            sil = silhouettes(f.triangle_id, f.depth)
            vdiff = ours_cov != vcov
            both = ours_cov & vcov & ~sil
            dmax_vtk = float(np.abs(f.depth[both] - vdep[both]).max()) if both.any() else 0.0
            s = f.stats
            rows.append({
                "tris": k, "n": len(tri), "res": f"{w}x{h}", "ours_s": t_ours, "bary_s": t_bary, "gl_s": t_gl,
                "gl1_s": t_gl1, "vtk_s": t_vtk,
                "after_cull": s["triangles_rasterized"], "binned": s["triangles_binned"],
                "tested": s["fragments_tested"], "written": s["pixels_written"], "covered": s["pixels_covered"],
                "id_diff": id_diff, "cov_diff": cov_diff, "dmax_gl": dmax_gl, "vtk_cov_diff": int(vdiff.sum()),
                "vtk_on_sil": int((vdiff & sil).sum()), "dmax_vtk": dmax_vtk})
            r = rows[-1]
            print(f"{k} {r['res']}: ours {t_ours:.3f}s gl {t_gl:.3f}s gl1 {t_gl1:.3f}s vtk {t_vtk:.3f}s  "
                  f"id diff {id_diff} "
                  f"dmax {dmax_gl:.2g}  vtk cov diff {r['vtk_cov_diff']} ({r['vtk_on_sil']} on silhouettes)",
                  flush=True)
        vt.close()
    lines = [
        "# Rasterizer: terrainwarp vs llvmpipe (moderngl) vs pyvista/VTK (llvmpipe)",
        "",
        f"Command: `{' '.join(['.venv/bin/python', 'benchmarks/bench_raster.py', *sys.argv[1:]])}`",
        "",
        f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; OpenGL: {glinfo}; "
        f"LP_NUM_THREADS={os.environ.get('LP_NUM_THREADS', 'unset (llvmpipe uses all cores)')}; load average "
        f"{load:.1f} at the start, {os.getloadavg()[0]:.1f} at the end (other processes on these cores). "
        f"terrainwarp runs on {parallel.threads()} thread(s) (Warp CPU backend, launches split by "
        "kernels/parallel.py; `--threads`).",
        "",
        "Terrain: `Heightmap.fbm(s, s, seed=7, dx=10, max_height=800)` grid, 2 (s-1)^2 triangles, "
        "`Camera.default_for` (whole terrain in view). Times are the best of 7 runs (up to 1e5 triangles), 3 (1e6) "
        "or 2 (1e7); ours, +bary and gl run in turn, frame by frame. ours = full "
        "`rasterize` (vertex transform, clipping, binning, coverage, depth test, id and depth images); "
        "+bary = the same plus the perspective-correct barycentric image (computed on first access of "
        "`Fragments.barycentrics`); gl = draw + glFinish of the "
        "pre-uploaded clip coordinates (gl 1 thread: the same with LP_NUM_THREADS=1, in a child process); "
        "vtk = `Render` + `WaitForCompletion`, unlit. Ratio = their / ours.",
        "",
        "| triangles | res | ours s | +bary s | gl s | gl/ours | gl 1 thread s | gl1/ours | vtk s | vtk/ours "
        "| after cull | binned | frags tested "
        "| px written | px covered | id diff vs gl | cov diff vs gl | max dz vs gl | cov diff vs vtk "
        "(on silhouette) | max dz vs vtk (off sil.) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['n']:,} | {r['res']} | {r['ours_s']:.3f} | {r['ours_s'] + r['bary_s']:.3f} | {r['gl_s']:.3f} "
            f"| {r['gl_s'] / r['ours_s']:.2f} | {r['gl1_s']:.3f} | {r['gl1_s'] / r['ours_s']:.2f} "
            f"| {r['vtk_s']:.3f} | {r['vtk_s'] / r['ours_s']:.2f} | {r['after_cull']:,} | {r['binned']:,} "
            f"| {r['tested']:,} | {r['written']:,} | {r['covered']:,} | {r['id_diff']} | {r['cov_diff']} "
            f"| {r['dmax_gl']:.2g} | {r['vtk_cov_diff']} ({r['vtk_on_sil']}) | {r['dmax_vtk']:.2g} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if out_md:
        write_text(out_md, text)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="1e4 and 1e5 triangles only")
    ap.add_argument("--no-1e7", action="store_true", help="skip the 1e7-triangle frames")
    ap.add_argument("--out", default=None, help="the results file (default: benchmarks/results/raster.md for a "
                    "full run; a --quick run is printed only, so it never replaces the full table)")
    ap.add_argument("--threads", type=int, default=None, help="our CPU threads (default: every core we may use)")
    a = ap.parse_args(argv)
    tw.kernels.parallel.set_threads(a.threads)
    sizes = ["1e4", "1e5"] if a.quick else ["1e4", "1e5", "1e6"] + ([] if a.no_1e7 else ["1e7"])
    out = a.out if a.out else (None if a.quick else str(ROOT / "benchmarks" / "results" / "raster.md"))
    run(sizes, out_md=out)


if __name__ == "__main__":
    main()

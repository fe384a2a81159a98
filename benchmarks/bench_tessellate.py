"""Tessellator throughput: the deaconu2021 configuration (64 root nodes, tessellation level 32; their
Table 1 counts 67,108,864 processed vertices = 64 roots x 32 x 32 leaves x 32 x 32 segments) and
smaller frames of the same shape, against a vectorised numpy implementation of the same
integer-spacing grid in the same run.

A frame: 8 x 8 roots over a 1025 x 1025 heightmap, each root split into k x k leaf patches, every
patch at level 32 (equal spacing; outer and inner levels all 32). Stages timed (best of --repeat):

* domain: count -> scan -> emit (the fixed-function tessellator; D3D ring order and stitching);
* frame: the whole ``tessellate_patches`` (domain + bilinear displacement, camera-relative float32
  positions, heightmap uv, patch id, level), including the copies to numpy;
* numpy domain / numpy frame: the same (L+1)^2 grid per patch and 2 L^2 triangles by broadcasting,
  then bilinear heights and positions, vectorised over all patches.

Memory: bytes of the frame's output arrays per million vertices (positions 12, uv 8, domain 8, patch
id 4, level 4, triangles 12 per triangle, about 2 triangles per vertex) and the process's peak RSS.

    python benchmarks/bench_tessellate.py [--k 1 2 4 8 16] [--repeat 2] [--full]
"""

from __future__ import annotations

import argparse
import resource
import time

import numpy as np
from _common import best_of, md_table, write_result

from terrainwarp.kernels.parallel import set_threads, threads
from terrainwarp.kernels.pool import release_buffers
from terrainwarp.kernels.tessellator import (
    SPACING_CODES,
    tessellate_device,
    tessellate_patches,
    tessellate_patches_device,
)

LEVEL = 32
ROOTS = 8  # per side: 64 roots
N = 1025
DX = 10.0


def heights() -> np.ndarray:
    y, x = np.mgrid[0:N, 0:N] / (N - 1)
    return (300 * np.sin(7 * x) * np.cos(5 * y) + 40 * np.sin(41 * x + 3 * y)).astype(np.float32)


def frame(k: int) -> dict:
    side = (N - 1) * DX / (ROOTS * k)
    n = ROOTS * k
    c, r = np.meshgrid(np.arange(n), np.arange(n))
    org = np.stack([c.ravel() * side, r.ravel() * side], 1)
    p = org.shape[0]
    return {"origin_xz": org, "size": np.full(p, side), "outer": np.full((p, 4), LEVEL, np.float32),
            "inner": np.full((p, 2), LEVEL, np.float32), "level": np.full(p, 5, np.int32)}


def numpy_domain(p: int, lv: int):
    t = np.arange(lv + 1, dtype=np.float32) / lv
    uv = np.stack(np.meshgrid(t, t), -1).reshape(-1, 2)  # (L+1)^2 points, u fastest
    i, j = np.meshgrid(np.arange(lv), np.arange(lv), indexing="ij")
    a = (i * (lv + 1) + j).ravel()
    quad = np.stack([a, a + 1, a + lv + 2, a, a + lv + 2, a + lv + 1], 1).reshape(-1, 3)
    nv = (lv + 1) ** 2
    uv_all = np.broadcast_to(uv, (p, nv, 2)).reshape(-1, 2)
    tri_all = (quad[None] + (np.arange(p) * nv)[:, None, None]).reshape(-1, 3).astype(np.int32)
    pid = np.repeat(np.arange(p, dtype=np.int32), nv)
    return uv_all, tri_all, pid


def numpy_frame(pt: dict, h: np.ndarray, eye):
    p = pt["outer"].shape[0]
    uv, tri, pid = numpy_domain(p, LEVEL)
    wx = pt["origin_xz"][pid, 0] + uv[:, 0] * pt["size"][pid]
    wz = pt["origin_xz"][pid, 1] + uv[:, 1] * pt["size"][pid]
    gx = np.clip(wx / DX, 0, N - 1).astype(np.float32)
    gz = np.clip(wz / DX, 0, N - 1).astype(np.float32)
    j0 = np.minimum(gx.astype(np.int64), N - 2)
    i0 = np.minimum(gz.astype(np.int64), N - 2)
    fu, fv = gx - j0, gz - i0
    h00, h01, h10, h11 = h[i0, j0], h[i0, j0 + 1], h[i0 + 1, j0], h[i0 + 1, j0 + 1]
    y = (h00 + (h01 - h00) * fu) + ((h10 + (h11 - h10) * fu) - (h00 + (h01 - h00) * fu)) * fv
    pos = np.stack([(wx - eye[0]).astype(np.float32), (y - eye[1]).astype(np.float32),
                    (wz - eye[2]).astype(np.float32)], 1)
    return pos, tri, pid


def device_frame(pt: dict, h: np.ndarray, eye, depth_only: bool = False):
    """The device stages: every per-point output, or (depth_only) positions and triangles alone."""
    return tessellate_patches_device(pt, h, DX, DX, eye, need=() if depth_only else None)


def output_bytes(res) -> int:
    return sum(a.capacity for a in (res.positions, res.triangles, res.uv, res.domain, res.patch_id, res.level)
               if a is not None)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--k", type=int, nargs="+", default=[1, 2, 4, 8, 16], help="leaves per root side")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--full", action="store_true", help="also run the device stages of k = 32 (~4.3 GiB)")
    ap.add_argument("--threads", type=int, default=None, help="CPU threads (default: every core we may use)")
    args = ap.parse_args()
    set_threads(args.threads)
    h = heights()
    eye = (5000.0, 800.0, 5000.0)
    tessellate_patches(frame(1), h, DX, DX, eye)  # compile
    code = SPACING_CODES["equal"]
    rows = []
    for k in args.k:
        pt = frame(k)
        p = pt["outer"].shape[0]
        t_dom, res = best_of(lambda pt=pt: tessellate_device(pt["outer"], pt["inner"], code, "cpu"), args.repeat)
        nv, nt = res[0], res[1]
        del res
        t_dev, res = best_of(lambda pt=pt: device_frame(pt, h, eye), args.repeat)
        nbytes = output_bytes(res)
        del res
        t_depth, res = best_of(lambda pt=pt: device_frame(pt, h, eye, True), args.repeat)
        depth_bytes = output_bytes(res)
        del res
        t_frame, tess = best_of(lambda pt=pt: tessellate_patches(pt, h, DX, DX, eye), args.repeat)
        assert tess.positions.shape[0] == nv == p * (LEVEL + 1) ** 2 and tess.triangles.shape[0] == nt
        del tess
        t_np_dom, _ = best_of(lambda p=p: numpy_domain(p, LEVEL), args.repeat)
        t_np_frame, _ = best_of(lambda pt=pt: numpy_frame(pt, h, eye), args.repeat)
        rss_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
        rows.append([p, nv, nt, t_dom * 1e3, nv / t_dom / 1e6, t_dev * 1e3, nv / t_dev / 1e6, t_frame * 1e3,
                     t_np_dom / t_dom, t_np_frame / t_dev, t_np_frame / t_frame, nbytes / nv * 1e6 / 2**20,
                     t_depth * 1e3, nv / t_depth / 1e6 / threads(), depth_bytes / nv * 1e6 / 2**20, rss_gb])
        print(f"k={k}: {p} patches, {nv:,} vertices, domain {t_dom:.3f} s, device frame {t_dev:.3f} s, "
              f"with numpy copies {t_frame:.3f} s", flush=True)
    header = ["patches", "vertices", "triangles", "domain ms", "domain Mpts/s", "displaced ms", "displaced Mvtx/s",
              "+ to numpy ms", "numpy/warp domain", "numpy/warp displaced", "numpy/warp + to numpy",
              "MiB per M vertices", "depth-only ms", "depth-only Mvtx/s per thread", "depth-only MiB per M vertices",
              "peak RSS GiB"]
    body = md_table(header, rows)
    full_p = 64 * 32 * 32
    full_nv = full_p * (LEVEL + 1) ** 2
    body += (
        f"\n\nAll patches at level {LEVEL} (equal spacing): (L+1)^2 = {(LEVEL + 1) ** 2} domain points and "
        f"2 L^2 = {2 * LEVEL ** 2} triangles each. 'domain' is count -> scan -> emit; 'displaced' adds the "
        "domain shader (bilinear height, camera-relative float32 positions, uv, level; fused into the emit "
        "launch) and is the pipeline stage of a shaded frame; 'depth-only' makes positions and triangles alone "
        "(what a depth or error frame asks for: `need=()`); "
        "'+ to numpy' is the whole public call including the host-side arrays. 'numpy/warp' > 1 "
        "means the Warp kernels beat the vectorised numpy grid of the same size in the same run (numpy "
        "builds the plain grid; the kernels run the real tessellator: ring order, transition stitching, "
        f"fixed-point placement). Warp CPU launches split across {threads()} thread(s) (`--threads`; per core: "
        "divide the Mvtx/s by that); numpy runs on one; best of --repeat, so a later frame: the outputs reuse "
        "the buffers the frame before dropped (the frame-buffer pool); timings on this shared 2-core "
        "machine vary by about 2x between runs. Memory: output bytes "
        "(positions 12, uv 8, domain 8, patch id 4, level 4, triangles 2 x 12 per vertex; depth-only: positions "
        "and triangles, 12 + 12 x 2048/1089 bytes per vertex = 32.97 MiB per million vertices, the floor for float32 "
        "positions and int32 index triples).\n")
    if args.full:
        release_buffers()  # the k rows' kept buffers
        pt = frame(32)
        t0 = time.perf_counter()
        res = tessellate_device(pt["outer"], pt["inner"], code, "cpu")
        t_dom = time.perf_counter() - t0
        del res
        times = {}
        for depth_only in (False, True):
            release_buffers()  # a first frame: every output written to fresh pages
            for when in ("first", "later"):  # a later frame: the outputs reuse the dropped frame's buffers
                t0 = time.perf_counter()
                res = device_frame(pt, h, eye, depth_only)
                times[depth_only, when] = time.perf_counter() - t0
                assert res[0] == full_nv
                del res
        release_buffers()
        rss_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
        t_dev, t_depth = times[False, "later"], times[True, "later"]
        body += (f"\ndeaconu2021's 64-root, level-32 frame, measured (device stages only; a first frame writes "
                 "fresh pages, a later one the buffers the frame before it dropped, kept by the frame-buffer pool "
                 f"`kernels.pool.pooled_rows`): {full_p:,} leaf patches, {full_nv:,} domain points, "
                 f"{full_p * 2 * LEVEL ** 2:,} triangles (their 67,108,864 counts 32 x 32 per patch): domain "
                 f"{t_dom:.2f} s ({full_nv / t_dom / 1e6:.1f} Mpts/s); displaced {times[False, 'first']:.2f} s first, "
                 f"{t_dev:.2f} s later ({full_nv / t_dev / 1e6:.1f} Mvtx/s); depth-only "
                 f"{times[True, 'first']:.2f} s first, {t_depth:.2f} s later ({full_nv / t_depth / 1e6:.1f} "
                 f"Mvtx/s); peak RSS {rss_gb:.1f} GiB.\n")
    else:
        p, nv = rows[-1][0], rows[-1][1]
        scale = full_p / p
        body += (f"\ndeaconu2021's 64-root, level-32 frame ({full_p:,} leaf patches, {full_nv:,} domain points, "
                 f"{full_p * 2 * LEVEL ** 2:,} triangles; their 67,108,864 counts 32 x 32 per patch) not run "
                 f"(pass --full; about {rows[-1][11] * full_nv / 1e6 / 1024:.1f} GiB of outputs, "
                 f"{rows[-1][14] * full_nv / 1e6 / 1024:.1f} depth-only). Extrapolated "
                 f"linearly from {p:,} patches: domain about {rows[-1][3] * scale / 1e3:.1f} s, displaced about "
                 f"{rows[-1][5] * scale / 1e3:.1f} s.\n")
    write_result("tessellate", "Tessellator throughput (bench_tessellate.py)", body)


if __name__ == "__main__":
    main()

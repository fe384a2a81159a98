"""Walk along the ground of a procedural terrain far larger than memory (65,537^2 samples: 17 GB as
float32), reading only the tiles each frame needs; writes walk_<k>.png and prints what each frame read.

    python examples/streamed_terrain.py --out out/streamed [--size 65537 --frames 4 --width 960 --height 540]
"""

from __future__ import annotations

import argparse
import resource
import time
from pathlib import Path

import terrainwarp as tw
from terrainwarp.io.files import write_image


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="out/streamed")
    ap.add_argument("--size", type=int, default=65537)
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--width", type=int, default=960)
    ap.add_argument("--height", type=int, default=540)
    a = ap.parse_args(argv)
    hm = tw.heightmap.StreamedHeightmap.fbm(a.size, seed=1, max_height=2000.0, dx=10.0)   # never held in memory
    (x0, z0), (x1, z1) = hm.bounds_xz
    rows = []
    for k in range(a.frames):
        x, z = 0.5 * (x0 + x1) + 150.0 * k, 0.5 * (z0 + z1) + 45.0 * k
        ground = float(hm.sample([x], [z])[0])                                  # through the tiles
        cam = tw.Camera(position=(x, ground + 40.0, z), target=(x + 958.0, ground + 20.0, z + 287.0),
                        fov_y_deg=60.0, width=a.width, height=a.height, near=1.0, far=x1 - x0)
        t0 = time.perf_counter()
        frame = tw.render(tw.Scene(hm, camera=cam, mesh="lod", outputs=("image",)))
        out = Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        write_image(out / f"walk_{k}.png", frame.image)
        rows.append({"frame": k, "s": round(time.perf_counter() - t0, 2), **frame.report.info["tiles"],
                     "triangles": frame.mesh.n_triangles,
                     "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024})
        print(rows[-1])
    return rows


if __name__ == "__main__":
    main()

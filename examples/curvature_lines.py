"""Line- and hatch-shaded pictures of the bundled SRTM DEM (curtis2004 "Utilizing curvature"), one per
row of the paper's parameter tables (figures 3 and 4), plus the normal map (deaconu2021 figure 8) and
the maximum-curvature intensity image (curtis2004 figure 2).

    python examples/curvature_lines.py --out out/curvature_lines [--only fig3a,fig4c] [--crop 64]

Curvature scales in the tables are per sample spacing (the paper's terrain had unit spacing): the
Equation-1 methods get ``scale = table scale * mean spacing`` so their values are curvature times
spacing (dimensionless); edge-angle is dimensionless already. Writes ``<name>.png`` per picture and
``index.json`` listing every picture with its parameters and stroke counts.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import terrainwarp as tw
from terrainwarp.io.files import write_image, write_json
from terrainwarp.surface.differential import max_curvature, normal_map_image
from terrainwarp.surface.strokes import hatch_strokes, line_strokes

STYLE = {"3 norm": "three_normal", "2 norm": "two_normal", "Edge": "edge_angle", "3 Vert": "three_vertex"}
# curtis2004 figure 3: curv style, curv dist, curv scale, has contours, min len, line width
FIG3 = {
    "a": ("3 norm", 2, 6, False, 6, 1), "b": ("3 norm", 2, 6, True, 6, 1), "c": ("3 norm", 2, 11, True, 2, 1),
    "d": ("2 norm", 1, 2, False, 5, 1), "e": ("2 norm", 1, 11, False, 2, 1), "f": ("2 norm", 1, 6, False, 2, 1),
    "g": ("3 norm", 2, 3, True, 5, 1), "h": ("2 norm", 1, 3, False, 5, 1), "i": ("Edge", 1, 2, True, 5, 1),
    "j": ("3 Vert", 1, 2, False, 5, 1), "k": ("2 norm", 1, 1, False, 5, 1), "l": ("Edge", 1, 1, True, 5, 1),
    "m": ("3 Vert", 1, 1, False, 5, 1), "n": ("3 norm", 1, 1.5, False, 2, 6),
}
# curtis2004 figure 4: curv style, curv dist, curv scale, has contours, hatch len, line width, hatch dir
FIG4 = {
    "a": ("3 norm", 2, 4, False, 0.75, 1, "with"), "b": ("3 norm", 1, 4, False, 0.75, 1, "with"),
    "c": ("3 norm", 1, 4, False, 0.75, 1, "perp"), "d": ("2 norm", 1, 4, False, 0.75, 4, "perp"),
    "e": ("2 norm", 1, 8, False, 0.25, 1, "perp"), "f": ("3 norm", 2, 8, True, 0.75, 1, "perp"),
    "g": ("3 norm", 1, 3, False, 2.15, 2, "perp"), "h": ("3 Vert", 1, 2, False, 0.45, 3, "with"),
}


def _scale(style: str, table_scale: float, spacing: float) -> float:
    return table_scale if style == "Edge" else table_scale * spacing


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/curvature_lines")
    ap.add_argument("--only", default="", help="comma-separated picture names (fig3a, fig4c, ...); default all")
    ap.add_argument("--crop", type=int, default=0, help="use only the top-left N x N samples (tests)")
    ap.add_argument("--size-px", type=int, default=800)
    ap.add_argument("--threshold", type=float, default=0.5, help="line shading curvature threshold")
    ap.add_argument("--hatch-threshold", type=float, default=0.05)
    a = ap.parse_args(argv)
    out = Path(a.out)
    hm = tw.Heightmap.example()
    if a.crop:
        hm = tw.Heightmap.from_array(hm.heights[: a.crop, : a.crop], hm.dx, hm.dz, name=f"{hm.name}_crop")
    sp = 0.5 * (hm.dx + hm.dz)
    only = {s.strip() for s in a.only.split(",") if s.strip()}
    index: dict[str, dict] = {}

    def wanted(name: str) -> bool:
        return not only or name in only

    if wanted("normal_map"):
        n = tw.compute_normals(hm, "sobel", border="clamp")
        write_image(out / "normal_map.png", normal_map_image(n))
        index["normal_map"] = {"method": "sobel", "border": "clamp"}
    if wanted("max_curvature"):
        k = tw.compute_curvature(hm, "three_normal", scale=4 * sp, distance=2)
        kmax, _ = max_curvature(k)
        img = (255 - np.clip(kmax, 0, 1) * 255).round().astype(np.uint8)  # dark = high curvature
        write_image(out / "max_curvature.png", img)
        index["max_curvature"] = {"method": "three_normal", "table_scale": 4, "distance": 2}
    for key, (style, dist, scl, cont, min_len, width) in FIG3.items():
        name = f"fig3{key}"
        if not wanted(name):
            continue
        t0 = time.perf_counter()
        s = line_strokes(hm, method=STYLE[style], scale=_scale(style, scl, sp), distance=dist,
                         threshold=a.threshold, min_length=min_len)
        title = f"fig 3{key}: {style}, dist {dist}, scale {scl}, min len {min_len}, width {width}"
        s.picture(out / f"{name}.png", heightmap=hm, contours=cont, line_width=width, size_px=a.size_px,
                  title=title)
        index[name] = {"kind": "line", "style": style, "distance": dist, "table_scale": scl, "contours": cont,
                       "min_length": min_len, "line_width": width, "threshold": a.threshold,
                       "segments": len(s), "paths": s.n_paths, "time_s": round(time.perf_counter() - t0, 3)}
    for key, (style, dist, scl, cont, hlen, width, hdir) in FIG4.items():
        name = f"fig4{key}"
        if not wanted(name):
            continue
        t0 = time.perf_counter()
        s = hatch_strokes(hm, method=STYLE[style], scale=_scale(style, scl, sp), distance=dist, length=hlen,
                          direction=hdir, threshold=a.hatch_threshold)
        title = f"fig 4{key}: {style}, dist {dist}, scale {scl}, len {hlen}, width {width}, {hdir}"
        s.picture(out / f"{name}.png", heightmap=hm, contours=cont, line_width=0.5 * width, size_px=a.size_px,
                  title=title)
        index[name] = {"kind": "hatch", "style": style, "distance": dist, "table_scale": scl, "contours": cont,
                       "length": hlen, "line_width": width, "direction": hdir, "threshold": a.hatch_threshold,
                       "segments": len(s), "time_s": round(time.perf_counter() - t0, 3)}
    write_json(out / "index.json", {"heightmap": hm.name, "shape": list(hm.shape), "dx": hm.dx, "dz": hm.dz,
                                    "pictures": index})
    for name, d in index.items():
        print(f"{name:14s} {d}")
    return index


if __name__ == "__main__":
    main()

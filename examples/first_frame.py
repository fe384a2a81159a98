"""Render the bundled SRTM DEM from its default camera and write frame.png, depth.exr, report.json.

    python examples/first_frame.py --out out/first_frame [--width 640 --height 480]
"""

from __future__ import annotations

import argparse

import terrainwarp as tw


def main(argv: list[str] | None = None) -> tw.Frame:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="out/first_frame")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    a = ap.parse_args(argv)
    hm = tw.Heightmap.example()                                   # 344 x 403 SRTM, metres
    cam = tw.Camera.default_for(hm, a.width, a.height)            # three-quarter view from the south
    frame = tw.render(tw.Scene(hm, camera=cam, outputs=("image", "depth", "report")))
    frame.save(a.out)
    print(frame.report.table())
    return frame


if __name__ == "__main__":
    main()

"""A real DEM as a GeoTIFF: its CRS gives the metre spacing and the orientation, its no-data cells become holes,
and a part of it is read at a lower resolution without loading the whole. Without ``--dem``, the bundled SRTM
tile (3 arc-seconds, Tennessee) is written first as a GeoTIFF in geographic coordinates (EPSG:4326, int16, a
no-data patch), as an SRTM download would come. Writes frame.png and part.png.

    python examples/real_geotiff.py --out out/real_geotiff [--dem my_dem.tif --width 640 --height 360]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import rasterio
from affine import Affine
from matplotlib import cbook

import terrainwarp as tw


def srtm_geotiff(path: Path) -> Path:
    """The bundled SRTM tile as an EPSG:4326 GeoTIFF, with a no-data patch (-32768, as SRTM voids are)."""
    d = cbook.get_sample_data("jacksboro_fault_dem.npz")
    z = np.asarray(d["elevation"]).astype(np.int16)
    z[100:120, 200:230] = -32768
    # the file's ymin is the northern edge of row 0 (rows run south): the north-west corner and the spacing
    transform = Affine(float(d["dx"]), 0.0, float(d["xmin"]), 0.0, -float(d["dy"]), float(d["ymin"]))
    with rasterio.open(path, "w", driver="GTiff", width=z.shape[1], height=z.shape[0], count=1, dtype="int16",
                       crs="EPSG:4326", transform=transform, nodata=-32768) as f:
        f.write(z, 1)
    return path


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/real_geotiff")
    ap.add_argument("--dem", default=None, help="a GeoTIFF (or any GDAL raster) of your own")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=360)
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    dem = Path(a.dem) if a.dem else srtm_geotiff(out / "srtm.tif")
    hm = tw.Heightmap.load(dem)  # metres, north-up, no-data as NaN
    print(hm.meta["summary"])
    frame = tw.render(tw.Scene(hm, camera=tw.Camera.default_for(hm, a.width, a.height), outputs=("image",)))
    frame.save(out)
    with rasterio.open(dem) as f:
        left, bottom, right, top = f.bounds  # in the file's own coordinates (degrees here)
    part = tw.Heightmap.load(dem, bounds=(left, bottom, 0.5 * (left + right), 0.5 * (bottom + top)), decimate=2)
    f2 = tw.render(tw.Scene(part, camera=tw.Camera.default_for(part, a.width, a.height), outputs=("image",)))
    tw.io.files.write_image(out / "part.png", f2.image)
    return {"shape": hm.shape, "dx": hm.dx, "dz": hm.dz, "no_data": int(np.isnan(hm.heights).sum()),
            "part_shape": part.shape, "part_dx": part.dx}


if __name__ == "__main__":
    main()

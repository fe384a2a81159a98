"""terrainwarp.io.files: every file the writers make is byte-identical across runs (issue 20, item 2)."""

import hashlib
import time

import numpy as np
import pytest
from rasterio.crs import CRS

from terrainwarp.io.files import save_figure, write_image
from terrainwarp.io.geotiff import write_geotiff


class _Grid:  # what write_geotiff needs of a heightmap (io.geotiff.HeightGrid)
    def __init__(self, heights, meta):
        self.heights, self.dx, self.dz, self.name, self.meta = heights, 30.0, 30.0, "g", meta


def _write_all(d, a):
    d.mkdir()
    u8 = (a * 255).astype(np.uint8)
    for name, arr in (("f.exr", a), ("f.tif", a), ("rgb.exr", np.dstack([a, a, a])), ("u8.png", u8),
                      ("u16.png", (a * 60000).astype(np.uint16)), ("u8.tif", u8), ("u8.jpg", u8)):
        write_image(d / name, arr)
    meta = {"transform": [30.0, 0.0, 500000.0, 0.0, -30.0, 4000000.0], "crs": CRS.from_epsg(32617).to_wkt(),
            "nodata": -9999.0, "source_dtype": "int16"}
    write_geotiff(_Grid(np.round(a * 1000), meta), d / "geo.tif")
    big = np.round(np.random.default_rng(1).random((520, 530)) * 1000).astype(np.float32)  # tiled GeoTIFF
    write_geotiff(_Grid(big, {**meta, "source_dtype": "float32"}), d / "geo_tiled.tif")
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(d.iterdir())}


def test_written_files_are_byte_identical_across_runs(tmp_path):
    """OpenImageIO stamped EXR and TIFF files with a DateTime header (the seconds of the write), so two
    identical runs a second apart gave different bytes."""
    a = np.random.default_rng(0).random((16, 24)).astype(np.float32)
    first = _write_all(tmp_path / "a", a)
    time.sleep(1.1)  # the header's resolution is a second
    second = _write_all(tmp_path / "b", a)
    assert len(first) == 9
    assert first == second


@pytest.mark.parametrize("fmt", ["png", "pdf", "svg"])
def test_saved_figures_are_byte_identical_across_runs(tmp_path, fmt):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def one(path):
        fig, ax = plt.subplots(figsize=(2, 2))
        ax.plot([0, 1, 2], [1, 0, 2], label="x")
        ax.legend()
        save_figure(fig, path)
        return hashlib.sha256(path.read_bytes()).hexdigest()

    a = one(tmp_path / f"a.{fmt}")
    time.sleep(1.1)
    assert one(tmp_path / f"b.{fmt}") == a

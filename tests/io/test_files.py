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


# -- output sets: renamed into place only when every file is written -------------------------------------------


def _state(d):
    return {p.name: p.read_bytes() for p in sorted(d.iterdir())}


def test_an_output_set_appears_whole_or_not_at_all(tmp_path):
    from terrainwarp.io.files import output_set, write_json, write_text

    d = tmp_path / "out"
    with output_set(d):
        write_text(d / "a.txt", "one\n")
        write_json(d / "b.json", {"v": 1})
        assert not (d / "a.txt").exists()  # pending under a temporary name until the set is written
    before = _state(d)
    assert before == {"a.txt": b"one\n", "b.json": b'{\n  "v": 1\n}\n'}
    with pytest.raises(RuntimeError, match="boom"), output_set(d):  # the second file's write fails
        write_text(d / "a.txt", "two\n")
        raise RuntimeError("boom")
    assert _state(d) == before  # the previous set is whole, no temporary file is left
    with pytest.raises(KeyboardInterrupt), output_set(d):
        write_text(d / "c.txt", "new\n")
        raise KeyboardInterrupt
    assert _state(d) == before  # nothing new either


def test_nested_sets_are_written_by_the_outermost_and_deferred_removals_wait(tmp_path):
    from terrainwarp.io.files import output_set, remove_when_written, write_text

    d = tmp_path / "o"
    d.mkdir()
    (d / "journal.partial").write_text("rows\n")
    with output_set(d):
        with output_set(d / "sub"):
            write_text(d / "sub" / "x.txt", "x")
        assert not (d / "sub" / "x.txt").exists()  # the outer set holds it
        write_text(d / "t.csv", "table")
        remove_when_written(d / "journal.partial")
        assert (d / "journal.partial").exists()  # removed only once the table is in place
    assert (d / "sub" / "x.txt").read_text() == "x" and (d / "t.csv").read_text() == "table"
    assert not (d / "journal.partial").exists()
    (d / "journal.partial").write_text("rows\n")
    with pytest.raises(OSError), output_set(d):
        remove_when_written(d / "journal.partial")
        raise OSError("disk")
    assert (d / "journal.partial").exists()  # a failed set keeps the journal: a rerun resumes


def test_a_full_disk_names_the_file_and_the_size(tmp_path, monkeypatch):
    import errno
    import pathlib

    from terrainwarp.io.files import write_image, write_text

    def full(self, data):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(pathlib.Path, "write_bytes", full)
    with pytest.raises(OSError, match=r"no space left on device writing report.json \(12 B\)") as e:
        write_text(tmp_path / "report.json", "x" * 12)
    assert e.value.errno == errno.ENOSPC and e.value.filename == str(tmp_path / "report.json")
    monkeypatch.undo()
    monkeypatch.setattr("terrainwarp.io.files._out_of_space", lambda p, n: True)
    import OpenImageIO as oiio

    class _Failing:  # OpenImageIO reports a failed write with a message, no error number
        def open(self, *a):
            return True

        def write_image(self, *a):
            return False

        def geterror(self):
            return "Failed OpenEXR write"

        def close(self):
            return True

    monkeypatch.setattr(oiio.ImageOutput, "create", staticmethod(lambda path: _Failing()))
    with pytest.raises(OSError, match=r"no space left on device writing depth.exr \(3.2 kB\)"):
        write_image(tmp_path / "depth.exr", np.zeros((20, 40), np.float32))
    assert not list(tmp_path.iterdir())

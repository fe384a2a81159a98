"""Frames show as pictures in Jupyter, reports, errors and fits as tables (what IPython's display formatter
returns for them, the same call a notebook makes)."""

from __future__ import annotations

import io
from html import escape

import numpy as np
import pytest
from IPython.core.interactiveshell import InteractiveShell

import terrainwarp as tw


@pytest.fixture(scope="module")
def shell():
    return InteractiveShell.instance()


@pytest.fixture(scope="module")
def hm():
    return tw.Heightmap.fbm(65, seed=6, max_height=400.0, dx=10.0)


def _png(data: bytes) -> np.ndarray:
    import matplotlib.image as mpimg

    return np.round(mpimg.imread(io.BytesIO(data), format="png") * 255).astype(np.uint8)


def test_a_frame_shows_as_its_image_else_its_depth_else_its_ids(shell, hm):
    cam = tw.Camera.default_for(hm, 64, 48)
    f = tw.render(tw.Scene(hm, camera=cam, outputs=("image", "depth")))
    data, _ = shell.display_formatter.format(f)
    assert np.array_equal(_png(data["image/png"]), f.image)
    depth = tw.render(tw.Scene(hm, camera=cam, outputs=("depth",)))
    pic = _png(shell.display_formatter.format(depth)[0]["image/png"])
    drawn = depth.depth < 1.0
    near, far = np.unravel_index(np.argmin(np.where(drawn, depth.depth, 2)), drawn.shape), \
        np.unravel_index(np.argmax(np.where(drawn, depth.depth, -1)), drawn.shape)
    assert pic.shape == (48, 64, 3) and pic[near][0] > pic[far][0]
    ids = tw.render(tw.Scene(hm, camera=cam, outputs=("error",)))
    assert ids.depth is None and ids.triangle_id is not None
    assert _png(shell.display_formatter.format(ids)[0]["image/png"]).shape == (48, 64, 3)
    mesh_only = tw.render(tw.Scene(hm, camera=cam, outputs=("mesh",)))
    assert "image/png" not in shell.display_formatter.format(mesh_only)[0]
    assert repr(mesh_only).startswith("Frame('scene', 64x48, no images, 8192 triangles")


def test_report_error_and_fit_show_as_tables(shell, hm):
    cam = tw.Camera.default_for(hm, 64, 48)
    sc = tw.Scene(hm, camera=cam, mesh="lod", lod=tw.LodConfig(roots=4, tess=4), outputs=("image", "error"))
    f = tw.render(sc)
    rep = shell.display_formatter.format(f.report)[0]["text/html"]
    assert rep.startswith("<table><caption>frame cost (select + mesh + raster): ")
    assert [f"<td>{s.name}</td>" in rep for s in f.report.stages] == [True] * len(f.report.stages)
    assert rep.count("<table>") == 1 and "pipeline statistic" not in rep  # no counters asked for: none shown
    counted = tw.render(sc.with_(outputs=("depth", "counters"))).report
    rep = shell.display_formatter.format(counted)[0]["text/html"]
    assert rep.count("<table>") == 2
    assert [f"<td>{k}</td><td>{v}</td>" in rep for k, v in counted.counters.items()
            if isinstance(v, int)] == [True] * sum(isinstance(v, int) for v in counted.counters.values())
    err = shell.display_formatter.format(f.error)[0]["text/html"]
    assert f"<td>{f.error.p99_px:.4g}</td>" in err and "primary" in err and "see-through pixels" in err
    fit = tw.fit_lod(sc, 2.0, policy="chunked", cameras=[cam])
    html = shell.display_formatter.format(fit)[0]["text/html"]
    assert escape(fit.message) in html and f"<td>{fit.value:.4g}</td>" in html
    assert html.count("<table>") == 2  # the fit, then its camera

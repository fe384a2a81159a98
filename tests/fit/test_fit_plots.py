"""fit.png (issue 44, defects 7 and 8): a one-knob fit had an empty 0-1 left panel (no relaxed rounds to show) and,
with one try, y ticks from 9.86e-1 to 1e0; and plot_fit switched the caller's matplotlib backend to Agg (in
Jupyter that stops inline plots)."""

from __future__ import annotations

import matplotlib
import pytest

from terrainwarp import Camera, Heightmap, Scene, fit_lod
from terrainwarp.fit.plots import fit_figure, plot_convergence, plot_fit


@pytest.fixture(scope="module")
def one_knob():
    hm = Heightmap.fbm(33, seed=2, dx=20.0, max_height=300.0)
    sc = Scene(hm, camera=Camera.default_for(hm, 64, 48))
    res = fit_lod(sc, 2.0, "sse", sc.camera_path(2))
    assert res.met and not any(h.get("stage") == "relaxed" for h in res.history)
    return res


def test_one_knob_fit_has_no_empty_panel_and_readable_ticks(one_knob):
    fig = fit_figure(one_knob)
    assert len(fig.axes) == 1 and fig.axes[0].get_title().startswith("exact tries")
    assert all(ax.lines for ax in fig.axes)  # every panel draws something
    lo, hi = fig.axes[0].get_ylim()
    assert hi / lo >= 4.0 and lo < one_knob.budget_px < hi
    # a cost-against-budget panel needs two budgets; with two it is there
    assert len(fit_figure(one_knob, [(2.0, 100.0)]).axes) == 1
    assert len(fit_figure(one_knob, [(1.0, 150.0), (2.0, 100.0)]).axes) == 2


def test_plot_fit_leaves_the_callers_backend_and_pyplot_alone(one_knob, tmp_path):
    import matplotlib.pyplot as plt

    before = matplotlib.get_backend()
    try:
        matplotlib.use("pdf")
        open_figures = plt.get_fignums()
        plot_fit(one_knob, tmp_path / "fit.png")
        plot_convergence({"fit_lod": one_knob.trace}, tmp_path / "convergence.png")
        assert matplotlib.get_backend() == "pdf" and plt.get_fignums() == open_figures
    finally:
        matplotlib.use(before)
    assert (tmp_path / "fit.png").read_bytes()[:4] == b"\x89PNG"

"""lod.png (plot_patches): the heightmap's outline, and patches that overhang it hatched beyond the border with
a legend note saying what happens there (issue 20 item 12)."""

from __future__ import annotations

import pytest

from terrainwarp import Camera, Heightmap, Scene
from terrainwarp.cli import main
from terrainwarp.experiments.plots import OVERHANG_NOTE, patches_figure, plot_patches
from terrainwarp.heightmap import StreamedHeightmap
from terrainwarp.lod import ScreenErrorPolicy, Terrain, select

pytest.importorskip("matplotlib")


def _legend(fig) -> list[str]:
    return [t.get_text() for t in fig.axes[0].get_legend().get_texts()]


def _selection(hm: Heightmap):
    cam = Camera.default_for(hm, 320, 240)
    return select(Terrain.prepare(hm, roots=4, tess=16), cam, ScreenErrorPolicy(1.0)), cam


def test_overhanging_patches_are_hatched_and_explained(tmp_path):
    import matplotlib.pyplot as plt

    hm = Heightmap.example()  # 344 x 403 samples: the power-of-two roots reach past its east and south edges
    patches, cam = _selection(hm)
    (x0, z0), (x1, z1) = hm.bounds_xz
    ends = patches.origin + patches.size
    assert (ends[:, 0] > x1).any() or (ends[:, 1] > z1).any()
    fig = patches_figure(hm, patches, cam)
    try:
        legend = _legend(fig)
        assert "heightmap border" in legend and OVERHANG_NOTE in legend and "clamped" in OVERHANG_NOTE
        hatched = [p for p in fig.axes[0].patches if p.get_hatch()]
        assert hatched and all(p.get_x() >= x1 or p.get_y() >= z1 or p.get_x() + p.get_width() <= x0
                               or p.get_y() + p.get_height() <= z0 for p in hatched)  # only beyond the border
        # the view shows the overhang, not just the heightmap
        lo, hi = sorted(fig.axes[0].get_xlim())
        assert hi >= float(ends[:, 0].max())
    finally:
        plt.close(fig)
    out = plot_patches(hm, patches, cam, tmp_path / "lod.png")
    assert out.stat().st_size > 1000


def test_no_overhang_no_note():
    import matplotlib.pyplot as plt

    hm = Heightmap.fbm(65, seed=2)  # 64 x 64 cells: four roots cover it exactly
    patches, cam = _selection(hm)
    fig = patches_figure(hm, patches, cam)
    try:
        legend = _legend(fig)
        assert "heightmap border" in legend and OVERHANG_NOTE not in legend
        assert not [p for p in fig.axes[0].patches if p.get_hatch()]
    finally:
        plt.close(fig)


def test_lod_command_draws_a_streamed_terrain(tmp_path, capsys):
    # fuzz finding: `terrainwarp lod` on a scene with stream = true printed a traceback
    # (AttributeError: 'StreamedHeightmap' object has no attribute 'heights', from the hillshade)
    scene = tmp_path / "s.toml"
    scene.write_text('[heightmap]\nfbm = {rows = 65, seed = 1, octaves = 3}\nstream = true\n')
    assert isinstance(Scene.load(scene).heightmap, StreamedHeightmap)
    rc = main(["lod", str(scene), "--width", "16", "--height", "12", "--out", str(tmp_path / "out")])
    assert rc == 0 and (tmp_path / "out" / "lod.png").stat().st_size > 0

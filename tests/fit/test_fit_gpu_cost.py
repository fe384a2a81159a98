"""fit_lod with GPU profiles and with several models at once (the worst modelled ms per frame): the exact tries
price each frame with the models themselves."""

from __future__ import annotations

import numpy as np
import pytest

from terrainwarp import Camera, Heightmap, LodConfig, Scene
from terrainwarp.fit import fit_lod
from terrainwarp.fit.exact import references_for
from terrainwarp.measure.gpu import shipped_profile
from terrainwarp.rendering.pipeline import render


@pytest.fixture(scope="module")
def scene():
    hm = Heightmap.fbm(129, seed=4, dx=20.0, max_height=600.0, feature_size=48.0)
    sc = Scene(hm, camera=Camera.default_for(hm, 128, 96), lod=LodConfig(roots=4, tess=8))
    cams = sc.camera_path(3)
    return sc, cams, references_for(sc, cams)


def test_a_fit_for_several_gpus_minimises_each_frames_worst_modelled_ms(scene):
    sc, cams, refs = scene
    models = [shipped_profile("gf100"), shipped_profile("mali")]
    both = fit_lod(sc, 2.0, "sse", cams, references=refs, cost=["gpu:gf100", "gpu:mali"])
    assert both.met and both.cost == "worst modelled ms over gf100, mali"
    v = both.validated
    counted = [render(both.scene.with_(camera=c, outputs=("counters",))).report.counters for c in cams]
    assert v.costs == [max(m(c) for m in models) for c in counted]
    assert v.cost == float(np.mean(v.costs))
    one = fit_lod(sc, 2.0, "sse", cams, references=refs, cost="gpu:gf100")
    assert one.met and one.cost == "modelled gf100 ms"
    assert one.validated.costs == [models[0](render(one.scene.with_(camera=c, outputs=("counters",)))
                                             .report.counters) for c in cams]

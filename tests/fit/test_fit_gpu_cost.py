"""fit_lod with GPU profiles and with several models at once (the worst modelled ms per frame): the exact tries
price each frame with the models themselves."""

from __future__ import annotations

import numpy as np
import pytest
from fit_scenes import fit_scene

from terrainwarp.fit import fit_lod
from terrainwarp.measure.gpu import shipped_profile
from terrainwarp.rendering.pipeline import render


@pytest.fixture(scope="module")
def scene():
    return fit_scene()


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

"""Rankings that say how sure they are (terrainwarp.measure.ranking): the winner under a model, whether it
survives every rate x1/3..x3, and the smallest change that flips it."""

from __future__ import annotations

import pytest

from terrainwarp.kernels.counters import PIPELINE_COUNTERS
from terrainwarp.measure.cost import CostModel, shipped_model
from terrainwarp.measure.gpu import shipped_profile
from terrainwarp.measure.ranking import rate_terms, verdict

ZERO = dict.fromkeys(PIPELINE_COUNTERS, 0)


def _frame(tris: float, lanes: float, samples: float = 1e6) -> dict:
    return {**ZERO, "clipping_input_primitives": tris, "fragment_shader_invocations": lanes,
            "samples_passed": samples}


def test_the_winner_is_the_cheapest_mean_over_frames_and_names_its_bound_stage():
    p = shipped_profile("gf100")
    cands = {"many small triangles": [_frame(4e6, 6e6), _frame(3e6, 6e6)],
             "few big triangles": [_frame(2e5, 9e6), _frame(2e5, 9e6)]}
    v = verdict(cands, p)
    costs = {k: sum(p(f) for f in fs) / len(fs) for k, fs in cands.items()}
    assert v.winner == min(costs, key=costs.get) == "few big triangles" and v.cost == costs[v.winner]
    assert v.bound == "shade" and v.model == "gf100"


def test_a_dominated_field_is_robust_and_a_close_call_names_the_rate_that_flips_it():
    p = shipped_profile("gf100")
    dominant = {"a": [_frame(1e5, 1e6)], "b": [_frame(2e6, 2e7)]}
    v = verdict(dominant, p)
    assert v.winner == "a" and v.robust and v.flip == ""
    # a: setup-bound (2.5e6 tris = 0.89 ms), b: shade-bound (6.4e7 lanes = 2.9 ms): b wins only if shading is
    # more than 3.2x faster than published, a loses as soon as setup is ~3.3x slower: neither within x1/3..x3
    # alone at these numbers, so move them closer: b at 2.2e7 lanes (0.98 ms) flips with setup x<0.9
    close = {"a": [_frame(2.5e6, 1e6)], "b": [_frame(1e5, 2.2e7)]}
    v = verdict(close, p)
    assert v.winner == "a" and not v.robust and v.flip.endswith("-> b")
    assert v.flip.startswith("setup (triangles_per_clock) x") or v.flip.startswith("shade (pixels_per_clock) x")
    factor = float(v.flip.split(" x")[1].split()[0])
    assert 1 / 3 <= factor <= 3
    # the named change really flips it
    stage = v.flip.split(" (")[0]
    assert verdict(close, p.scaled({stage: factor})).winner == "b"


def test_a_linear_model_reads_its_weights_as_rates():
    m = CostModel("toy", {"clipping_input_primitives": 1e-6, "samples_passed": 1e-6}, intercept_ms=0.5)
    names, t, combine, overhead = rate_terms(m, [_frame(1e6, 0, 2e6)])
    assert names == ["clipping_input_primitives", "samples_passed"] and combine == "sum" and overhead == 0.5
    assert t.tolist() == [[1.0, 2.0]]
    v = verdict({"x": [_frame(1e6, 0, 2e6)], "y": [_frame(1.9e6, 0, 1.0e6)]}, m)
    assert v.winner == "y" and v.cost == pytest.approx(0.5 + 1.9 + 1.0) and not v.robust and v.bound == ""
    assert "1/weight of " in v.flip and v.flip.endswith("-> x")
    assert verdict({"x": [_frame(1e6, 0, 2e6)]}, shipped_model()).robust  # one candidate: nothing to flip to


def test_bad_candidates_are_refused():
    with pytest.raises(ValueError, match="at least one setting"):
        verdict({}, shipped_profile("rdna"))
    with pytest.raises(ValueError, match="at least one frame"):
        verdict({"a": []}, shipped_profile("rdna"))
    with pytest.raises(TypeError, match="CostModel or a GpuProfile"):
        rate_terms(object(), [ZERO])

"""A cost model's weights file (terrainwarp.measure.cost.CostModel.to_json / from_json): strict JSON, an undefined
R^2 written as null with its reason and read back as NaN, the checksum over what was written."""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict

import pytest

from terrainwarp.measure.cost import CostModel


def _strict(text: str) -> dict:
    def refuse(token: str):
        raise ValueError(f"not strict JSON: {token}")

    return json.loads(text, parse_constant=refuse)


def _model(r2: float) -> CostModel:
    return CostModel("toy", {"draw_calls": 0.01, "samples_passed": 1e-6}, intercept_ms=0.5, driver="d",
                     r2_heldout=r2, frames=4, families={"sse": 4}, command="terrainwarp calibrate --gl")


def _same_but_r2(a: CostModel, b: CostModel) -> bool:
    return {k: v for k, v in asdict(a).items() if k != "r2_heldout"} == \
        {k: v for k, v in asdict(b).items() if k != "r2_heldout"}


def test_an_undefined_r2_is_null_with_its_reason_and_loads_back_as_nan(tmp_path):
    m = _model(math.nan)
    d = _strict(m.to_json())
    assert d["r2_heldout"] is None and d["r2_heldout_reason"].startswith("nan: undefined")
    p = tmp_path / "weights.json"
    p.write_text(m.to_json())
    back = CostModel.load(p)
    assert math.isnan(back.r2_heldout) and _same_but_r2(back, m)
    assert back.to_json() == m.to_json()
    d["r2_heldout"] = 0.99  # a null filled in by hand: the checksum refuses it
    p.write_text(json.dumps(d))
    with pytest.raises(ValueError, match="checksum"):
        CostModel.load(p)


def test_a_finite_r2_has_no_reason_and_a_file_written_with_nan_tokens_still_loads():
    m = _model(0.93)
    d = _strict(m.to_json())
    assert d["r2_heldout"] == 0.93 and "r2_heldout_reason" not in d and CostModel.from_json(m.to_json()) == m
    old = asdict(_model(math.nan))  # as the earlier to_json wrote it: a bare NaN token, hashed as such
    old["features"] = list(old["weights"])
    old["sha256"] = hashlib.sha256(json.dumps(old, sort_keys=True).encode()).hexdigest()
    text = json.dumps(old, indent=2, sort_keys=True)
    assert "NaN" in text
    back = CostModel.from_json(text)
    assert math.isnan(back.r2_heldout) and _same_but_r2(back, m)

"""The fuzz suite (issue 31): its bounded run in ``make test``, and the harness itself.

The full run (10,000+ cases) is ``python benchmarks/bench_fuzz.py``; here a few hundred cases of every target
run through the same worker subprocess, and must give no finding: no crash, no hang, no exception but a
ValueError, TypeError or OSError naming the input, no bad result, no CLI traceback. The harness is tested too:
a worker that segfaults, aborts, dies of SIGBUS or hangs is caught and its input kept; the oracle flags an
escaped exception, an unnamed error and a bad result; the cases are the same for a seed.
"""

from __future__ import annotations

import hashlib
import json
import sys

import pytest
from fuzz_corpus import TARGETS, Case
from fuzz_runner import Supervisor, each_case, fuzz, judge_cli, judge_load, keep_finding, names_input

import terrainwarp.cli as cli
from terrainwarp import Heightmap

SEED = 31
LOADERS = {"png": 60, "tiff": 60, "geotiff": 80, "npy": 60}
SCENES_AND_CLI = {"toml": 60, "cli": 30}


def _report(counts) -> str:
    return "\n".join(f"{f['target']} #{f['index']} {f['verdict']}: {f.get('type')}: {f.get('message')} "
                     f"[{f['how'][:200]}] {f.get('argv') or f.get('call')}" for f in counts.findings[:20])


def test_the_loaders_refuse_every_mutated_file_cleanly(tmp_path):
    counts = fuzz(LOADERS, seed=SEED, findings=tmp_path / "findings", log=tmp_path / "worker.log")
    assert {t: sum(v.values()) for t, v in counts.verdicts.items()} == LOADERS
    assert counts.n_findings() == 0, _report(counts)
    for t in LOADERS:  # each target both loads and refuses something: the mutations reach the decoders
        assert counts.verdicts[t]["ok"] > 0 and counts.verdicts[t]["ValueError"] > 0, (t, counts.verdicts[t])


def test_scenes_and_command_lines_are_refused_cleanly(tmp_path):
    counts = fuzz(SCENES_AND_CLI, seed=SEED, findings=tmp_path / "findings", log=tmp_path / "worker.log")
    assert counts.n_findings() == 0, _report(counts)
    assert counts.verdicts["cli"]["ok"] > 0 and counts.verdicts["cli"]["refused"] > 0


# -- the harness ---------------------------------------------------------------------------------------------
def test_a_worker_that_crashes_or_hangs_is_replaced_and_its_input_kept(tmp_path):
    calls = [{}, {"do": "segv"}, {}, {"do": "sleep", "s": 30}, {"do": "abort"}, {"do": "bus"}, {"do": "exit"}, {}]
    cases = [Case("selftest", i, f"in{i}.bin", f"input {i}".encode(), call=c) for i, c in enumerate(calls)]
    sup = Supervisor(log=tmp_path / "worker.log", hang_s=2.0)
    try:
        got = {c.index: r for c, r in sup.run(cases)}
    finally:
        sup.close()
    verdicts = ["ok", "crash", "ok", "hang", "crash", "crash", "crash", "ok"]
    assert [got[i]["verdict"] for i in range(len(cases))] == verdicts
    assert [got[i]["message"] for i in (1, 4, 5, 6)] == [f"worker exited with {how}" for how in (
        "signal SIGSEGV", "signal SIGABRT", "signal SIGBUS", "code 3")]
    assert 2.0 <= got[3]["secs"] < 10.0 and sup.restarts == 5
    d = keep_finding(tmp_path / "findings", cases[1], got[1], seed=0)
    assert (d / "in1.bin").read_bytes() == b"input 1"
    assert json.loads((d / "finding.json").read_text())["verdict"] == "crash"


def test_the_oracle_flags_what_it_should(tmp_path, monkeypatch):
    case = Case("npy", 0, "x.npy", b"")
    (tmp_path / "x.npy").write_bytes(b"")
    p = tmp_path / "x.npy"
    for exc, verdict in ((KeyError("k"), "exception"), (ValueError("boom"), "unnamed"),
                         (ValueError(f"path: {p}: boom"), "ValueError"), (FileNotFoundError(f"path: {p}"), "OSError"),
                         (TypeError("channel: expected an integer"), "unnamed")):
        def load(*a, exc=exc, **k):
            raise exc
        monkeypatch.setattr(Heightmap, "load", load)
        assert judge_load(case, tmp_path)["verdict"] == verdict, exc
    monkeypatch.setattr(Heightmap, "load", lambda *a, **k: object())
    assert judge_load(case, tmp_path)["verdict"] == "bad-result"

    def boom(argv):
        raise RuntimeError("not a clean error")
    monkeypatch.setattr(cli, "main", boom)
    assert judge_cli(Case("cli", 0, "s.toml", b"", argv=["demo"]), tmp_path)["verdict"] == "traceback"

    def unnamed(argv):
        print("terrainwarp: error: something went wrong", file=sys.stderr)
        return 2
    monkeypatch.setattr(cli, "main", unnamed)
    assert judge_cli(Case("cli", 0, "s.toml", b"", argv=["demo", "--width", "16"]), tmp_path)["verdict"] == "unnamed"
    assert names_input("--width: expected an integer", {"width"}) and names_input("lod.tess: no", {"tess"})
    assert not names_input("invalid literal for int() with base 10: 'x'", {"n", "path", "x.toml"})


@pytest.mark.parametrize("target", TARGETS)
def test_every_target_mutates_its_seeds_the_same_way_for_a_seed(target):
    def draw(seed: int) -> list[bytes]:
        seen: list[Case] = []
        each_case(target, 40, seed, seen.append)
        return [c.data + repr((c.call, c.argv, c.name)).encode() for c in seen]

    a = draw(3)
    assert len(a) == 40 and len(set(a)) >= 20  # mutated, not one seed over and over
    assert draw(3) == a  # drawn in their own process: whatever this one has imported
    if target == "png":
        assert hashlib.sha256(b"".join(draw(4))).digest() != hashlib.sha256(b"".join(a)).digest()

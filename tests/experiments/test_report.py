import csv
import io
import math

import pytest

from terrainwarp import Camera, Heightmap, Scene
from terrainwarp.experiments.pareto import (
    TIMING_COLUMNS,
    Setting,
    budget_table,
    default_settings,
    pareto,
    rows_to_csv,
    summarise,
    sweep,
    write_report,
)
from terrainwarp.schemes import SCHEMES, scheme_range


@pytest.fixture(scope="module")
def small():
    hm = Heightmap.fbm(65, 80, seed=9, dx=20.0, max_height=400.0)
    sc = Scene(hm, camera=Camera.default_for(hm, 96, 72))
    return sc, sc.camera_path(2)


SETTINGS = [Setting("grid", 0.0), Setting("sse", 0.1), Setting("sse", 8.0), Setting("continuous", 8.0),
            Setting("delatin", 2.0), Setting("martini", 8.0), Setting("polytree", 4.0), Setting("bintree", 15.0)]


def _strip(text: str) -> list[dict]:
    rows = list(csv.DictReader(io.StringIO(text)))
    for r in rows:
        for k in (*TIMING_COLUMNS, "prepare_ms"):
            r.pop(k, None)
    return rows


def test_sweep_is_reproducible_apart_from_timings(small):
    sc, cams = small
    a = sweep(sc, cams, SETTINGS, progress=False)
    b = sweep(sc, cams, SETTINGS, progress=False)
    assert _strip(rows_to_csv(a)) == _strip(rows_to_csv(b))
    assert len(a) == len(SETTINGS) * len(cams)
    grid = [r for r in a if r["policy"] == "grid"]
    assert all(r["p99_px"] < 1e-2 and r["see_through_px"] == 0 for r in grid)
    coarse = [r for r in a if r["setting"] == "sse=8"]
    fine = [r for r in a if r["setting"] == "sse=0.1"]
    assert sum(r["triangles"] for r in coarse) < sum(r["triangles"] for r in fine)
    assert all(r["see_through_px"] == 0 for r in a if r["policy"] in ("sse", "continuous", "polytree", "bintree"))
    assert all(r["triangles"] > 0 and r["peer_mesh_ms"] > 0 for r in a if r["policy"] in ("polytree", "bintree"))


def test_report_files_and_tables(small, tmp_path):
    sc, cams = small
    rows = sweep(sc, cams, SETTINGS[:1] + SETTINGS[4:6], progress=False, images=False)
    paths = {p.name for p in write_report(sc, cams, rows, tmp_path)}
    assert paths == {"frames.csv", "pareto.png", "report.md", "timing.md"}
    summ = summarise(rows)
    front = pareto(summ)
    assert front and all(r in summ for r in front)
    tab = budget_table(summ, budgets=(1e9,))
    assert {r[1] for r in tab} == {"grid", "delatin", "martini"}
    md = (tmp_path / "report.md").read_text()
    assert "Cheapest setting per budget" in md and "frame_ms" not in md  # CPU time is timing.md's
    assert "frame_ms" in (tmp_path / "timing.md").read_text()


def _frames_csv(path) -> list[dict]:
    return list(csv.DictReader(io.StringIO((path / "frames.csv").read_text())))


def test_frames_csv_has_the_primary_image_and_popping_columns(small, tmp_path):
    sc, cams = small
    rows = sweep(sc, cams, [Setting("grid", 0.0), Setting("sse", 8.0), Setting("delatin", 2.0)], progress=False,
                 images=False)
    write_report(sc, cams, rows, tmp_path, path=sc.path_info(2))
    got = _frames_csv(tmp_path)
    for col in ("p99_px", "max_px", "image_err_p99_px", "image_err_max_px", "see_through_px", "pop_p99_px",
                "pop_max_px", "popped_samples"):
        assert col in got[0], col
    for r in got:
        assert (r["pop_p99_px"] == "nan") == (r["frame"] == "0")  # no pair before the first frame
    grid = [r for r in got if r["policy"] == "grid"]
    assert all(float(r["p99_px"]) == 0.0 and float(r["pop_max_px"] if r["frame"] != "0" else 0) == 0.0
               for r in grid)
    assert all(float(r["image_err_p99_px"]) < 1e-2 for r in grid)
    md = (tmp_path / "report.md").read_text()
    assert "Camera path: flyover of 2 cameras at" in md and "2.0% of the" in md and "'ground'" in md
    assert "Popping" in md and "Old yardstick's floor here" in md and "image_err_p99_px" in md
    # beside each image p99, its family's floor on that camera (the lowest over the family's swept settings)
    for r in got:
        same = [float(x["image_err_p99_px"]) for x in got if x["policy"] == r["policy"] and x["frame"] == r["frame"]]
        assert float(r["image_err_floor_p99_px"]) == min(same) <= float(r["image_err_p99_px"])
    assert "image_err_floor_p99_px" in md and "cracks" not in md.replace("cracks are check_watertight", "")
    for r in got:  # too few samples for a p99: flagged per frame
        n, cov = int(r["samples_visible"]), int(r["covered"])
        assert r["sparse"] == str(int(n < 1000 or 50 * n < cov))


def test_popping_is_zero_for_a_static_camera_and_an_unchanged_selection(small):
    sc, cams = small
    still = [cams[1], cams[1]]  # two identical cameras
    nudged = [cams[1], cams[1].with_(position=tuple(p + d for p, d in zip(cams[1].position, (0.5, 0.0, 0.5))))]
    settings = [Setting("sse", 64.0), Setting("sse", 2.0), Setting("bintree", 15.0), Setting("delatin", 2.0)]
    for path in (still, nudged):
        rows = sweep(sc, path, settings, progress=False, images=False)
        for r in rows:
            if r["frame"] == 1 and (path is still or r["setting"] == "sse=64"):
                assert (r["pop_p99_px"], r["pop_max_px"], r["popped_samples"]) == (0.0, 0.0, 0), r
    # the coarse selection is the same from both cameras: the held frame is the current one
    rows = sweep(sc, cams, [Setting("sse", 0.5)], progress=False, images=False)
    assert rows[1]["pop_max_px"] > 0  # a real move changes a fine selection


def test_the_schemes_are_report_policies_with_error_popping_and_cost(small):
    """CDLOD, clipmaps and chunked LOD (rendering.sources.SCHEMES) sweep beside the others: a few settings each
    in the parameter's range, and every row has the primary and image error, popping, triangles and frame ms."""
    sc, cams = small
    settings = [s for s in default_settings(sc.heightmap, quick=True) if s.policy in SCHEMES]
    assert [s.policy for s in settings] == [n for n in SCHEMES for _ in range(2)]
    for s in settings:
        lo, hi = scheme_range(s.policy, sc.heightmap)
        assert lo <= s.param <= hi
    rows = sweep(sc, cams, settings, progress=False, images=False, workers=0)
    assert {r["policy"] for r in rows} == set(SCHEMES) and len(rows) == len(settings) * len(cams)
    for r in rows:
        assert not r["error"], r
        for k in ("p99_px", "max_px", "image_err_p99_px", "triangles", "frame_ms", "select_ms", "mesh_ms",
                  "raster_ms"):
            assert math.isfinite(r[k]), (k, r)
        assert r["triangles"] > 0 and r["frame_ms"] > 0
        assert math.isfinite(r["pop_p99_px"]) == (r["frame"] == 1)
    summ = {r["setting"]: r for r in summarise(rows)}
    assert all(math.isfinite(summ[s.label]["pop_p99_px"]) for s in settings)


def test_report_md_pareto_png_and_frames_csv_are_byte_identical_across_runs_and_threads(small, tmp_path):
    """What a report ranks by is counted, not timed: report.md, pareto.png and frames.csv without its timing
    columns (cost_ms, a cost model of the counters, kept) are the same bytes for one and two kernel threads."""
    from terrainwarp.kernels.parallel import set_threads

    sc, cams = small
    settings = [Setting("grid", 0.0), Setting("sse", 2.0), Setting("delatin", 2.0), Setting("cdlod", 600.0)]
    out = []
    for k, threads in enumerate((1, 2)):
        try:
            set_threads(threads)
            rows = sweep(sc, cams, settings, progress=False, images=False, workers=0)
        finally:
            set_threads(None)
        d = tmp_path / str(k)
        write_report(sc, cams, rows, d, path=sc.path_info(2))
        out.append(d)
    for name in ("report.md", "pareto.png"):
        assert (out[0] / name).read_bytes() == (out[1] / name).read_bytes(), name
    a, b = (_strip((d / "frames.csv").read_text()) for d in out)
    assert a == b and all(float(r["cost_ms"]) > 0 and int(r["draw_calls"]) >= 1 for r in a)


def test_report_ranks_by_the_cost_asked_for(small, tmp_path):
    from terrainwarp.measure.cost import cost, shipped_model

    sc, cams = small
    rows = sweep(sc, cams, [Setting("sse", 0.5), Setting("sse", 8.0), Setting("delatin", 2.0)], progress=False,
                 images=False, workers=0)
    model = shipped_model()
    for r in rows:
        assert r["cost_ms"] == model(r)  # the shipped model of the row's counters
    by_model = {r["setting"]: r["cost"] for r in summarise(rows)}
    by_fs = {r["setting"]: r["cost"] for r in summarise(rows, cost("fragment_shader_invocations"))}
    for label in by_model:
        rs = [r for r in rows if r["setting"] == label]
        assert by_fs[label] == sum(r["fragment_shader_invocations"] for r in rs) / len(rs)
    write_report(sc, cams, rows, tmp_path, cost_of="triangles")
    md = (tmp_path / "report.md").read_text()
    assert "Cost (`cost`): `triangles` per frame" in md and "Pareto front (triangles)" in md
    with pytest.raises(ValueError, match="cost"):
        cost("pixels")

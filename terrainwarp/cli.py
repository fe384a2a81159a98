"""The ``terrainwarp`` command line.

Every command that takes a scene file uses the demo scene (the bundled SRTM DEM, default camera) when
none is given. Outputs go under ``--out DIR``. Bad arguments print one line on stderr and exit 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from .camera import Camera
from .experiments.pareto import Setting, default_settings, summarise, sweep, write_report
from .experiments.plots import plot_patches
from .experiments.stability import EXPLANATIONS, FAIL, run_suite, write_stability_md
from .fit.lod_fit import Evaluation, evaluations_from_rows, fit_lod, plot_fit
from .heightmap import Heightmap
from .io.files import write_json, write_text
from .lod.policies import make_policy
from .lod.quadtree import Terrain, select
from .rendering.pipeline import render
from .rendering.reference_tessellator import tessellation_json, write_tessellation_picture
from .scene import LOD_POLICIES, POLICY_TABLE, SPACINGS, LodConfig, Scene

__all__ = ["main", "sweep_evaluator"]


_LOD = LodConfig()  # the defaults of the LOD options


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit code 2, no usage dump
        print(f"terrainwarp: error: {message}", file=sys.stderr)
        raise SystemExit(2)


def _scene(args: argparse.Namespace) -> Scene:
    if getattr(args, "scene", None):
        sc = Scene.load(args.scene)
    else:
        sc = Scene(Heightmap.example("jacksboro"), name="demo")
    cam = sc.camera
    if getattr(args, "width", None) is not None or getattr(args, "height", None) is not None:
        w = cam.width if args.width is None else args.width
        h = cam.height if args.height is None else args.height
        cam = Camera.default_for(sc.heightmap, w, h, cam.fov_y_deg) if not sc.source.get("camera") \
            else cam.with_(width=w, height=h)
        sc = sc.with_(camera=cam)
    return sc


def _cmd_render(args: argparse.Namespace) -> int:
    sc = _scene(args)
    if "report" not in sc.outputs:
        sc = sc.with_(outputs=(*sc.outputs, "report"))
    frame = render(sc)
    written = frame.save(args.out)
    print(frame.report.table())
    print("wrote: " + ", ".join(str(p) for p in written))
    return 0


def _positive_float(s: str) -> float:
    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {s!r}") from None
    if not (v > 0 and v < float("inf")):
        raise argparse.ArgumentTypeError(f"expected a positive finite number, got {s}")
    return v


def _nonnegative_int(s: str) -> int:
    try:
        v = int(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {s!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected >= 0, got {v}")
    return v


def _cmd_lod(args: argparse.Namespace) -> int:
    sc = _scene(args)
    terrain = Terrain.prepare(sc.heightmap, roots=args.roots, tess=args.tess)
    # the policy from the table: the chosen policy's parameter (--tolerance-px, --k or --target-px), the
    # hysteresis and the level; roots and tess go to the terrain (any tess in 1..64 here)
    cfg = LodConfig(policy=args.policy, hysteresis=args.hysteresis, level=args.level,
                    **{s.field: getattr(args, s.field) for s in POLICY_TABLE.values()})
    patches = select(terrain, sc.camera, make_policy(cfg))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    patches.to_csv(out / "patches.csv")
    plot_patches(sc.heightmap, patches, sc.camera, out / "lod.png",
                 title=f"{args.policy}: {len(patches)} patches, {patches.stats['culled']} culled")
    print(json.dumps({**patches.stats, "levels": np.bincount(patches.level).tolist() if len(patches) else []}))
    print(f"wrote: {out / 'lod.png'}, {out / 'patches.csv'}")
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    sc = _scene(args)
    cams = sc.camera_path(args.frames)
    settings = default_settings(sc.heightmap, quick=args.quick)
    if args.policies:
        want = set(args.policies.split(","))
        bad = want - {s.policy for s in settings}
        if bad:
            raise ValueError(f"--policies: unknown {sorted(bad)}")
        settings = [s for s in settings if s.policy in want]
    # jobs run on a Dask LocalCluster (one process per core) or --scheduler; rows are saved to
    # frames.csv.partial as they arrive, so a rerun after an interruption resumes where it stopped
    rows = sweep(sc, cams, settings, progress=not args.no_progress, images=not args.no_images,
                 scheduler=args.scheduler, workers=args.workers, out=Path(args.out) / "frames.csv")
    failed = [r for r in rows if r["error"]]
    for r in failed[:5]:
        print(f"failed: {r['setting']} frame {r['frame']}: {r['error']}", file=sys.stderr)
    paths = write_report(sc, cams, rows, args.out)
    for r in summarise(rows):
        print(f"{r['setting']:>18}  p99 {r['p99_px']:8.3f} px  {r['frame_ms']:9.2f} ms  {int(r['triangles']):>9} tris")
    print("wrote: " + ", ".join(str(p) for p in paths))
    return 0


def sweep_evaluator(scene: Scene, cameras: list[Camera], policy: str, workers: int | None = None,
                    scheduler: str | None = None, device: str = "cpu"):
    """A grid-search evaluator (:func:`terrainwarp.fit.grid_search`) that runs the evaluations as jobs of the
    sweep runner (:func:`terrainwarp.experiments.pareto.sweep`, dask.distributed): ``workers`` local worker
    processes (None: one per core) or an existing ``scheduler``; the workers prepare their own terrain and
    references, and the table is the same as in-process."""
    def run(values: list[float]) -> list[Evaluation]:
        rows = sweep(scene, cameras, [Setting(policy, v) for v in values], progress=False, images=False,
                     device=device, scheduler=scheduler, workers=workers)
        return evaluations_from_rows(rows, policy, values)

    return run


def _cmd_fit(args: argparse.Namespace) -> int:
    sc = _scene(args)
    cams = sc.camera_path(args.frames)
    grid_evaluator = None if args.workers == 0 else sweep_evaluator(sc, cams, args.policy, args.workers)
    res = fit_lod(sc, args.budget_px, policy=args.policy, cameras=cams, grid_points=args.grid_points,
                  grid_evaluator=grid_evaluator)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    curve = []
    for b in args.curve_budgets:
        r = fit_lod(sc, b, policy=args.policy, cameras=cams)
        if r.met:
            curve.append((b, r.validated.cost))
    write_json(out / "fit.json", res.to_dict())
    plot_fit(res, out / "fit.png", curve or None)
    g = res.grid
    lines = ["# Fit", "", f"policy {args.policy}, budget {args.budget_px:g} px, {len(cams)} cameras", "",
             "| method | value | worst p99 px | triangles/frame | pipeline evaluations | wall s |",
             "|---|---|---|---|---|---|",
             f"| fit | {res.value:.4g} | {res.validated.worst_p99:.3g} | {res.validated.cost:.0f} | {res.evaluations} "
             f"| {res.wall_s:.1f} |"]
    if g:
        if g["value"] is None:
            lines.append(f"| grid search ({g['points']} points) | none met the budget | | | {g['evaluations']} | "
                         f"{g['wall_s']:.1f} |")
        else:
            lines.append(f"| grid search ({g['points']} points) | {g['value']:.4g} | {g['worst_p99_px']:.3g} | "
                         f"{g['cost']:.0f} | {g['evaluations']} | {g['wall_s']:.1f} |")
    lines += ["", res.message, ""]
    write_text(out / "report.md", "\n".join(lines))
    print(res.message)
    print(f"wrote: {out / 'fit.json'}, {out / 'fit.png'}, {out / 'report.md'}")
    return 0 if res.met else 1


def _cmd_stability(args: argparse.Namespace) -> int:
    n = 129 if args.full else 33
    cases = [c for c in args.cases.split(",") if c] if args.cases else None
    rows = run_suite(n, cases=cases, progress=not args.no_progress)
    cmd = "terrainwarp stability --out DIR" + (" --full" if args.full else "")
    path = write_stability_md(rows, args.out, command=cmd, n=n)
    counts = {}
    for r in rows:
        counts[r.status] = counts.get(r.status, 0) + 1
    print(", ".join(f"{v} {k}" for k, v in counts.items()))
    print(f"wrote: {path}")
    unexplained = [r for r in rows if r.status == FAIL and not any(k in r.note for k in EXPLANATIONS)]
    for r in unexplained:
        print(f"FAIL {r.case}/{r.stage}: {r.note}", file=sys.stderr)
    return 1 if unexplained else 0


def _cmd_tessellate(args: argparse.Namespace) -> int:
    out = Path(args.out)
    doc = tessellation_json(args.outer, args.inner, args.spacing)
    write_tessellation_picture(out / "tessellation.png", args.outer, args.inner, args.spacing)
    write_json(out / "tessellation.json", doc)
    print(json.dumps(doc))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="terrainwarp", description="A deterministic CPU simulator of the GPU terrain pipeline.")
    sub = p.add_subparsers(dest="cmd", required=True, parser_class=_Parser)
    d = sub.add_parser("demo", help="render the bundled real DEM (frame.png, depth.exr, report.json)")
    d.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    d.add_argument("--width", type=int, default=None)
    d.add_argument("--height", type=int, default=None)
    d.set_defaults(func=_cmd_render, scene=None)
    r = sub.add_parser("render", help="render a scene file")
    r.add_argument("scene", nargs="?", default=None, help="scene TOML (default: the demo scene)")
    r.add_argument("--out", default="out/render")
    r.add_argument("--width", type=int, default=None)
    r.add_argument("--height", type=int, default=None)
    r.set_defaults(func=_cmd_render)
    lo = sub.add_parser("lod", help="select LOD patches: top-down picture (lod.png) and table (patches.csv)")
    lo.add_argument("scene", nargs="?", default=None, help="scene TOML (default: the demo scene)")
    lo.add_argument("--out", default="out/lod")
    lo.add_argument("--policy", choices=list(LOD_POLICIES), default=_LOD.policy)
    for spec in POLICY_TABLE.values():  # --tolerance-px, --k, --target-px
        lo.add_argument("--" + spec.field.replace("_", "-"), type=_positive_float, default=getattr(_LOD, spec.field),
                        help=spec.help)
    lo.add_argument("--level", type=int, default=_LOD.level, help="continuous: the patch grid's level")
    lo.add_argument("--hysteresis", type=float, default=_LOD.hysteresis)
    lo.add_argument("--roots", type=int, default=_LOD.roots)
    lo.add_argument("--tess", type=int, default=_LOD.tess)
    lo.add_argument("--width", type=int, default=None)
    lo.add_argument("--height", type=int, default=None)
    lo.set_defaults(func=_cmd_lod)
    rp = sub.add_parser("report", help="sweep LOD settings and peers over the camera path: frames.csv, "
                                       "pareto.png, report.md")
    rp.add_argument("scene", nargs="?", default=None, help="scene TOML (default: the demo scene)")
    rp.add_argument("--out", default="out/report")
    rp.add_argument("--frames", type=int, default=None, help="cameras on the path (default: the scene's, or 8)")
    rp.add_argument("--policies", default=None,
                    help="comma-separated subset of grid,sse,distance,continuous,martini,delatin,polytree,bintree")
    rp.add_argument("--quick", action="store_true", help="two settings per policy")
    rp.add_argument("--no-images", action="store_true", help="skip shading (no PSNR/SSIM)")
    rp.add_argument("--no-progress", action="store_true")
    rp.add_argument("--width", type=int, default=None)
    rp.add_argument("--height", type=int, default=None)
    rp.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                    help="run the jobs on this Dask scheduler's cluster (default: a local cluster)")
    rp.add_argument("--workers", type=_nonnegative_int, default=None,
                    help="local worker processes (default: one per core; 0: in this process)")
    rp.set_defaults(func=_cmd_report)
    st = sub.add_parser("stability", help="run the extreme-case stability suite through every stage: stability.md")
    st.add_argument("--out", required=True, help="output folder for stability.md")
    st.add_argument("--full", action="store_true", help="129 x 129 grids instead of 33 x 33")
    st.add_argument("--cases", default=None, help="comma-separated subset of terrainwarp.experiments.extreme.CASES")
    st.add_argument("--no-progress", action="store_true")
    st.set_defaults(func=_cmd_stability)
    ft = sub.add_parser("fit", help="fit LOD thresholds to a screen-space error budget (fit.json, fit.png)")
    ft.add_argument("scene", nargs="?", default=None, help="scene TOML (default: the demo scene)")
    ft.add_argument("--budget-px", type=_positive_float, required=True, help="p99 screen error budget, pixels")
    ft.add_argument("--policy", choices=list(LOD_POLICIES), default=_LOD.policy)
    ft.add_argument("--frames", type=int, default=None)
    ft.add_argument("--grid-points", type=int, default=0, help="also run a grid search baseline with N points")
    ft.add_argument("--workers", type=int, default=0,
                    help="grid search on the sweep runner with N worker processes (0: in this process)")
    ft.add_argument("--curve-budgets", type=_positive_float, nargs="*", default=[],
                    help="also fit these budgets for the cost-against-budget curve")
    ft.add_argument("--out", default="out/fit")
    ft.add_argument("--width", type=int, default=None)
    ft.add_argument("--height", type=int, default=None)
    ft.set_defaults(func=_cmd_fit)
    te = sub.add_parser("tessellate", help="one quad patch through the GPU tessellator: tessellation.png and the "
                                          "triangles as JSON")
    te.add_argument("--outer", type=float, nargs=4, required=True, metavar="L",
                    help="4 outer levels: u=0, v=0, u=1, v=1 edges (gl_TessLevelOuter order)")
    te.add_argument("--inner", type=float, nargs=2, required=True, metavar="L", help="2 inner levels: along u, v")
    te.add_argument("--spacing", choices=list(SPACINGS), default=SPACINGS[0])
    te.add_argument("--out", default="out/tessellate")
    te.set_defaults(func=_cmd_tessellate)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (ValueError, TypeError, FileNotFoundError, IsADirectoryError, PermissionError) as e:
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        print(f"terrainwarp: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("terrainwarp: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())



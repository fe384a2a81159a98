#!/usr/bin/env bash
# The whole GPU check of terrainwarp, on the lent GPU machine (one H200, 16 cores, Python 3.12, no network):
# sets up from what the call carried, then, each stage time-boxed under one 7.5-minute deadline, writes to OUTDIR
#   cuda_parity.md        cpu vs cuda:0, every kernel module's outputs (benchmarks/cuda_parity.py)
#   gpu_frame.md          bench_terrain_frame's frames: CUDA, the 16 CPU cores, NVIDIA's OpenGL (bench_gpu_frame.py)
#   tests.log             the device-parametrised tests on cuda:0 (pytest -k cuda)
#   cuda_parity_nofma.md  the parity with fuse_fp=False in every module (is a float difference FMA contraction?)
#   calibration_gpu.md    the GPU-cost model fitted to NVIDIA's GL frame times (benchmarks/gpu_calibrate.py), where
#                         terrainwarp.experiments.calibrate exists
#   codegen.md            every module compiled for sm_90 by NVRTC
#   README.md             what ran, how long, what failed; run.log: everything printed
#
# How a session with a GPU runs it (BENCHMARKS.md, "GPU check"): `bash scripts/gpu-pack.sh` here first (builds the
# git-ignored .gpu/: warp-lang, moderngl, glcontext and the GL loader .debs, ~88 MiB in two parts, since one call
# carries 64 MiB), then two device calls, the second at once after the first (the machine stays warm 30 s):
#   run(command="bash scripts/gpu-check.sh --stage", carry=[".gpu/1"], timeout_s=120)
#   run(command="bash scripts/gpu-check.sh $OUT", carry=[".gpu/2"], timeout_s=540)
# then copy $OUT's *.md but README.md into benchmarks/results/ and run benchmarks/collect.py.
#
# Here, without a GPU: `bash scripts/gpu-check.sh --cpu-only [--quick] OUTDIR` runs the same stages on a copy of
# the working tree with the CPU standing in for cuda:0 (parity CPU x all threads vs CPU x 1 thread), Warp from
# .gpu/ when it is packed (else from .venv; GPU_CHECK_PAYLOAD=0: always), the packages the GPU machine lacks
# hidden, and no .deb unpacked.
set -uo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
MODE=device QUICK=0 OUTDIR=
for a in "$@"; do
  case $a in
    --stage) MODE=stage ;;
    --cpu-only) MODE=cpu ;;
    --quick) QUICK=1 ;;
    -*) echo "gpu-check: unknown option $a" >&2; exit 2 ;;
    *) OUTDIR=$a ;;
  esac
done
STASH=/tmp/terrainwarp-gpu  # where the staging call leaves part 1 (outside the repository copy)

if [ "$MODE" = stage ]; then  # the first device call: keep part 1 for the second, and look at the machine
  [ -f "$ROOT/.gpu/1/payload.1" ] || { echo "gpu-check --stage: .gpu/1 was not carried (carry=[\".gpu/1\"])" >&2; exit 2; }
  mkdir -p "$STASH" && cp "$ROOT/.gpu/1/payload.1" "$ROOT/.gpu/1/MANIFEST" "$STASH/" || exit 1
  echo "staged: $(du -h "$STASH/payload.1" | cut -f1) in $STASH; now, at once: bash scripts/gpu-check.sh \$OUT with .gpu/2"
  nvidia-smi -L 2>&1 | head -2; python3 --version; nproc; df -h /tmp | tail -1
  exit 0
fi
[ -n "$OUTDIR" ] || { echo "usage: gpu-check.sh [--cpu-only] [--quick] OUTDIR | --stage" >&2; exit 2; }
mkdir -p "$OUTDIR" && OUTDIR=$(cd "$OUTDIR" && pwd)
rm -f "$OUTDIR/run.log"

check() {
T0=$(date +%s)
DEADLINE=$(( T0 + 450 ))  # 7.5 minutes for everything: the device call's limit leaves a minute to spare
WORK=/tmp/terrainwarp-check
rm -rf "$WORK" && mkdir -p "$WORK"
SUMMARY=()
note() { SUMMARY+=("$1"); echo "== $1"; }

# -- set-up: the payload (warp-lang etc.), the GL loaders, the source tree ------------------------------------
part1=$STASH/payload.1
[ -f "$ROOT/.gpu/1/payload.1" ] && part1=$ROOT/.gpu/1/payload.1
part2=$ROOT/.gpu/2/payload.2
SITE=
if [ -f "$part2" ] && [ -f "$part1" ] && { [ "$MODE" = device ] || [ "${GPU_CHECK_PAYLOAD:-1}" != 0 ]; }; then
  want=$(sed -n 's/^sha256: //p' "$ROOT/.gpu/2/MANIFEST")
  have=$(cat "$part1" "$part2" | sha256sum | cut -d' ' -f1)
  if [ "$want" != "$have" ]; then
    echo "gpu-check: the two parts do not make the packed payload (sha256 $have, expected $want): part 1 is from" \
         "another pack; stage .gpu/1 again" >&2; exit 3
  fi
  mkdir -p "$WORK/pkg"
  cat "$part1" "$part2" | python3 -c "import sys, tarfile; tarfile.open(fileobj=sys.stdin.buffer, mode='r|xz').extractall('$WORK/pkg', filter='tar')" \
    || { echo "gpu-check: could not unpack the payload" >&2; exit 3; }
  SITE=$WORK/pkg/site
  note "set-up: payload unpacked ($(sed -n 's/^contents: //p' "$ROOT/.gpu/2/MANIFEST")), $(( $(date +%s) - T0 )) s"
elif [ "$MODE" = device ]; then
  [ -f "$part2" ] || echo "gpu-check: .gpu/2 was not carried (carry=[\".gpu/2\"])" >&2
  [ -f "$part1" ] || echo "gpu-check: part 1 is not on this machine: run the --stage call with .gpu/1 first, and" \
                         "this one at once after it (a machine left idle 30 s goes back, with the stash)" >&2
  exit 3
else
  note "set-up: no .gpu/ payload (bash scripts/gpu-pack.sh makes it): Warp from .venv"
fi

if [ "$MODE" = device ]; then
  PY=(python3)
  for f in "$WORK"/pkg/gl/*.deb; do dpkg -x "$f" /; done
  ldconfig
  vendor=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
  [ -f "$vendor" ] && export __EGL_VENDOR_LIBRARY_FILENAMES=$vendor
  SRC=$ROOT  # the device's copy of the working tree, given back with the machine
  DEV=cuda:0 K=cuda
  export PYTHONPATH=$SRC:$SITE
else
  # a copy of what a device call carries (tracked and untracked-not-ignored files), and a python that sees only
  # PYTHONPATH: .venv's packages, less those the GPU machine lacks; Warp from the payload when there is one
  VENV=$("$ROOT/.venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
  PY=("$ROOT/.venv/bin/python" -S)
  SRC=$WORK/repo
  mkdir -p "$SRC" && (cd "$ROOT" && git ls-files -z -co --exclude-standard | xargs -0 cp --parents -t "$SRC" 2>/dev/null)
  mkdir -p "$WORK/block" "$WORK/warp-only"
  for m in pyvista vtk vtkmodules rasterio OpenImageIO pymartini pydelatin dask distributed; do
    mkdir -p "$WORK/block/$m" && echo "raise ImportError('$m: not on the GPU machine (gpu-check --cpu-only)')" \
      > "$WORK/block/$m/__init__.py"
  done
  [ -n "$SITE" ] && ln -s "$SITE/warp" "$WORK/warp-only/warp"
  DEV=cpu K=cpu
  export PYTHONPATH=$WORK/block:$SRC:$WORK/warp-only:$VENV
fi
rm -rf "$SRC/terrainwarp/kernels" && cp -r "$SRC/kernels" "$SRC/terrainwarp/kernels"  # as the wheel lays it out
export MPLBACKEND=Agg XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONUNBUFFERED=1 PYTHONDONTWRITEBYTECODE=1
cd "$SRC" || exit 1
"${PY[@]}" - <<'EOF' || { echo "gpu-check: terrainwarp or Warp does not import" >&2; exit 4; }
import sys, warp as wp, numpy as np, terrainwarp
wp.init()
print(f"python {sys.version.split()[0]}, numpy {np.__version__}, warp {wp.__version__} from {wp.__file__}, "
      f"terrainwarp from {terrainwarp.__file__}; devices: {[str(d) for d in wp.get_devices()]}")
EOF
if [ "$MODE" = device ]; then
  nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm,clocks.max.sm --format=csv,noheader
fi

# -- stages -----------------------------------------------------------------------------------------------------
stage() {  # stage NAME LIMIT_S COMMAND...: run it for at most LIMIT_S (and never past the deadline)
  local name=$1 limit=$2; shift 2
  local left=$(( DEADLINE - $(date +%s) ))
  (( limit > left )) && limit=$left
  if (( limit < 15 )); then note "$name: skipped (no time left)"; return; fi
  echo "== $name (at most $limit s): $*"
  local t=$(date +%s)
  timeout --kill-after=5 "$limit" "$@"
  local rc=$? dt=$(( $(date +%s) - t ))
  case $rc in
    0) note "$name: ok, $dt s" ;;
    124|137) note "$name: TIMED OUT after $dt s (limit $limit s)" ;;
    *) note "$name: FAILED (exit $rc), $dt s" ;;
  esac
}
if (( QUICK )); then SIZE=tiny FRAME=(--quick --reps 1); else SIZE=full FRAME=(--reps 3); fi
if [ "$MODE" = device ]; then B=(--b cuda:0); else B=(--b cpu --b-threads 1); fi
TESTS=(tests/test_launches.py tests/kernels/test_tessellator.py tests/kernels/test_raster.py tests/kernels/test_counters.py
       tests/lod/test_lod.py
       tests/surface/test_normals.py tests/surface/test_curvature.py tests/lod/test_polytree.py
       tests/lod/test_bintree.py tests/lod/test_cdlod.py tests/lod/test_clipmaps.py tests/lod/test_chunked.py
       tests/measure/test_sample_error.py tests/diff/test_ops.py tests/diff/test_interpolate.py)
(( QUICK )) && TESTS=(tests/test_launches.py tests/kernels/test_tessellator.py tests/lod/test_lod.py)

if [ "$MODE" = device ]; then LOAD=cpu,cuda:0; else LOAD=cpu; fi
# every module compiled in parallel, then the parity's own variants (a module compiled at its first launch in a
# process can hash differently from the module loaded whole) by tiny runs: the stages after it compile little
WARM="${PY[*]} benchmarks/cuda_parity.py ${B[*]} --size tiny --out $WORK/warm > /dev/null"
(( QUICK )) && WARM=true  # the quick parity is the tiny one
stage "compile (Warp's cache, $LOAD)" 120 bash -c "${PY[*]} tests/cuda_codegen.py --load $LOAD --workers $(nproc) && \
  $WARM && ${WARM/--size tiny/--size tiny --fuse-fp off}"
stage "parity (fuse_fp on)" 100 "${PY[@]}" benchmarks/cuda_parity.py "${B[@]}" --size "$SIZE" --out "$OUTDIR"
stage "frame timings" 120 "${PY[@]}" benchmarks/bench_gpu_frame.py --device "$DEV" "${FRAME[@]}" --out "$OUTDIR"
stage "device tests (-k $K)" 150 bash -c "${PY[*]} -m pytest -q -p no:cacheprovider --timeout 90 -k '$K or launches' \
  ${TESTS[*]} > '$OUTDIR/tests.log' 2>&1; rc=\$?; tail -4 '$OUTDIR/tests.log'; exit \$rc"
stage "parity (fuse_fp off)" 100 "${PY[@]}" benchmarks/cuda_parity.py "${B[@]}" --size "$SIZE" --fuse-fp off --out "$OUTDIR"
if "${PY[@]}" -c "import terrainwarp.experiments.calibrate" >/dev/null 2>&1; then
  (( QUICK )) && CAL=(--frames-per-family 2 --reps 1) || CAL=(--frames-per-family 20 --reps 3)
  stage "calibration (GL)" 75 "${PY[@]}" benchmarks/gpu_calibrate.py "${CAL[@]}" --out "$OUTDIR"
else
  note "calibration: skipped (no terrainwarp.experiments.calibrate in this checkout: the GPU-cost issue has not landed)"
fi
stage "codegen (sm_90 PTX)" 60 bash -c "${PY[*]} tests/cuda_codegen.py --workers $(nproc) > '$OUTDIR/codegen.md'"

# -- summary ----------------------------------------------------------------------------------------------------
{
  echo "# terrainwarp GPU check ($MODE$( (( QUICK )) && echo ', quick'))"
  echo
  echo "$(date -u +%Y-%m-%dT%H:%MZ), $(( $(date +%s) - T0 )) s in all, device $DEV, $(nproc) cores."
  echo
  for s in "${SUMMARY[@]}"; do echo "- $s"; done
  echo
  echo "Next: copy the tables (cuda_parity*.md, gpu_frame.md) into benchmarks/results/, run benchmarks/collect.py."
} > "$OUTDIR/README.md"
cat "$OUTDIR/README.md"
case "${SUMMARY[*]}" in *FAILED*|*TIMED*) return 1 ;; esac
}

check 2>&1 | tee "$OUTDIR/run.log"
exit "${PIPESTATUS[0]}"

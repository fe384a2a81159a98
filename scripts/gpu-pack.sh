#!/usr/bin/env bash
# Builds what scripts/gpu-check.sh needs on the lent GPU machine (one NVIDIA H200, Python 3.12 with numpy,
# JAX, optax, pytest, xxhash..., no warp-lang, no network), into the git-ignored folder .gpu/:
#
#   .gpu/1/payload.1   .gpu/2/payload.2   one xz tarball (tar | xz --x86 -9e), cut in two
#   .gpu/*/MANIFEST    the tarball's sha256, its parts' sizes, the versions inside
#
# The tarball holds a site-packages folder (site/) with warp-lang (its wheel, less warp/examples and
# warp/tests), moderngl and glcontext (CPython 3.12 manylinux wheels; the image has neither), and gl/ with
# Debian's GL loader packages (libegl1 libgl1 libglvnd0 libopengl0 libglx0 libgles2) for OpenGL through
# EGL on NVIDIA's driver. Versions are those of this checkout's .venv.
#
# Why two parts: a device call carries at most 64 MiB (working tree included), and warp-lang alone is a
# 149 MB wheel (warp.so: 299 MB, NVRTC and the CUDA kernels of 7 architectures; warp-clang.so: 69 MB, the
# CPU backend); xz with the x86 filter brings everything to about 100 MB. So one call stages part 1 and
# the next, on the same warm machine, brings part 2 and runs the check (BENCHMARKS.md, "GPU check").
#
#   bash scripts/gpu-pack.sh          # ~5-8 min on 2 cores (xz -9e); reuses .gpu/ when nothing changed
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
PY=${PY:-$ROOT/.venv/bin/python}
OUT=$ROOT/.gpu
LIMIT_MIB=64  # what one device call carries, the working tree included
PYVER=3.12    # the GPU machine's python3 (KINDS.md: 3.12.3)

[ -x "$PY" ] || { echo "gpu-pack: $PY missing (make setup first)" >&2; exit 2; }
ver() { "$PY" -c "import importlib.metadata as m; print(m.version('$1'))"; }
WARP=$(ver warp-lang) MGL=$(ver moderngl) GLC=$(ver glcontext)
DEBS="libegl1 libgl1 libglvnd0 libopengl0 libglx0 libgles2"
KEY="warp-lang==$WARP moderngl==$MGL glcontext==$GLC cp${PYVER/./} | $DEBS"
if [ -f "$OUT/1/MANIFEST" ] && [ -f "$OUT/2/MANIFEST" ] && grep -qxF "contents: $KEY" "$OUT/1/MANIFEST" \
   && grep -qxF "contents: $KEY" "$OUT/2/MANIFEST"; then
  echo "gpu-pack: .gpu/ is up to date ($KEY)"; exit 0
fi

WORK=$(mktemp -d /tmp/terrainwarp-gpu-pack.XXXXXX)
trap 'rm -rf "$WORK"' EXIT
mkdir -p "$WORK/whl" "$WORK/pkg/site" "$WORK/pkg/gl"
echo "gpu-pack: downloading $KEY"
PLAT=()
for p in manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_17_x86_64 manylinux2014_x86_64 manylinux1_x86_64; do
  PLAT+=(--platform "$p")
done
"$PY" -m pip download -q --disable-pip-version-check --no-deps --only-binary=:all: --python-version "$PYVER" \
  --implementation cp "${PLAT[@]}" -d "$WORK/whl" "warp-lang==$WARP" "moderngl==$MGL" "glcontext==$GLC" \
  2>&1 | grep -v "^WARNING: Location" || true
n=$(ls "$WORK"/whl/*.whl | wc -l)
[ "$n" -eq 3 ] || { echo "gpu-pack: expected 3 wheels, got $n" >&2; exit 1; }
for w in "$WORK"/whl/*.whl; do
  case $w in *warp_lang*) x=(-x "warp/examples/*" "warp/tests/*") ;; *) x=() ;; esac
  unzip -q -o "$w" -d "$WORK/pkg/site" "${x[@]}"
done

# the GL loaders, as the device README downloads them (amd64 lists of their own, in /tmp)
A=(-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64)
mkdir -p /tmp/amd64/partial
apt-get "${A[@]}" update -qq >/dev/null
(cd "$WORK/pkg/gl" && apt-get "${A[@]}" download $DEBS 2>&1 | grep -v "unsandboxed" || true)
[ "$(ls "$WORK"/pkg/gl/*.deb | wc -l)" -eq 6 ] || { echo "gpu-pack: GL packages missing" >&2; exit 1; }

echo "gpu-pack: compressing $(du -sh "$WORK/pkg" | cut -f1) (xz --x86 -9e; minutes)"
tar -C "$WORK/pkg" -cf - site gl | xz -T2 --x86 --lzma2=preset=9e -c > "$WORK/payload.tar.xz"
SIZE=$(stat -c %s "$WORK/payload.tar.xz")
SUM=$(sha256sum "$WORK/payload.tar.xz" | cut -d' ' -f1)

# what travels besides a part: tracked and untracked-not-ignored files (git ls-files -co --exclude-standard)
TREE=$(git ls-files -z -co --exclude-standard | xargs -0 stat -c %s 2>/dev/null | awk '{s+=$1} END {print s+0}')
ROOM=$(( LIMIT_MIB * 1048576 - TREE - 1048576 ))  # 1 MiB to spare
HALF=$(( (SIZE + 1) / 2 ))
[ "$HALF" -le "$ROOM" ] || { echo "gpu-pack: $SIZE bytes do not fit in two calls beside a $TREE-byte tree" >&2; exit 1; }
rm -rf "$OUT"
mkdir -p "$OUT/1" "$OUT/2"
head -c "$HALF" "$WORK/payload.tar.xz" > "$OUT/1/payload.1"
tail -c +"$(( HALF + 1 ))" "$WORK/payload.tar.xz" > "$OUT/2/payload.2"
for i in 1 2; do
  cat > "$OUT/$i/MANIFEST" <<EOF
contents: $KEY
sha256: $SUM
bytes: $SIZE
part1: $HALF
part2: $(( SIZE - HALF ))
made: $(date -u +%Y-%m-%dT%H:%MZ) by scripts/gpu-pack.sh
EOF
done
echo "gpu-pack: .gpu/1 and .gpu/2, $(( HALF >> 20 )) + $(( (SIZE - HALF) >> 20 )) MiB (tree: $(( TREE >> 20 )) MiB)"

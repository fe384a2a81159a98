#!/usr/bin/env bash
# Installs the Debian packages terrainwarp's optional features use, only when missing:
#   Mesa's EGL + llvmpipe (off-screen OpenGL for pyvista pictures and the OpenGL oracle tests).
# Never fails the build: a feature that cannot get its package says so when it is used.
set -u
need=()
have_lib() { ldconfig -p 2>/dev/null | grep -q "$1"; }
have_lib 'libEGL.so.1' || need+=(libegl1)
have_lib 'libEGL_mesa.so.0' || need+=(libegl-mesa0)
[ -e /usr/lib/x86_64-linux-gnu/dri/swrast_dri.so ] || [ -e /usr/lib/aarch64-linux-gnu/dri/swrast_dri.so ] || need+=(libgl1-mesa-dri)
have_lib 'libGL.so.1' || need+=(libgl1)
have_lib 'libXrender.so.1' || need+=(libxrender1)
if [ ${#need[@]} -eq 0 ]; then exit 0; fi
if [ "$(id -u)" -ne 0 ] || ! command -v apt-get >/dev/null 2>&1; then
  echo "terrainwarp: optional system packages missing (${need[*]}); off-screen OpenGL features will be unavailable." >&2
  exit 0
fi
echo "terrainwarp: installing system packages: ${need[*]}" >&2
export DEBIAN_FRONTEND=noninteractive
apt-get update -qq >/dev/null 2>&1 || true
apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null 2>&1 \
  || echo "terrainwarp: could not install ${need[*]}; off-screen OpenGL features will be unavailable." >&2
exit 0

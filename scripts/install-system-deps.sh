#!/usr/bin/env bash
# Debian packages tissuecast needs: CalculiX (cross-checks, second FEM backend),
# SuiteSparse headers + OpenBLAS (scikit-sparse CHOLMOD), GL/EGL libraries (gmsh, VTK renders),
# the official OpenIGTLink C++ library and a C++ compiler (the interoperability test builds a client),
# and chromium (the report's headless-browser test: the page loads, the 3D view draws).
# Skips apt when everything is already there; needs root (or sudo) otherwise.
set -euo pipefail
pkgs=(calculix-ccx libsuitesparse-dev libopenblas0-pthread libopenblas-dev libglu1-mesa libxrender1
      libxcursor1 libxft2 libxinerama1 libgl1 libegl1 libopenigtlink-dev g++ chromium)
missing=()
for p in "${pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
[ ${#missing[@]} -eq 0 ] && exit 0
if ! command -v apt-get >/dev/null; then
  echo "install-system-deps: apt-get not found; install these yourself: ${missing[*]}" >&2
  exit 0
fi
SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
$SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"

#!/usr/bin/env bash
# Build the Python bindings of CLIPPER and TEASER++ into the project's .venv from local source trees.
#
# Neither is on PyPI and both CMake projects download their dependencies at configure time; this script
# points every such download at a local copy instead (FETCHCONTENT_SOURCE_DIR_<NAME>), so that the build
# needs no network. The sources are not part of the repository: pass their paths.
#
# Usage:
#   tools/build_peers.sh [--clipper DIR] [--teaser DIR] --pmc DIR [--spectra DIR] [--tinyply DIR]
#                        [--pybind11-src DIR] [--python PY] [--build DIR] [--jobs N]
#
#   --clipper DIR       mit-acl/clipper source tree (builds the module `clipperpy`)
#   --teaser DIR        MIT-SPARK/TEASER-plusplus source tree (builds `teaserpp_python`);
#                       needs --spectra (jingnanshi/spectra) and --tinyply (ddiakopoulos/tinyply)
#   --pmc DIR           jingnanshi/pmc source tree (the max-clique solver both use)
#   --pybind11-src DIR  a pybind11 source tree (CLIPPER adds it as a subproject); default: the sdist of the
#                       pybind11 installed in the venv, fetched with `pip download --no-binary :all:`
#   --python PY         the venv's interpreter (default: .venv/bin/python beside this script's parent)
#   --build DIR         scratch build directory (default: a new temporary directory)
#   --jobs N            parallel compile jobs (default: the number of cores; on a shared machine give 1)
#
# Needs cmake >= 3.14, a C++14 compiler, Eigen 3 (Debian: apt-get install libeigen3-dev) and pybind11 in
# the venv (pip install pybind11). See docs/peers.md for the versions this was run with.
set -euo pipefail

here=$(cd "$(dirname "$0")/.." && pwd)
py="$here/.venv/bin/python"
clipper="" teaser="" pmc="" spectra="" tinyply="" pyb_src="" build="" jobs=""
while [[ $# -gt 0 ]]; do
  case "$1" in
    --clipper) clipper=$(realpath "$2"); shift 2 ;;
    --teaser) teaser=$(realpath "$2"); shift 2 ;;
    --pmc) pmc=$(realpath "$2"); shift 2 ;;
    --spectra) spectra=$(realpath "$2"); shift 2 ;;
    --tinyply) tinyply=$(realpath "$2"); shift 2 ;;
    --pybind11-src) pyb_src=$(realpath "$2"); shift 2 ;;
    --python) py="$2"; shift 2 ;;
    --build) build=$(realpath -m "$2"); shift 2 ;;
    --jobs) jobs="$2"; shift 2 ;;
    -h|--help) sed -n '2,23p' "$0"; exit 0 ;;
    *) echo "build_peers.sh: unknown argument $1 (see --help)" >&2; exit 2 ;;
  esac
done
[[ -n "$clipper$teaser" ]] || { echo "build_peers.sh: give --clipper DIR and/or --teaser DIR" >&2; exit 2; }
[[ -n "$pmc" && -f "$pmc/CMakeLists.txt" ]] || { echo "build_peers.sh: --pmc must be a pmc source tree" >&2; exit 2; }
[[ -x "$py" ]] || { echo "build_peers.sh: no interpreter at $py (use --python)" >&2; exit 2; }
"$py" -c "import pybind11" 2>/dev/null || { echo "build_peers.sh: pip install pybind11 into the venv first" >&2; exit 2; }
build=${build:-$(mktemp -d)}
mkdir -p "$build"
site=$("$py" -c "import sysconfig; print(sysconfig.get_paths()['purelib'])")
pyb_dir=$("$py" -m pybind11 --cmakedir)
jobs=${jobs:-$(nproc 2>/dev/null || echo 2)}
common=(-DCMAKE_BUILD_TYPE=Release -DPython_EXECUTABLE="$py" -DPYTHON_EXECUTABLE="$py" -DPMC_BUILD_SHARED=OFF
        -DFETCHCONTENT_FULLY_DISCONNECTED=ON -DFETCHCONTENT_SOURCE_DIR_PMC="$pmc")

if [[ -n "$clipper" ]]; then
  if [[ -z "$pyb_src" ]]; then
    ver=$("$py" -c "import pybind11; print(pybind11.__version__)")
    "$py" -m pip download --no-binary :all: --no-deps -d "$build/dl" "pybind11==$ver" >/dev/null
    tar xzf "$build/dl/pybind11-$ver.tar.gz" -C "$build"
    pyb_src="$build/pybind11-$ver"
  fi
  # SCS (only for CLIPPER's SDP relaxation, unused here) is switched off; libclipper.so is shipped inside
  # the package directory and found there through $ORIGIN.
  cmake -S "$clipper" -B "$build/clipper" "${common[@]}" -DFETCHCONTENT_SOURCE_DIR_PYBIND11="$pyb_src" \
    -DCLIPPER_BUILD_BINDINGS_PYTHON=ON -DCLIPPER_ENABLE_SCS_SDR=OFF -DCLIPPER_ENABLE_MAXCLIQUE=ON \
    -DCLIPPER_BUILD_TESTS=OFF -DCLIPPER_BUILD_BENCHMARKS=OFF -DCMAKE_BUILD_RPATH='$ORIGIN'
  cmake --build "$build/clipper" --target py_clipper -j "$jobs"
  rm -rf "$site/clipperpy"
  cp -r "$build/clipper/bindings/python/clipperpy" "$site/clipperpy"
  cp -P "$build/clipper"/libclipper.so* "$site/clipperpy/"
  "$py" -c "import clipperpy; print('clipperpy', clipperpy.__version__, 'installed')"
fi

if [[ -n "$teaser" ]]; then
  [[ -d "$spectra" && -d "$tinyply" ]] || { echo "build_peers.sh: --teaser needs --spectra and --tinyply" >&2; exit 2; }
  # Static libraries so that the one extension module carries everything; tests and docs would download more.
  cmake -S "$teaser" -B "$build/teaser" "${common[@]}" -Dpybind11_DIR="$pyb_dir" \
    -DFETCHCONTENT_SOURCE_DIR_SPECTRA="$spectra" -DFETCHCONTENT_SOURCE_DIR_TINYPLY="$tinyply" \
    -DBUILD_PYTHON_BINDINGS=ON -DBUILD_SHARED_LIBS=OFF -DBUILD_TESTS=OFF -DBUILD_DOC=OFF \
    -DBUILD_TEASER_FPFH=OFF -DENABLE_DIAGNOSTIC_PRINT=OFF
  cmake --build "$build/teaser" --target teaserpp_python -j "$jobs"
  rm -rf "$site/teaserpp_python"
  mkdir -p "$site/teaserpp_python"
  cp "$teaser"/python/teaserpp_python/__init__.py "$build/teaser"/python/teaserpp_python/_teaserpp*.so \
    "$site/teaserpp_python/"
  "$py" -c "import teaserpp_python; print('teaserpp_python installed')"
fi

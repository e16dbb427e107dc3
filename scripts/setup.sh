#!/usr/bin/env bash
# scripts/setup.sh: installs the Debian/Ubuntu packages scandyn's build and tests need.
#
# Idempotent: asks dpkg first and calls apt-get only for what is missing, so a
# second run takes well under a second. Uses sudo only when not root.
# CUDA (nvcc) is not installed here: it is optional, and CMake turns the CUDA
# backend on by itself when it finds nvcc (PATH, $CUDACXX or /usr/local/cuda/bin).
set -euo pipefail

packages=(
  cmake            # >= 3.20
  ninja-build
  g++              # C++17; brings libgomp (OpenMP for GCC)
  libgomp1
  libeigen3-dev
  liburdfdom-dev   # URDF parsing (pulls console_bridge, tinyxml, urdfdom_headers)
  nlohmann-json3-dev  # scene files (JSON), header-only
  libgtest-dev
  libbenchmark-dev
  python3          # scripts/
  python3-venv     # scripts/setup_python.sh (.venv with numpy and Pinocchio)
  python3-dev      # the Python package's extension module (Python.h; docs/python.md)
  clang            # scripts/fuzz.sh: libFuzzer targets (brings libclang-rt, the fuzzer runtime)
  libsuitesparse-dev  # optional: CHOLMOD for the factor-graph solvers (docs/factor-graph.md)
  libmetis-dev        # optional: METIS nested dissection for CHOLMOD
)

missing=()
for p in "${packages[@]}"; do
  status=$(dpkg-query -W -f='${db:Status-Status}' "$p" 2>/dev/null || true)
  [[ "$status" == installed ]] || missing+=("$p")
done

if ((${#missing[@]} == 0)); then
  echo "setup.sh: all ${#packages[@]} packages already installed"
  exit 0
fi

echo "setup.sh: installing ${missing[*]}"
if ((EUID == 0)); then
  SUDO=()
elif command -v sudo >/dev/null 2>&1; then
  SUDO=(sudo)
else
  echo "setup.sh: not root and no sudo; install these packages first: ${missing[*]}" >&2
  exit 1
fi
export DEBIAN_FRONTEND=noninteractive
${SUDO[@]+"${SUDO[@]}"} env DEBIAN_FRONTEND=noninteractive apt-get update -q
${SUDO[@]+"${SUDO[@]}"} env DEBIAN_FRONTEND=noninteractive \
  apt-get install -y -q --no-install-recommends "${missing[@]}"
echo "setup.sh: done"

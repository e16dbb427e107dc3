#!/usr/bin/env bash
# bench/compare/fetch_wheels.sh: fetch, on a networked machine, the wheels that the GPU
# comparison (bench/compare/gpu.sh) installs offline, into .whl/ (git-ignored: add /.whl/ to
# .git/info/exclude). Pinned versions, CPython 3.12, manylinux x86-64, no dependency
# resolution (--no-deps): every package the GPU machine's image lacks is named here.
#
#   bench/compare/fetch_wheels.sh [--with-warp]
#
# Default set (36 MiB, mujoco's wheel 25 of it; the GPU machine's working tree may carry
# 64 MiB in all, .deps and .models take about 10):
#   mujoco 3.17.0, mujoco-mjx 3.17.0 (MJX, JAX implementation; JAX 0.11.2 with CUDA 13 is in
#   the image), trimesh (imported by MJX), grid-rbd 0.6.0 and what it imports beyond the
#   image (beautifulsoup4, soupsieve, platformdirs). mujoco's declared glfw and PyOpenGL are
#   left out: nothing here imports them (3.4 MiB).
# --with-warp adds warp-lang 1.18.0 and mujoco-warp 3.17.0 (MuJoCo Warp). warp-lang's wheel
#   alone is 142 MiB (every release since 1.6 is 120-159 MiB: warp.so links NVRTC and
#   libmathdx statically), so it cannot travel within the 64 MiB limit; on a machine with
#   network or without that limit, use this flag (or pip install the same pins).
# The image already has numpy, scipy, jax, jaxlib, absl-py, etils, fsspec, zipp,
# typing-extensions, sympy, lxml and torch (KINDS.md's package list).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."

with_warp=0
[[ "${1:-}" == --with-warp ]] && with_warp=1

wheels=(
  mujoco==3.17.0
  mujoco-mjx==3.17.0
  trimesh==5.2.0
  grid-rbd==0.6.0
  beautifulsoup4==4.15.0
  soupsieve==4.1.2
  platformdirs==4.14.7
)
if ((with_warp)); then
  wheels+=(warp-lang==1.18.0 mujoco-warp==3.17.0)
fi

plat=()
for p in manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_17_x86_64 manylinux2014_x86_64 \
         manylinux1_x86_64 manylinux_2_31_x86_64 manylinux_2_34_x86_64 manylinux_2_35_x86_64; do
  plat+=(--platform "$p")
done
mkdir -p .whl
grep -qx '/.whl/' .git/info/exclude 2>/dev/null || grep -qx '/.whl/' "$(git rev-parse --git-common-dir)/info/exclude" 2>/dev/null ||
  echo "fetch_wheels.sh: note: add /.whl/ to $(git rev-parse --git-common-dir)/info/exclude so git ignores it" >&2
for w in "${wheels[@]}"; do
  python3 -m pip download -q --disable-pip-version-check --no-deps --only-binary=:all: --python-version 3.12 \
    --implementation cp "${plat[@]}" -d .whl "$w"
done
# one version of each package only (an older download would stop the install)
ls .whl
du -ch .whl/*.whl | tail -n1
total=$(du -cb .whl/*.whl | tail -n1 | cut -f1)
if ((total > 50 * 1024 * 1024)); then
  echo "fetch_wheels.sh: warning: .whl/ holds $((total / 1024 / 1024)) MiB: more than the GPU machine's carry limit allows with the other carried folders" >&2
fi

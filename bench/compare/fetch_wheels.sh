#!/usr/bin/env bash
# bench/compare/fetch_wheels.sh: fetch, on a networked machine, the wheels that the GPU
# comparison (bench/compare/gpu.sh) installs offline, into .whl/ (git-ignored: add /.whl/ to
# .git/info/exclude). Pinned versions, CPython 3.12, manylinux x86-64, no dependency
# resolution (--no-deps): every package the GPU machine's image lacks is named here.
#
#   bench/compare/fetch_wheels.sh [--with-warp]
#
# Default set (36 MiB, mujoco's wheel 25 of it; the GPU machine's working tree may carry
# 64 MiB in all, .deps takes about 10):
#   mujoco 3.17.0, mujoco-mjx 3.17.0 (MJX, JAX implementation; JAX 0.11.2 with CUDA 13 is in
#   the image), trimesh (imported by MJX), grid-rbd 0.6.0 and what it imports beyond the
#   image (beautifulsoup4, soupsieve, platformdirs). mujoco's declared glfw and PyOpenGL are
#   left out: nothing here imports them (3.4 MiB).
# --with-warp also fetches warp-lang 1.18.0 and mujoco-warp 3.17.0 (MuJoCo Warp) into
#   .whl-warp/ (git-ignored like .whl/). warp-lang's wheel alone is 142 MiB (every release
#   since 1.6 is 120-159 MiB: warp.so links NVRTC and libmathdx statically), more than one
#   device call may carry (64 MiB), so it is cut into parts of 48 MiB, one folder per call:
#   .whl-warp/part1, part2, ... each with the parts' MANIFEST (sha256 of every whole wheel
#   and of every part). On the GPU machine, one call per folder stages it:
#     carry [".whl-warp/partK"], command: bench/compare/stage_wheels.sh .whl-warp/partK
#   (the machine keeps /tmp/whl-stage between calls while it stays warm); gpu.sh then
#   joins complete wheels from /tmp/whl-stage, checks their sha256 and installs them with
#   .whl/. A wheel with a part missing or a wrong checksum is named and left out.
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
warp_wheels=(warp-lang==1.18.0 mujoco-warp==3.17.0)

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

if ((with_warp)); then
  rm -rf .whl-warp && mkdir -p .whl-warp/fetch
  mkdir -p "$(git rev-parse --git-common-dir)/info"
  grep -qx '/.whl-warp/' "$(git rev-parse --git-common-dir)/info/exclude" 2>/dev/null ||
    echo '/.whl-warp/' >>"$(git rev-parse --git-common-dir)/info/exclude"
  for w in "${warp_wheels[@]}"; do
    python3 -m pip download -q --disable-pip-version-check --no-deps --only-binary=:all: --python-version 3.12 \
      --implementation cp "${plat[@]}" -d .whl-warp/fetch "$w"
  done
  (
    cd .whl-warp/fetch
    for f in *.whl; do
      split -b 48M -d -a 2 "$f" "$f.part"
      rm "$f"
    done
    # MANIFEST lines: "wheel <sha256> <name> <parts>" and "part <sha256> <file>"
    {
      for f in $(ls *.part* | sed 's/\.part[0-9]*$//' | sort -u); do
        n=$(ls "$f".part* | wc -l)
        echo "wheel $(cat "$f".part* | sha256sum | cut -d' ' -f1) $f $n"
      done
      for p in *.part*; do echo "part $(sha256sum "$p" | cut -d' ' -f1) $p"; done
    } >MANIFEST
  )
  # folders of at most 50 MiB, one per device call
  k=1 size=0
  mkdir -p .whl-warp/part1
  for p in $(cd .whl-warp/fetch && ls -S *.part*); do
    s=$(stat -c %s ".whl-warp/fetch/$p")
    if ((size > 0 && size + s > 50 * 1024 * 1024)); then k=$((k + 1)) size=0; mkdir -p ".whl-warp/part$k"; fi
    mv ".whl-warp/fetch/$p" ".whl-warp/part$k/"
    size=$((size + s))
  done
  for d in .whl-warp/part*; do cp .whl-warp/fetch/MANIFEST "$d/"; done
  rm -rf .whl-warp/fetch
  echo "fetch_wheels.sh: MuJoCo Warp in $(ls -d .whl-warp/part* | wc -l) folders (one device call each):"
  du -sh .whl-warp/part*
fi

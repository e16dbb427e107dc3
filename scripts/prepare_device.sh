#!/usr/bin/env bash
# scripts/prepare_device.sh: stages, on this (networked) machine, what the GPU
# machine lacks, so that scripts/gpu_check.sh can run there offline.
#
#   .deps/debs/   the .deb files of urdfdom and its dependencies, and of SuiteSparse's
#                 CHOLMOD and METIS (apt-get download)
#   .deps/root/   the same packages unpacked (dpkg -x); gpu_check.sh points
#                 CMAKE_PREFIX_PATH at .deps/root/usr and LD_LIBRARY_PATH at its libs
#   .whl/         Python wheels the GPU machine's python3 lacks (pure Python):
#                 gymnasium and farama-notifications, for scandyn.envs and its tests
#                 (numpy, cloudpickle, typing-extensions, torch are there). On the GPU
#                 machine: python3 -m pip install --no-index --no-deps --target /tmp/site
#                 .whl/*.whl; export PYTHONPATH=/tmp/site (docs/python.md, "On the GPU machine")
# All are git-ignored; they travel to the GPU machine with the working tree (the
# device tool carries .deps and .whl when they are named in its carry list).
#
# The packages are the dependency closure of liburdfdom-dev (urdfdom libraries
# and headers, console_bridge, tinyxml) and nlohmann-json3-dev (scene files;
# header-only), minus the C/C++ runtime every machine
# with g++ has. They are built for this machine's Debian release and architecture
# (see .deps/manifest.txt); the GPU machine must be the same architecture with a
# glibc/libstdc++ at least as new.
#
# urdfdom's exported CMake targets name libtinyxml.so by absolute path
# (/usr/lib/<arch>/libtinyxml.so); the unpacked copy is patched to name it
# relative to its own prefix, so the unpacked tree works wherever it lies.
#
set -euo pipefail

cd "$(dirname "${BASH_SOURCE[0]}")/.."
repo=$PWD
deps=$repo/.deps
debs=$deps/debs
root=$deps/root

die() { echo "prepare_device.sh: $*" >&2; exit 1; }
note() { echo "prepare_device.sh: $*"; }

command -v apt-get >/dev/null && command -v dpkg-deb >/dev/null ||
  die "needs apt-get and dpkg (Debian/Ubuntu)"

# ---- which packages --------------------------------------------------------
# the runtime every target machine has; everything else in the closure is staged
base_re='^(libc6|libgcc-s1|libstdc\+\+6|gcc-[0-9]+-base)$'
closure() {
  apt-cache depends --recurse --no-recommends --no-suggests --no-conflicts --no-breaks \
    --no-replaces --no-enhances liburdfdom-dev nlohmann-json3-dev 2>/dev/null |
    grep -E '^[a-z0-9]' | grep -Ev "$base_re" | sort -u || true
}
mapfile -t packages < <(closure)
if ((${#packages[@]} == 0)); then
  note "apt does not know liburdfdom-dev yet; running apt-get update"
  if ((EUID == 0)); then apt-get update -q; else sudo apt-get update -q; fi
  mapfile -t packages < <(closure)
fi
((${#packages[@]} > 0)) || die "cannot resolve liburdfdom-dev's dependencies with apt-cache"
for must in liburdfdom-dev liburdfdom-headers-dev libconsole-bridge-dev libtinyxml-dev nlohmann-json3-dev; do
  printf '%s\n' "${packages[@]}" | grep -qx "$must" || die "expected $must among: ${packages[*]}"
done
# SuiteSparse (CHOLMOD, its orderings, METIS) for the factor-graph solvers and the
# simulator's sparse loop path (cmake/factor_graph.cmake): named one by one, since
# libsuitesparse-dev's closure pulls every BLAS alternative. liblapack3 / libblas3
# are the reference builds; their libraries sit in lapack/ and blas/ subfolders
# (Debian's alternatives link them at install; copied up below).
packages+=(libsuitesparse-dev libcholmod3 libamd2 libcamd2 libccolamd2 libcolamd2 libsuitesparseconfig5
           libmetis5 libmetis-dev libblas3 liblapack3 libgfortran5 libquadmath0)
mapfile -t packages < <(printf '%s\n' "${packages[@]}" | sort -u)
note "packages: ${packages[*]}"

# ---- download (kept between runs) --------------------------------------------
mkdir -p "$debs"
need=()
for p in "${packages[@]}"; do
  v=$(apt-cache policy "$p" | awk '/Candidate:/ {print $2}')
  [[ -n "$v" && "$v" != "(none)" ]] || die "no installable version of $p"
  # .deb file names encode ':' of an epoch as %3a
  compgen -G "$debs/${p}_${v//:/%3a}_*.deb" >/dev/null || need+=("$p=$v")
done
if ((${#need[@]})); then
  note "downloading ${need[*]}"
  (cd "$debs" && apt-get download -q "${need[@]}") || die "apt-get download failed"
else
  note "all .deb files already in .deps/debs"
fi

# ---- unpack ------------------------------------------------------------------
rm -rf "$root"
mkdir -p "$root"
: >"$deps/manifest.txt"
for p in "${packages[@]}"; do
  v=$(apt-cache policy "$p" | awk '/Candidate:/ {print $2}')
  deb=$(compgen -G "$debs/${p}_${v//:/%3a}_*.deb" | head -n1)
  [[ -n "$deb" ]] || die "missing .deb for $p $v"
  dpkg-deb -x "$deb" "$root"
  printf '%s %s %s\n' "$(dpkg-deb -f "$deb" Package)" "$(dpkg-deb -f "$deb" Version)" \
    "$(dpkg-deb -f "$deb" Architecture)" >>"$deps/manifest.txt"
done
{
  echo "# unpacked by scripts/prepare_device.sh on $(date -u +%Y-%m-%dT%H:%M:%SZ)"
  echo "# host: $(. /etc/os-release && echo "$PRETTY_NAME"), $(dpkg --print-architecture)"
} >>"$deps/manifest.txt"

# Symbolic links (libfoo.so -> libfoo.so.1.0) become plain copies: the tree may
# travel by a transport that drops links.
while IFS= read -r -d '' link; do
  target=$(readlink -f "$link")
  if [[ ! -f "$target" ]]; then
    # links into packages that are not staged (libsuitesparse-dev links every
    # SuiteSparse library; documentation links); what is needed is checked below
    rm "$link"
    continue
  fi
  cp --remove-destination "$target" "$link"
done < <(find "$root" -type l -print0)

# ---- make urdfdom's CMake package relocatable ------------------------------------
mapfile -t exports < <(find "$root" -path '*/urdfdom/cmake/urdfdomExport.cmake')
((${#exports[@]} == 1)) || die "expected one urdfdomExport.cmake under .deps/root, found ${#exports[@]}"
# ";/usr/lib/..." inside INTERFACE_LINK_LIBRARIES -> ";${_IMPORT_PREFIX}/lib/..."
sed -i 's#;/usr/lib/#;${_IMPORT_PREFIX}/lib/#g' "${exports[0]}"
if grep -n 'INTERFACE_LINK_LIBRARIES.*"/usr/\|;/usr/' "${exports[0]}"; then
  die "urdfdomExport.cmake still names files under /usr (see above)"
fi

# ---- check the result ---------------------------------------------------------
multiarch=$(dirname "$(find "$root/usr/lib" -name 'liburdfdom_model.so.*' | head -n1)")
[[ -d "$multiarch" ]] || die "liburdfdom_model.so not unpacked"
for f in urdfdom/cmake/urdfdom-config.cmake console_bridge/cmake/console_bridge-config.cmake \
         libtinyxml.so libconsole_bridge.so liburdfdom_model.so; do
  [[ -e "$multiarch/$f" ]] || die "missing $multiarch/$f after unpacking"
done
[[ -e "$root/usr/include/urdf_parser/urdf_parser.h" && -e "$root/usr/include/tinyxml.h" ]] ||
  die "urdfdom/tinyxml headers missing after unpacking"
[[ -n "$(find "$root/usr/share" -name 'urdfdom_headers-config.cmake')" ]] ||
  die "urdfdom_headers CMake config missing after unpacking"
for alt in blas/libblas.so.3 lapack/liblapack.so.3; do
  [[ -f "$multiarch/$alt" ]] || die "missing $multiarch/$alt after unpacking"
  cp "$multiarch/$alt" "$multiarch/${alt#*/}"
done
rm -rf "$multiarch/blas" "$multiarch/lapack"
find "$root" -name '*.a' -delete  # static libraries (SuiteSparse's): the builds link the shared ones
[[ -e "$root/usr/include/suitesparse/cholmod.h" && -e "$multiarch/libcholmod.so" ]] ||
  die "CHOLMOD headers or library missing after unpacking"
note "unpacked into .deps/root (libraries in ${multiarch#"$repo"/})"

# ---- Python wheels ---------------------------------------------------------------
# for the GPU machine's python3 (3.12, x86-64); pure-Python wheels, one version each
wheels=(gymnasium==1.4.0 farama-notifications==0.0.6)
py=python3
[[ -x .venv/bin/python ]] && py=.venv/bin/python
mkdir -p .whl
# one version of each (two stop the install there): drop earlier downloads of these
for w in "${wheels[@]}"; do
  n=${w%%==*}
  find .whl -maxdepth 1 -iregex ".*/${n//-/[_-]}-[^-]*-.*\.whl" -delete
done
"$py" -m pip download -q --disable-pip-version-check --no-deps --only-binary=:all: --python-version 3.12 \
  --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 \
  --platform manylinux2014_x86_64 -d .whl "${wheels[@]}" || die "pip download of ${wheels[*]} failed"
for w in "${wheels[@]}"; do
  n=${w%%==*} v=${w##*==}
  find .whl -maxdepth 1 -iregex ".*/${n//-/[_-]}-${v//./\\.}-.*\.whl" | grep -q . || die "no wheel of $w in .whl"
done
note "wheels in .whl: $(cd .whl && echo *.whl)"

du -sh .deps/debs .deps/root .whl | sed 's/^/prepare_device.sh: size /'
note "done; on the GPU machine run: scripts/gpu_check.sh \"\$OUT\""

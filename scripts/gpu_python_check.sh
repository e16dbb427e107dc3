#!/usr/bin/env bash
# scripts/gpu_python_check.sh: the Python package on the GPU machine, offline.
#
#   scripts/gpu_python_check.sh [OUTDIR]        (default: $OUT)
#
# Needs what gpu_check.sh needs (.deps/root from scripts/prepare_device.sh, nvcc) and,
# on the machine, pip with scikit-build-core and nanobind (no download: the build is
# not isolated), pytest, and the array libraries to test with (torch, JAX, CuPy). Steps:
#   1. the machine's python3 (its numpy, torch, JAX, CuPy, scikit-build-core, nanobind:
#      python3 may itself be a virtual environment, whose packages a --system-site-packages
#      venv would not see); pip install --target $SCANDYN_PY_TARGET (default
#      /tmp/scandyn-site, put first on PYTHONPATH) --no-build-isolation
#      --no-index --no-deps . with CUDA (nvcc), urdfdom from .deps/root  -> pip.log
#   2. what was installed: versions, has_cuda, the CUDA backend's state   -> python-env.txt
#   3. loading a URDF after `import torch` (and jax, cupy), with and without
#      RTLD_DEEPBIND (SCANDYN_NO_DEEPBIND=1), exit codes and faulthandler output, and
#      the dynamic linker's bindings of urdfdom / tinyxml / console_bridge / the module
#      to any other library                                            -> import-order.txt
#   4. pytest python/tests against the installed package                -> pytest.log, pytest.xml
#   5. bench/python/call_overhead.py (iiwa float, B = 1, 10^4, 10^6; C++ rows from the
#      installed package's scandyn program)                            -> python-overhead.csv
#      (SCANDYN_SKIP_BENCH=1 skips it)
# SCANDYN_PY_SKIP_INSTALL=1 reuses the package already installed in the environment.
# summary.txt lists each step's outcome; the exit status is non-zero if any failed.
set -uo pipefail

cd "$(dirname "${BASH_SOURCE[0]}")/.."
repo=$PWD
out=${1:-${OUT:-}}
[[ -n "$out" ]] || { echo "gpu_python_check.sh: no output directory: pass it as \$1 or set \$OUT" >&2; exit 2; }
mkdir -p "$out"
out=$(cd "$out" && pwd)
summary=$out/summary.txt
: >"$summary"
status=0
record() {
  local word=ok
  [[ "$2" == 0 ]] || { word="FAILED (exit $2)"; status=1; }
  printf '%-28s %s\n' "$1" "$word" | tee -a "$summary"
}
note() { printf '\n==== [%s] %s\n' "$(date +%H:%M:%S)" "$*"; }

deps=$repo/.deps/root
cfg=$(find "$deps/usr/lib" -path '*/urdfdom/cmake/urdfdom-config.cmake' 2>/dev/null | head -n1)
[[ -n "$cfg" ]] || { echo "gpu_python_check.sh: no urdfdom under $deps: run scripts/prepare_device.sh" >&2; exit 2; }
libdir=$(dirname "$(dirname "$(dirname "$cfg")")")
export LD_LIBRARY_PATH=$libdir${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
export CMAKE_PREFIX_PATH=$deps/usr${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}
export SCANDYN_MODELS_DIR=$repo/models
if ! command -v nvcc >/dev/null 2>&1 && [[ -x /usr/local/cuda/bin/nvcc ]]; then
  export PATH=/usr/local/cuda/bin:$PATH
fi
export CMAKE_CUDA_ARCHITECTURES=${CMAKE_CUDA_ARCHITECTURES:-90}
export CMAKE_BUILD_PARALLEL_LEVEL=${SCANDYN_JOBS:-$(nproc)}

# ---- 1. install --------------------------------------------------------------------
target=${SCANDYN_PY_TARGET:-/tmp/scandyn-site}
note "pip install . into $target -> $out/pip.log"
py=$(command -v python3)
export PYTHONPATH=$target${PYTHONPATH:+:$PYTHONPATH}
if [[ "${SCANDYN_PY_SKIP_INSTALL:-0}" == 1 ]]; then
  record "pip install (skipped: SCANDYN_PY_SKIP_INSTALL=1)" 0
else
  t0=$(date +%s)
  "$py" -m pip install -v --no-build-isolation --no-index --no-deps --upgrade --target "$target" . \
    -C cmake.define.CMAKE_CUDA_ARCHITECTURES="$CMAKE_CUDA_ARCHITECTURES" >"$out/pip.log" 2>&1
  rc=$?
  echo "pip install: $(($(date +%s) - t0)) s, exit $rc" >>"$out/pip.log"
  record "pip install ($(($(date +%s) - t0)) s)" $rc
  ((rc == 0)) || exit 1
fi

# ---- 2. what is installed ----------------------------------------------------------------
cd "$out"  # away from the source tree: `import scandyn` is the installed package
"$py" - >"$out/python-env.txt" 2>&1 <<'PY'
import importlib, sys
import scandyn as sd
from scandyn.__main__ import cli_path
print("python", sys.version.split()[0])
print("scandyn", sd.__version__, sd.__file__, "has_cuda", sd.has_cuda, "cuda:", sd.backend_unusable("cuda") or "usable")
print("program", cli_path())
for lib in ("numpy", "torch", "jax", "jaxlib", "cupy", "pytest"):
    try:
        print(lib, importlib.import_module(lib).__version__)
    except Exception as e:  # noqa: BLE001
        print(lib, "not importable:", type(e).__name__, e)
PY
record "python env" $?
cli=$("$py" -c 'from scandyn.__main__ import cli_path; print(cli_path())')

# ---- 3. import order ---------------------------------------------------------------
note "URDF after torch / jax / cupy -> $out/import-order.txt"
{
  for lib in torch jax cupy; do
    "$py" -c "import $lib" 2>/dev/null || { echo "$lib: not importable"; continue; }
    for deep in on off; do
      env_=()
      [[ $deep == off ]] && env_=(SCANDYN_NO_DEEPBIND=1)
      env "${env_[@]}" "$py" -X faulthandler -c "import $lib
import scandyn as sd
m = sd.load_model('iiwa'); print('nv', m.nv, 'hyq', sd.load_model('hyq').nv)" >"$out/io.txt" 2>&1
      echo "import $lib, then load_model, RTLD_DEEPBIND $deep: exit $?"
      sed 's/^/    /' "$out/io.txt" | tail -n 20
    done
  done
  echo
  echo "bindings of urdfdom / tinyxml / console_bridge / _scandyn references to other libraries"
  echo "(after import torch; RTLD_DEEPBIND off, then on):"
  for deep in off on; do
    env_=()
    [[ $deep == off ]] && env_=(SCANDYN_NO_DEEPBIND=1)
    rm -f "$out"/ld.*
    env "${env_[@]}" LD_DEBUG=bindings LD_DEBUG_OUTPUT="$out/ld" "$py" -c "import torch
import scandyn as sd
sd.load_model('iiwa')" >/dev/null 2>&1
    echo "  RTLD_DEEPBIND $deep (exit $?):"
    cat "$out"/ld.* 2>/dev/null | grep -E "binding file \S*(urdfdom|tinyxml|console_bridge|_scandyn)" |
      grep -vE "to \S*(urdfdom|tinyxml|console_bridge|_scandyn|libstdc\+\+|libc\.so|libm\.so|libgcc_s|ld-linux)" |
      sed 's/^[0-9]*: *//' | sort | uniq -c | sort -rn | head -n 40 | sed 's/^/    /'
    rm -f "$out"/ld.*
  done
} >"$out/import-order.txt" 2>&1
rm -f "$out/io.txt"
record "import order (see file)" 0

# ---- 4. pytest -----------------------------------------------------------------------
note "pytest python/tests -> $out/pytest.log"
SCANDYN_CLI=$cli "$py" -m pytest -v -rs --junitxml="$out/pytest.xml" -p no:cacheprovider \
  --rootdir="$repo/python/tests" "$repo/python/tests" >"$out/pytest.log" 2>&1
rc=$?
tail -n 3 "$out/pytest.log"
record "pytest" $rc

# ---- 5. call overhead ------------------------------------------------------------------
if [[ "${SCANDYN_SKIP_BENCH:-0}" != 1 ]]; then
  note "bench/python/call_overhead.py -> $out/python-overhead.csv"
  "$py" "$repo/bench/python/call_overhead.py" --scandyn "$cli" --out "$out/python-overhead.csv" \
    >"$out/python-overhead.log" 2>&1
  record "call overhead" $?
fi
cat "$summary"
exit $status

#!/usr/bin/env bash
# bench/compare/stage_wheels.sh: on the GPU machine, keep one carried folder of wheel parts
# (.whl-warp/partK from bench/compare/fetch_wheels.sh --with-warp) in /tmp/whl-stage, where
# the machine keeps it between calls while it stays warm. gpu.sh joins and installs the
# complete wheels. Prints which parts are staged and which are still missing.
#
#   bench/compare/stage_wheels.sh .whl-warp/partK [...]
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
stage=${SCANDYN_WHEEL_STAGE:-/tmp/whl-stage}
(($#)) || { echo "stage_wheels.sh: name the carried folder(s) of parts (.whl-warp/partK)" >&2; exit 2; }
mkdir -p "$stage"
for d in "$@"; do
  [[ -f "$d/MANIFEST" ]] || { echo "stage_wheels.sh: $d: no MANIFEST (was it carried? fetch_wheels.sh --with-warp makes it)" >&2; exit 2; }
  cp "$d/MANIFEST" "$stage/MANIFEST"
  for p in "$d"/*.part*; do
    want=$(awk -v f="$(basename "$p")" '$1 == "part" && $3 == f {print $2}' "$d/MANIFEST")
    got=$(sha256sum "$p" | cut -d' ' -f1)
    [[ "$want" == "$got" ]] || { echo "stage_wheels.sh: $p: sha256 $got, MANIFEST says ${want:-nothing}" >&2; exit 1; }
    cp "$p" "$stage/"
  done
done
missing=$(awk '$1 == "part" {print $3}' "$stage/MANIFEST" | while read -r f; do [[ -f "$stage/$f" ]] || echo "$f"; done)
echo "stage_wheels.sh: staged in $stage: $(cd "$stage" && ls *.part* | paste -sd' ')"
if [[ -n "$missing" ]]; then
  echo "stage_wheels.sh: still missing: $(echo "$missing" | paste -sd' ')"
else
  echo "stage_wheels.sh: every part is staged: gpu.sh will join and install them"
fi

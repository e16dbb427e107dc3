# bench/compare/install_wheels.sh (sourced): installs the peers' wheels offline on the GPU
# machine into /tmp/site and puts it on PYTHONPATH: .whl/*.whl (bench/compare/fetch_wheels.sh)
# and every wheel whose parts bench/compare/stage_wheels.sh staged in earlier calls (MuJoCo
# Warp), joined and checked against the MANIFEST's sha256. Used by gpu.sh.
#
#   source bench/compare/install_wheels.sh        (from the repository root)
wheels=()
compgen -G ".whl/*.whl" >/dev/null && wheels+=(.whl/*.whl)
# wheels too large for one call, staged in parts by bench/compare/stage_wheels.sh (MuJoCo Warp)
stage=${SCANDYN_WHEEL_STAGE:-/tmp/whl-stage}
if [[ -f "$stage/MANIFEST" ]]; then
  while read -r kind sum name n; do
    [[ "$kind" == wheel ]] || continue
    have=$(compgen -G "$stage/$name.part*" | wc -l)
    if ((have != n)); then
      echo "install_wheels.sh: $name: $have of $n parts staged (bench/compare/stage_wheels.sh); left out"
      continue
    fi
    cat "$stage/$name".part* >"$stage/$name"
    if [[ "$(sha256sum "$stage/$name" | cut -d' ' -f1)" == "$sum" ]]; then
      wheels+=("$stage/$name")
      echo "install_wheels.sh: $name joined from $n staged parts"
    else
      echo "install_wheels.sh: $name: joined parts do not match the MANIFEST's sha256; left out"
      rm -f "$stage/$name"
    fi
  done <"$stage/MANIFEST"
fi
if ((${#wheels[@]})); then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site "${wheels[@]}" ||
    echo "install_wheels.sh: warning: pip install of the wheels failed; peers whose import fails are recorded as not installed"
  export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
else
  echo "install_wheels.sh: no .whl/ (run bench/compare/fetch_wheels.sh on a networked machine); peers not installed are recorded as such"
fi

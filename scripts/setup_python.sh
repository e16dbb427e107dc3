#!/usr/bin/env bash
# scripts/setup_python.sh: a local virtual environment (.venv) with what the Python
# scripts need: numpy, Pinocchio (PyPI `pin`) for the independent cross-check
# scripts/check_pinocchio.py, matplotlib for scripts/accuracy_report, and what the
# Python package (python/, docs/python.md) is built and tested with: nanobind,
# scikit-build-core, pytest and gymnasium (scandyn.envs; its tests skip without it).
# Idempotent: a second run only checks the imports (and installs what is missing).
# Needs python3 with venv (Debian: python3-venv, installed by scripts/setup.sh).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

venv=.venv
py=$venv/bin/python
if [[ -x "$py" ]] && "$py" -c 'import numpy, pinocchio, matplotlib, nanobind, scikit_build_core, pytest, gymnasium' 2>/dev/null; then
  echo "setup_python.sh: $venv ready ($("$py" -c 'import pinocchio; print("pinocchio", pinocchio.__version__)'))"
  exit 0
fi
[[ -x "$py" ]] || python3 -m venv "$venv"
"$py" -m pip install -q --disable-pip-version-check 'numpy>=1.24' 'pin==4.1.0' 'matplotlib>=3.6' \
  'nanobind>=2.0' 'scikit-build-core>=0.10' 'pytest>=7' 'gymnasium>=1.0'
echo "setup_python.sh: $venv ready ($("$py" -c 'import pinocchio; print("pinocchio", pinocchio.__version__)'))"

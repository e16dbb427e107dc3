"""``python -m scandyn``: the scandyn command (info, eval, bench, rollout; the same flags,
output and exit codes as the program: docs/cli.md).

The command is the C++ program itself, shipped inside the package (scandyn/_bin/scandyn,
installed by pip next to the extension module) and run in place of this interpreter
(os.execv): its exit code, signals, standard streams and terminal progress bars are
the program's own. In a build tree (PYTHONPATH=<build>/python) it is <build>/scandyn.
pip also installs it as the console script ``scandyn``. Models named without a path
("--model iiwa") are the package's own unless $SCANDYN_MODELS_DIR names another directory."""

import os
import subprocess
import sys

_PKG = os.path.dirname(os.path.abspath(__file__))


def cli_path():
    """The scandyn program this package runs: scandyn/_bin/scandyn of an installed
    package, else the build tree's <build>/scandyn, else $SCANDYN_CLI. Raises
    FileNotFoundError naming where it looked."""
    candidates = [
        os.path.join(_PKG, "_bin", "scandyn"),
        os.path.join(os.path.dirname(os.path.dirname(_PKG)), "scandyn"),  # <build>/python/scandyn -> <build>/scandyn
    ]
    if os.environ.get("SCANDYN_CLI"):  # a build tree whose program lies elsewhere (the tests' variable)
        candidates.append(os.environ["SCANDYN_CLI"])
    for p in candidates:
        if os.path.isfile(p) and os.access(p, os.X_OK):
            return p
    raise FileNotFoundError("the scandyn program is not in this package (looked for " + " and ".join(candidates) +
                            "); reinstall it with pip install .")


def main(argv=None):
    """Runs the scandyn program with argv (default: this process's arguments); does not
    return on POSIX (the program replaces the interpreter)."""
    args = sys.argv[1:] if argv is None else list(argv)
    try:
        exe = cli_path()
    except FileNotFoundError as e:
        sys.stderr.write(f"scandyn: {e}\n")
        return 1
    # models by name ("--model iiwa"): the package's own, unless the caller names a directory
    models = os.path.join(_PKG, "models")
    if not os.environ.get("SCANDYN_MODELS_DIR") and os.path.isfile(os.path.join(models, "iiwa.urdf")):
        os.environ["SCANDYN_MODELS_DIR"] = models
    sys.stdout.flush()
    sys.stderr.flush()
    if os.name == "posix":
        os.execv(exe, [exe] + args)
    return subprocess.call([exe] + args)


if __name__ == "__main__":
    sys.exit(main())

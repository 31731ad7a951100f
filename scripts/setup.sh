#!/usr/bin/env bash
# Set up everything fdi_ros needs, from nothing, inside this checkout:
#   .venv/                   project venv with the pinned ROS 2 Jazzy wheels and Python deps
#   .venv (as ROS prefix)    the rosidl build of msg_defs/fdi_msgs installed into the venv root,
#                            which the ROS wheels already use as their prefix ($VENV/lib, /share)
#   fdi_ros                  installed editable into the venv (console script .venv/bin/fdi-ros)
#   .venv (as ament prefix)  fdi_ros laid out as colcon would (index marker, share/fdi_ros,
#                            lib/fdi_ros/<node>) and .venv/setup.sh, so ros2 run/launch find it
# Idempotent: each step is skipped when its stamp matches the hash of its inputs, so a second
# run does no network work and takes about a second.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$ROOT/.venv"
BUILD="$ROOT/build"
PY="${PYTHON:-python3}"
mkdir -p "$BUILD"

hash_of() { cat "$@" | sha256sum | cut -c1-16; }
stamp_ok() { [ -f "$BUILD/$1.stamp" ] && [ "$(cat "$BUILD/$1.stamp")" = "$2" ]; }
stamp_set() { echo "$2" > "$BUILD/$1.stamp"; }

t0=$(date +%s)
# 1. venv and pinned wheels ------------------------------------------------------------------
h_deps=$(hash_of "$ROOT/requirements.txt" "$ROOT/requirements-extras.txt" "$ROOT/constraints.txt")
if ! stamp_ok deps "$h_deps" || [ ! -x "$VENV/bin/python" ]; then
  echo "[setup] creating venv and installing pinned dependencies"
  [ -x "$VENV/bin/python" ] || "$PY" -m venv "$VENV"
  # uv (pinned in constraints.txt) installs the same pinned set as pip, in parallel: ~30 s
  # instead of ~85 s on 2 cores; pip does it when uv cannot be had.
  if "$VENV/bin/python" -m pip install -q --disable-pip-version-check -c "$ROOT/constraints.txt" \
        uv && [ -x "$VENV/bin/uv" ]; then
    UV_NO_CACHE=1 "$VENV/bin/uv" pip install -q --python "$VENV/bin/python" --compile-bytecode \
        -r "$ROOT/requirements.txt" -r "$ROOT/requirements-extras.txt" -c "$ROOT/constraints.txt"
  else
    "$VENV/bin/python" -m pip install -q --disable-pip-version-check \
        -r "$ROOT/requirements.txt" -r "$ROOT/requirements-extras.txt" -c "$ROOT/constraints.txt"
  fi
  # Pitfall 1 (ROS_ENV.md): the wheels' CMake exports carry the build machine's paths.
  "$VENV/bin/python" "$ROOT/scripts/fix_cmake_prefix.py" "$VENV"
  rm -f "$BUILD/msgs.stamp"
  stamp_set deps "$h_deps"
fi

# 2. rosidl build of msg_defs/fdi_msgs into the venv prefix -----------------------------------
h_msgs=$(hash_of "$ROOT"/msg_defs/fdi_msgs/CMakeLists.txt "$ROOT"/msg_defs/fdi_msgs/package.xml \
         "$ROOT"/msg_defs/fdi_msgs/msg/*.msg "$ROOT"/msg_defs/fdi_msgs/srv/*.srv)
if ! stamp_ok msgs "$h_msgs"; then
  echo "[setup] building msg_defs/fdi_msgs with rosidl (cmake + make)"
  rm -rf "$BUILD/fdi_msgs"
  mkdir -p "$BUILD/fdi_msgs"
  (
    cd "$BUILD/fdi_msgs"
    export AMENT_PREFIX_PATH="$VENV" CMAKE_PREFIX_PATH="$VENV" PATH="$VENV/bin:$PATH"
    cmake -S "$ROOT/msg_defs/fdi_msgs" -B . -DCMAKE_INSTALL_PREFIX="$VENV" \
          -DPython3_EXECUTABLE="$VENV/bin/python" -DBUILD_TESTING=OFF \
          -DCMAKE_BUILD_TYPE=Release > cmake.log 2>&1 || { cat cmake.log; exit 1; }
    make -j2 install > make.log 2>&1 || { tail -50 make.log; exit 1; }
  )
  stamp_set msgs "$h_msgs"
fi

# 3. fdi_ros itself (editable) -----------------------------------------------------------------
h_pkg=$(hash_of "$ROOT/setup.py" "$ROOT/setup.cfg")
if ! stamp_ok pkg "$h_pkg"; then
  echo "[setup] installing fdi_ros (editable)"
  "$VENV/bin/python" -m pip install -q --disable-pip-version-check --no-deps --no-build-isolation \
      -e "$ROOT"
  rm -f "$BUILD/ament.stamp"
  stamp_set pkg "$h_pkg"
fi

# 4. the venv as the ament prefix of fdi_ros (what `colcon build` would install) ---------------
h_ament=$(hash_of "$ROOT/scripts/ament_prefix.py" "$ROOT/setup.py" "$ROOT/package.xml" \
          "$ROOT/resource/fdi_ros")
if ! stamp_ok ament "$h_ament" || [ ! -f "$VENV/share/ament_index/resource_index/packages/fdi_ros" ]
then
  "$VENV/bin/python" "$ROOT/scripts/ament_prefix.py" "$VENV"
  stamp_set ament "$h_ament"
fi
echo "[setup] ready in $(( $(date +%s) - t0 )) s: $VENV/bin/fdi-ros"

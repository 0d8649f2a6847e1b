#!/usr/bin/env bash
# Build and install the minimal tf2_msgs interface package (interfaces/tf2_msgs: TFMessage only)
# into the active Python environment, for virtual environments made from the ROS 2 Jazzy PyPI
# wheels (requirements.txt), which have no tf2_msgs / tf2_ros wheel.
#
# Idempotent: does nothing when `python -c "import tf2_msgs.msg"` already works (a full ROS
# install with the real tf2_msgs sourced, or a previous run).
#
# Uses `python` from PATH (activate the venv first, or set PYTHON=/path/to/venv/bin/python).
# Needs, besides PyPI: cmake >= 3.16 and gcc/g++ (Debian: apt-get install -y cmake g++).
set -euo pipefail

PYTHON="${PYTHON:-python}"
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
PKG_DIR="$(cd "$HERE/../interfaces/tf2_msgs" && pwd)"

if "$PYTHON" -c "import tf2_msgs.msg" >/dev/null 2>&1; then
  echo "build_tf2_msgs: tf2_msgs already importable ($("$PYTHON" -c 'import tf2_msgs, os; print(os.path.dirname(tf2_msgs.__file__))')), nothing to do"
  exit 0
fi

# The generators and the ament CMake modules come from the venv's ROS wheels, so this only makes
# sense in the environment that has rclpy and geometry_msgs installed (requirements.txt).
if ! "$PYTHON" -c "import rclpy, geometry_msgs.msg" >/dev/null 2>&1; then
  echo "build_tf2_msgs: '$PYTHON' cannot import rclpy and geometry_msgs; install requirements.txt into it first" >&2
  exit 1
fi

missing=()
command -v cmake >/dev/null 2>&1 || missing+=(cmake)
command -v "${CC:-cc}" >/dev/null 2>&1 || missing+=(gcc)
command -v "${CXX:-c++}" >/dev/null 2>&1 || missing+=(g++)
if ((${#missing[@]})); then
  echo "build_tf2_msgs: missing build tools: ${missing[*]} (Debian/Ubuntu: apt-get install -y cmake g++)" >&2
  exit 1
fi

start=$SECONDS
echo "build_tf2_msgs: installing pinned build dependencies into $("$PYTHON" -c 'import sys; print(sys.prefix)')"
# ament_cmake_python runs `setup.py egg_info`; venvs made by `python -m venv` have setuptools,
# others (e.g. uv) may not.
if ! "$PYTHON" -c "import setuptools" >/dev/null 2>&1; then
  "$PYTHON" -m pip install --quiet "setuptools<81"
fi
"$PYTHON" -m pip install --quiet -r "$PKG_DIR/build-requirements.txt"

echo "build_tf2_msgs: building $PKG_DIR (CMake + rosidl, about 10 s)"
# No build isolation: CMake must find the ROS wheels installed in this environment.
# CMAKE_BUILD_PARALLEL_LEVEL: scikit-build-core otherwise builds with one job under make.
CMAKE_BUILD_PARALLEL_LEVEL="${CMAKE_BUILD_PARALLEL_LEVEL:-$(nproc 2>/dev/null || echo 2)}" \
  "$PYTHON" -m pip install --quiet --no-build-isolation --no-deps "$PKG_DIR"

"$PYTHON" -c "from tf2_msgs.msg import TFMessage; TFMessage()"
echo "build_tf2_msgs: tf2_msgs installed in $((SECONDS - start)) s"

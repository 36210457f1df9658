#!/usr/bin/env bash
# Build the ROS interface packages named on the command line (folders holding an
# ament_cmake package.xml, e.g. interfaces/stars_ros_msgs) into .venv from PyPI wheels alone
# (requirements-interfaces.txt), so a plain .venv/bin/python imports them with nothing to
# source. A no-op while the pins and the packages' files are unchanged.
# Steps and why: /work/shared/notes/ros-interfaces.md (the wheels' CMake exports name the
# wheel builder's Python and numpy include folders: they are rewritten to the venv's once).
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-$PWD/.venv}
PY=$VENV/bin/python
[ "$#" -gt 0 ] || { echo "usage: $0 PACKAGE_FOLDER..." >&2; exit 2; }
stamp=$VENV/.stars_ros-interfaces
want=$( (cat requirements-interfaces.txt; for pkg in "$@"; do (cd "$pkg" && find . -type f | LC_ALL=C sort | xargs sha256sum); done) | sha256sum | cut -d' ' -f1)
if [ "$(cat "$stamp" 2>/dev/null)" = "$want" ]; then
  exit 0
fi
"$PY" -m pip install --quiet -r requirements-interfaces.txt
include=$("$PY" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
numpy_include=$("$PY" -c 'import numpy; print(numpy.get_include())')
for export in "$VENV"/share/*/cmake/export_*__rosidl_generator_pyExport.cmake; do
  [ -f "$export" ] || continue
  # every foreign Python include folder (/opt/python/cp3XX-.../include/python3.X) and numpy include folder
  sed -i -E "s#/[^;\" ]*/site-packages/numpy/(_core|core)/include#${numpy_include}#g; s#/opt/python/[^;\" ]*/include/python3\.[0-9]+#${include}#g" "$export"
done
for pkg in "$@"; do
  name=$(basename "$pkg")
  build=$VENV/build/$name
  cmake -S "$pkg" -B "$build" -DCMAKE_PREFIX_PATH="$VENV" -DCMAKE_INSTALL_PREFIX="$VENV" \
    -DPython3_EXECUTABLE="$PY" -DBUILD_TESTING=OFF -DCMAKE_BUILD_TYPE=Release >/dev/null
  cmake --build "$build" -j "$(nproc)" >/dev/null
  cmake --install "$build" >/dev/null
done
echo "$want" > "$stamp"

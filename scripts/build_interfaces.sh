#!/usr/bin/env bash
# Build ament_cmake interface packages (.msg/.srv) into .venv from PyPI wheels alone, so a
# plain .venv/bin/python imports them with nothing to source (../shared/notes/ros-interfaces.md).
# Usage: scripts/build_interfaces.sh PACKAGE_DIR...   (paths from the repository root; STARS_VENV
# names another venv than .venv, as benchmarks/serving_install.py's serving-only one)
# Each package is rebuilt only when its files change (a stamp per package in .venv); a ROS
# workspace builds the same packages with colcon instead (docs/interfaces.md).
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${STARS_VENV:-$(pwd)/.venv}
PY=$VENV/bin/python
stamp=$VENV/.stars_ros-interface-wheels
want=$(sha256sum requirements-interfaces.txt | cut -d' ' -f1)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  "$PY" -m pip install --quiet -r requirements-interfaces.txt
  # The wheels' CMake exports name the wheel builder's Python and numpy headers; CMake refuses
  # them until they name this interpreter's own.
  python_include=$("$PY" -c "import sysconfig; print(sysconfig.get_paths()['include'])")
  numpy_include=$("$PY" -c "import numpy; print(numpy.get_include())")
  for file in "$VENV"/share/*/cmake/export_*__rosidl_generator_pyExport.cmake; do
    sed -i -E "s#/opt/python/[^/;\"]+/include/python3\.[0-9]+#${python_include}#g; \
s#/opt/python/[^/;\"]+/lib/python3\.[0-9]+/site-packages/numpy/_core/include#${numpy_include}#g" "$file"
  done
  echo "$want" > "$stamp"
fi
for package in "$@"; do
  name=$(basename "$package")
  package_stamp=$VENV/.stars_ros-interface-$name
  digest=$(cd "$package" && find . -type f ! -name '*.pyc' | LC_ALL=C sort | xargs sha256sum | sha256sum | cut -d' ' -f1)
  kinds=$(for kind in msg srv action; do if [ -d "$package/$kind" ]; then printf '%s.%s,' "$name" "$kind"; fi; done)
  if [ "$(cat "$package_stamp" 2>/dev/null)" = "$digest" ] && "$PY" -c "import ${kinds%,}" 2>/dev/null; then
    continue  # built from these files, and each of its msg, srv and action modules imports
  fi
  build=$(mktemp -d)
  trap 'rm -rf "$build"' EXIT
  echo "building the interface package $name into $VENV"
  cmake -S "$package" -B "$build" -DCMAKE_PREFIX_PATH="$VENV" -DCMAKE_INSTALL_PREFIX="$VENV" \
    -DPython3_EXECUTABLE="$PY" -DBUILD_TESTING=OFF > "$build/configure.log" 2>&1 \
    || { cat "$build/configure.log" >&2; exit 1; }
  cmake --build "$build" -j 2 > "$build/build.log" 2>&1 || { tail -50 "$build/build.log" >&2; exit 1; }
  cmake --install "$build" > /dev/null
  rm -rf "$build"
  trap - EXIT
  echo "$digest" > "$package_stamp"
done

#!/usr/bin/env bash
# Create .venv (Python 3.11) with every pinned dependency (serving, training, rclpy wheels, Ray and
# test/build tools: requirements-dev.txt), the typed interfaces stars_ros_msgs built into it
# (scripts/build_interfaces.sh) and stars_ros installed editable, so `ranker`, `scene_publisher` and
# `replay` are on its PATH. Re-running is cheap: nothing is reinstalled while the
# requirements files, setup.py, setup.cfg and package.xml are unchanged.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3.11}
command -v "$PYTHON" >/dev/null || PYTHON=python3
if [ ! -x .venv/bin/python ]; then
  "$PYTHON" -m venv .venv
fi
stamp=.venv/.stars_ros-installed
want=$(cat requirements.txt requirements-train.txt requirements-rclpy.txt requirements-ray.txt requirements-peers.txt requirements-dev.txt setup.py setup.cfg package.xml | sha256sum | cut -d' ' -f1)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  .venv/bin/python -m pip install --quiet --upgrade pip
  .venv/bin/python -m pip install --quiet -r requirements-dev.txt
  .venv/bin/python -m pip install --quiet --no-deps --no-build-isolation -e .
  echo "$want" > "$stamp"
fi
bash scripts/build_interfaces.sh interfaces/stars_ros_msgs  # a no-op while unchanged
# The feedback page's browser test drives Debian's chromium through playwright (never
# `playwright install`, which downloads a browser): installed here when running as root
# without it; elsewhere the test skips, saying so.
if [ ! -x /usr/bin/chromium ] && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null 2>&1 \
    || { apt-get update -qq >/dev/null 2>&1 && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; } \
    || echo "setup_venv.sh: chromium could not be installed; the browser test will skip" >&2
fi
# Register stars_ros in the venv's ament index, as colcon would in an install folder, so a
# ROS 2 command line with AMENT_PREFIX_PATH=$PWD/.venv finds it (`ros2 run stars_ros ranker`,
# `ros2 launch stars_ros hri.launch.py`): setup.py's data_files (the package marker,
# share/stars_ros's package.xml, launch files, shipped configs, msg_schemas, models) as
# `colcon build --symlink-install` lays them out, real folders of links to this checkout's files
# (scripts/link_share.py: `ros2 launch` does not look inside a linked folder), and lib/stars_ros
# (links to the executables pip put in .venv/bin).
.venv/bin/python scripts/link_share.py .venv
mkdir -p .venv/lib/stars_ros
for executable in $(sed -n "s/^ *'\([a-z_]*\) = stars_ros\..*/\1/p" setup.py); do
  ln -sfn "../../bin/$executable" ".venv/lib/stars_ros/$executable"
done

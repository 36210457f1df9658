#!/usr/bin/env bash
# Set up the environment, then run the whole test suite (`-m "not slow"` for the quick
# subset). Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_venv.sh
# The tests' stand-in for ROS4HRI's hri_msgs (test/interfaces/hri_msgs), never installed with the package;
# built before pytest starts, so every module that looks for hri_msgs finds it.
bash scripts/build_interfaces.sh test/interfaces/hri_msgs
export STARS_SOCNAV1_ROOT=${STARS_SOCNAV1_ROOT:-$(cd .. && pwd)/shared/datasets/socnav1}
set +e
.venv/bin/python -m pytest "$@"
status=$?
set -e
if [ "$status" -eq 5 ]; then
  echo "error: pytest collected no tests" >&2
  exit 1
fi
exit "$status"

#!/usr/bin/env bash
# The main job: set up the environment, then run the demo — the ranker serving two people
# with the packaged SocNav1 model, their rankings side by side, feedback recorded to MCAP
# in a new temporary folder (named in the summary), and a summary. Ends by itself. Extra arguments go to the demo
# (see `python -m stars_ros.examples.demo --help`).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_venv.sh
export STARS_SOCNAV1_ROOT=${STARS_SOCNAV1_ROOT:-$(cd .. && pwd)/shared/datasets/socnav1}
export ROS_AUTOMATIC_DISCOVERY_RANGE=${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}
exec .venv/bin/python -m stars_ros.examples.demo "$@"

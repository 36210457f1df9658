#!/usr/bin/env bash
# Set up the environment, then run the whole test suite (`-m "not slow"` for the quick
# subset). Extra arguments go to pytest. The tests run on as many pytest-xdist workers as there
# are cores, at most 2, each test file on one worker (`--dist loadfile`: a file's module-scoped
# node serves all its tests); `-n 0` (or any -n given) overrides that. docs/testing.md.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_venv.sh
# The tests' stand-in for ROS4HRI's hri_msgs (test/interfaces/hri_msgs), never installed with the package;
# built before pytest starts, so every module that looks for hri_msgs finds it.
bash scripts/build_interfaces.sh test/interfaces/hri_msgs
export STARS_SOCNAV1_ROOT=${STARS_SOCNAV1_ROOT:-$(cd .. && pwd)/shared/datasets/socnav1}
workers=$(nproc)
[ "$workers" -gt 2 ] && workers=2
parallel=(-n "$workers" --dist loadfile)
for arg in "$@"; do
  case $arg in
    -n|-n[0-9]*|--numprocesses|--numprocesses=*) parallel=() ;;
  esac
done
set +e
.venv/bin/python -m pytest "${parallel[@]}" "$@"
status=$?
set -e
if [ "$status" -eq 5 ]; then
  echo "error: pytest collected no tests" >&2
  exit 1
fi
exit "$status"

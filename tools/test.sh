#!/usr/bin/env bash
# Lint, then the whole test suite, in the set-up venv, with ROS traffic kept on loopback.
set -euo pipefail
cd "$(dirname "$0")/.."
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_LOG_DIR=$PWD/build/ros_log
export MPLBACKEND=Agg
echo "== lint (ruff: pyflakes, pycodestyle, pydocstyle/pep257 rules)"
.venv/bin/ruff check controlled_islanding test tools launch setup.py
echo "== tests"
exec .venv/bin/python -m pytest "$@"

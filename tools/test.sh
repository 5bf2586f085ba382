#!/usr/bin/env bash
# The whole test suite (lint included, as test/test_foundation_package.py), in the set-up venv, with ROS traffic kept on loopback.
set -euo pipefail
cd "$(dirname "$0")/.."
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_LOG_DIR=$PWD/build/ros_log
export MPLBACKEND=Agg

exec .venv/bin/python -m pytest "$@"

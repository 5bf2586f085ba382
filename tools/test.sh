#!/usr/bin/env bash
# The whole test suite (lint included, as test/test_foundation_package.py), in the set-up venv, with ROS traffic kept on loopback.
#
# Two pytest processes, one per core. One process left a core idle half the time (CPU 1.4 core-s per s of wall
# on 2 cores), because the ROS tests mostly wait on their node processes while the pure tests each use one core.
# The `ros` tests, many real time, run in front at normal priority. Everything else runs niced to 19, so it only
# gets the CPU they leave. Measured on 2026-12-04 on a 2-core machine: 1003 s in one process, 635 s split.
# Giving `-m` runs one process with that selection; so does `--junitxml`, which two processes would both write.
set -euo pipefail
cd "$(dirname "$0")/.."
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_LOG_DIR=$PWD/build/ros_log
export MPLBACKEND=Agg

for arg in "$@"; do
    case "$arg" in -m|-m*|--junitxml*|--junit-xml*) exec .venv/bin/python -m pytest "$@" ;; esac
done

mkdir -p build
log=build/tests_not_ros.log
echo "tests that start no ROS process: in a second pytest at nice 19, output in $log, shown at the end"
nice -n 19 .venv/bin/python -m pytest -m 'not ros' "$@" > "$log" 2>&1 &
other=$!
# A background job of a script ignores SIGINT: end it by its PID if this script is stopped.
trap 'kill -TERM "$other" 2>/dev/null || true' INT TERM

ros=0
.venv/bin/python -m pytest -m ros "$@" || ros=$?
rest=0
wait "$other" || rest=$?
trap - INT TERM
echo
echo "==== tests that start no ROS process ($log) ===="
cat "$log"

# 5 is pytest's "no tests collected": a selection that falls wholly on one side is not a failure of the other.
if [ "$ros" -eq 5 ] && [ "$rest" -eq 5 ]; then exit 5; fi
[ "$ros" -eq 5 ] && ros=0
[ "$rest" -eq 5 ] && rest=0
if [ "$ros" -ne 0 ]; then exit "$ros"; fi
exit "$rest"

#!/usr/bin/env bash
# Create .venv with pinned ROS 2 Jazzy wheels and every other dependency,
# compile msg_schemas/ for rclpy into it, and install this package.
#
# A second run with unchanged inputs is a no-op. Two stamps make it cheap to
# iterate: the wheel stamp lets a change to msg_schemas/ rebuild only the
# interfaces. The venv is trusted only once the final stamp is written, which
# is the very last step; any failure leaves it untrusted and named.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
VENV=${VENV:-$ROOT/.venv}
PYTHON=${PYTHON:-python3.11}
BUILD=$ROOT/build/setup
WHEELS_STAMP=$VENV/.setup-wheels
STAMP=$VENV/.setup-complete

hash_of() { cat "$@" | sha256sum | cut -d' ' -f1; }

step=""
on_error() {
  echo "setup: FAILED at step '$step' (log: $BUILD/*.log). $VENV is not trusted; fix the cause and rerun 'make setup'." >&2
}
trap on_error ERR

step="check python"
command -v "$PYTHON" >/dev/null || { echo "setup: $PYTHON not found; Python 3.11 is required (the ROS 2 Jazzy wheels are cp311)." >&2; exit 1; }
wheels_hash=$( { "$PYTHON" --version; cat requirements.txt constraints.txt; } | sha256sum | cut -d' ' -f1)
full_hash=$( { echo "$wheels_hash"; cat setup.py setup.cfg tools/setup.sh;
               find msg_schemas -type f | LC_ALL=C sort | xargs cat; } | sha256sum | cut -d' ' -f1)
if [[ -f $STAMP && "$(cat "$STAMP")" == "$full_hash" ]]; then
  exit 0
fi
rm -f "$STAMP"
mkdir -p "$BUILD"

if [[ ! -f $WHEELS_STAMP || "$(cat "$WHEELS_STAMP")" != "$wheels_hash" ]]; then
  echo "setup: creating $VENV with pinned wheels (about 2 minutes on a fresh machine)"
  step="create venv"
  rm -rf "$VENV"
  "$PYTHON" -m venv "$VENV"
  "$VENV/bin/python" -m pip install --quiet --upgrade pip >"$BUILD/pip.log" 2>&1
  step="install pinned wheels (pip install -r requirements.txt -c constraints.txt)"
  "$VENV/bin/python" -m pip install --progress-bar off -r requirements.txt -c constraints.txt \
    >>"$BUILD/pip.log" 2>&1 || { grep -v "^WARNING: Location" "$BUILD/pip.log" | tail -30 >&2; false; }

  step="patch wheel CMake configs"
  # About 14 exported CMake files hard-code the wheel build machine's include
  # directories; point them at this venv's Python and numpy.
  py_inc=$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
  np_inc=$("$VENV/bin/python" -c 'import numpy; print(numpy.get_include())')
  grep -rl --include='*.cmake' -e /opt/python/cp311-cp311 "$VENV/share" | while read -r f; do
    sed -i -e "s#/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include#$np_inc#g" \
           -e "s#/opt/python/cp311-cp311/include/python3.11#$py_inc#g" "$f"
  done
  echo "$wheels_hash" >"$WHEELS_STAMP"
fi

echo "setup: compiling msg_schemas/ into $VENV"
step="find a C compiler and cmake"
command -v cc >/dev/null || command -v gcc >/dev/null \
  || { echo "setup: no C compiler; the rosidl generators compile C (Debian: apt-get install build-essential)." >&2; false; }
CMAKE=$(command -v cmake || true)
if [[ -z $CMAKE ]]; then
  "$VENV/bin/python" -m pip install --quiet cmake >>"$BUILD/pip.log" 2>&1
  CMAKE=$VENV/bin/cmake
fi
build_msgs() {
  "$CMAKE" -S msg_schemas -B "$BUILD/msg_schemas" -DCMAKE_PREFIX_PATH="$VENV" -DCMAKE_INSTALL_PREFIX="$VENV" \
    -DPython3_EXECUTABLE="$VENV/bin/python" -DBUILD_TESTING=OFF \
  && "$CMAKE" --build "$BUILD/msg_schemas" -j 2 \
  && "$CMAKE" --install "$BUILD/msg_schemas"
}
step="compile msg_schemas (cmake configure, build, install)"
rm -rf "$BUILD/msg_schemas"
build_msgs >"$BUILD/msg_schemas.log" 2>&1 || { tail -30 "$BUILD/msg_schemas.log" >&2; false; }

step="install controlled_islanding (editable)"
"$VENV/bin/python" -m pip install --no-deps --no-build-isolation -e . >"$BUILD/package.log" 2>&1 \
  || { grep -v "^WARNING: Location" "$BUILD/package.log" | tail -30 >&2; false; }

step="import check"
"$VENV/bin/python" -c "import controlled_islanding_msgs.msg, controlled_islanding_msgs.srv, controlled_islanding, rclpy"

step="compile the numba kernels"
# numba compiles on a process's first call and caches beside the sources; compiled here once, not by every node
# process at its first decision (30 to 90 s each on a busy 2-core machine, past the supervisor's hang limit).
echo "setup: compiling the numba kernels (DTW, PAM, k rules, spectral repair, DSE filter and widening; the last three on import)"
"$VENV/bin/python" -c "
import numpy as np
import controlled_islanding.core.k_rules
import controlled_islanding.core.spectral
import controlled_islanding.core.dse_kernel
from controlled_islanding.core.dtw import dtw_distance_matrix
from controlled_islanding.core.pam import pam
rng = np.random.default_rng(0)
for parallel in (False, True):
    dtw_distance_matrix([rng.standard_normal(40) for _ in range(4)], window=10, parallel=parallel)
for n in (40, 1200):
    pam(rng.standard_normal((n, 2)), 2)
"

step="generate ANDES' numerical code"
# andes.load would generate it in a forked multiprocessing pool, which can deadlock inside a node (grid_sim).
echo "setup: generating ANDES' numerical code in build/andes_pycode (about 20 s)"
"$VENV/bin/python" -c "
import logging
from controlled_islanding.sim.andes_sim import ensure_pycode, quiet_andes
quiet_andes(logging.WARNING)
print('setup: ANDES code in', ensure_pycode())
"

echo "$full_hash" >"$STAMP"
echo "setup: done ($VENV)"

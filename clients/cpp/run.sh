#!/usr/bin/env bash
# Builds the C++ learner (incrementally, into clients/cpp/build or $TAMRM_CPP_BUILD_DIR)
# and runs it against the tamrm server at ADDR; extra arguments go to the learner.
#
#   bash clients/cpp/run.sh 127.0.0.1:50051 [--task ID] [--envs N] [--steps N] [--seed N]
#
# Needs cmake, g++ and gRPC's C++ packages (clients/cpp/README.md).
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
if [[ $# -lt 1 ]]; then
    echo "usage: $0 ADDR [learner options]" >&2
    exit 2
fi
build="${TAMRM_CPP_BUILD_DIR:-$here/build}"
if [[ ! -f "$build/CMakeCache.txt" ]]; then
    cmake -S "$here" -B "$build" >/dev/null
fi
cmake --build "$build" -j "${TAMRM_CPP_JOBS:-2}" >&2
exec "$build/tamrm_learner" "$@"

#!/usr/bin/env bash
# Installs the pinned packages (npm ci, when node_modules is missing or older than
# package-lock.json), generates the TypeScript types from ../../proto, compiles with tsc
# and runs the TypeScript learner against the tamrm server at ADDR; extra arguments go to
# the learner.
#
#   bash clients/node/run.sh 127.0.0.1:50051 [--task ID] [--envs N] [--steps N] [--seed N]
#
# Needs node >= 18 and npm (clients/node/README.md).
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
if [[ $# -lt 1 ]]; then
    echo "usage: $0 ADDR [learner options]" >&2
    exit 2
fi
cd "$here"
marker=node_modules/.package-lock.json
if [[ ! -f "$marker" || package-lock.json -nt "$marker" || package.json -nt "$marker" ]]; then
    npm ci --no-audit --no-fund --ignore-scripts --loglevel=error >&2
fi
npm run --silent build >&2
exec node dist/src/main.js "$@"

#!/usr/bin/env bash
# The one command of the reproduction (docs/reproduction.md): run every experiment x arm x
# seed on all cores, each run on an embedded tamrm engine of its own (or on a server with
# --address HOST:PORT; resumable: finished runs are skipped), then regenerate
# docs/reproduction.md and its plots from the raw CSVs.
#
#   experiments/reproduce.sh                # paper profile, every variant, 5 seeds
#   experiments/reproduce.sh --seeds 10     # more seeds (reuses the first 5)
#   experiments/reproduce.sh --fidelity authors --experiments cartpole   # a subset
#   experiments/reproduce.sh --quick        # smoke test; report into experiments/runs-quick/
#
# Env: TAMRM_VENV (default ./.venv-exp), TAMRM_BIN (default target/release/tamrm; recorded
# in the runs' versions only with --address).
set -euo pipefail
cd "$(dirname "$0")/.."
root=$PWD
py=${TAMRM_VENV:-$root/.venv-exp}/bin/python
export TAMRM_BIN=${TAMRM_BIN:-$root/target/release/tamrm}
export PYTHONPATH=$root/experiments${PYTHONPATH:+:$PYTHONPATH}
runs=experiments/runs
report=docs/reproduction.md
for arg in "$@"; do
    if [ "$arg" = "--quick" ]; then
        runs=experiments/runs-quick
        report=experiments/runs-quick/reproduction.md
    fi
done
"$py" -m tamrm_experiments run --out "$runs" "$@"
previous=()
if [ "$runs" = experiments/runs ] && [ -d experiments/runs-v1 ]; then
    previous=(--previous experiments/runs-v1)  # the first report's runs, shown as clean-v1
fi
"$py" -m tamrm_experiments report --runs "$runs" --out "$report" "${previous[@]}"

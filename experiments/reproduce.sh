#!/usr/bin/env bash
# The one command of the reproduction (docs/reproduction.md): run every experiment x arm x
# seed on all cores, each run on an embedded tamrm engine of its own (or on a server with
# --address HOST:PORT), into experiments/runs/; record the finished runs in the committed
# archive docs/reproduction/runs/ (add-runs: new runs only, one file each); regenerate
# docs/reproduction.md, its plots and README.md's summary from the archive. Resumable:
# runs finished in experiments/runs/ or recorded in the archive are skipped.
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
for arg in "$@"; do
    if [ "$arg" = "--quick" ]; then
        "$py" -m tamrm_experiments run --out experiments/runs-quick "$@"
        exec "$py" -m tamrm_experiments report --runs experiments/runs-quick \
            --out experiments/runs-quick/reproduction.md
    fi
done
"$py" -m tamrm_experiments run --out experiments/runs "$@"
"$py" -m tamrm_experiments add-runs --runs experiments/runs --to docs/reproduction/runs
"$py" -m tamrm_experiments report --readme README.md

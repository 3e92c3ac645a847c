#!/usr/bin/env bash
# Smoke test of the whole reproduction pipeline: lint, types, unit tests (the server backend
# included, against a local tamrm server), the --quick grid (1 seed, tiny budgets, every
# experiment x arm, each run on an embedded engine) and the report, written into a
# temporary directory (docs/reproduction.md is untouched); the runs recorded as the
# committed archive records (add-runs) must give the same page.
#
# Env: TAMRM_VENV (default ./.venv, with clients/python[sb3] installed), TAMRM_BIN (default
# target/release/tamrm). Called from .ci/run; takes 1-3 minutes.
set -euo pipefail
cd "$(dirname "$0")/.."
root=$PWD
venv=${TAMRM_VENV:-$root/.venv}
py=$venv/bin/python
export TAMRM_BIN=${TAMRM_BIN:-$root/target/release/tamrm}
export PYTHONPATH=$root/experiments${PYTHONPATH:+:$PYTHONPATH}

"$py" -m pip install --quiet --disable-pip-version-check -r experiments/requirements.txt
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT

cd experiments
echo "--- experiments: ruff"
"$py" -m ruff check .
"$py" -m ruff format --check .
echo "--- experiments: mypy"
"$py" -m mypy
echo "--- experiments: quick grid (embedded engine)"
"$py" -m tamrm_experiments run --quick --jobs 2 --out "$tmp/runs" --no-progress
echo "--- experiments: report"
"$py" -m tamrm_experiments report --runs "$tmp/runs" --out "$tmp/report/reproduction.md"
# One CSV per run of the quick grid, one plot per (experiment, variant).
want_csv=$("$py" -m tamrm_experiments run --quick --dry-run --out "$tmp/runs" | grep -c '^done')
want_png=$("$py" -m tamrm_experiments run --quick --dry-run --out "$tmp/runs" \
    | awk '{split($2, k, "/"); print k[1] "/" k[2]}' | sort -u | wc -l)
n_csv=$(find "$tmp/runs" -name 'seed*.csv' | wc -l)
n_png=$(find "$tmp/report/reproduction" -name '*.png' | wc -l)
grep -q "## Cart pole: authors" "$tmp/report/reproduction.md"
grep -q "## Claims" "$tmp/report/reproduction.md"
if [ "$want_csv" -lt 40 ] || [ "$n_csv" -ne "$want_csv" ] || [ "$n_png" -ne "$want_png" ]; then
    echo "expected $want_csv run CSVs and $want_png plots, got $n_csv and $n_png" >&2
    exit 1
fi
echo "--- experiments: add-runs (the committed layout) and the report from it"
"$py" -m tamrm_experiments add-runs --runs "$tmp/runs" --to "$tmp/archive"
"$py" -m tamrm_experiments add-runs --runs "$tmp/runs" --to "$tmp/archive" | grep -q '^added 0 runs'
cp "$tmp/report/reproduction.md" "$tmp/from-csv.md"
"$py" -m tamrm_experiments report --runs "$tmp/archive" --out "$tmp/report/reproduction.md"
# The same page from the records as from the CSVs, but for the runs directory's name.
sed "s#$tmp/archive#$tmp/runs#g" "$tmp/report/reproduction.md" | diff - "$tmp/from-csv.md"
echo "--- regime study: quick mode (E1 and E2: every arm, the tuning, freezing and report code)"
"$py" -m tamrm_regimes run --stage study --quick --families E1,E2 --jobs 2 --runs "$tmp/regimes"
"$py" -m tamrm_regimes report --quick --runs "$tmp/regimes" --out "$tmp/regimes-report/regimes.md"
grep -q "## The regime table" "$tmp/regimes-report/regimes.md"
grep -q "| E2-proc | tamrm |" "$tmp/regimes-report/regimes.md"
test "$(find "$tmp/regimes/confirm" -name 'seed*.json.gz' | wc -l)" -eq 44
# A reader reruns a run from its record and gets the same curve (SIL and the oracle pool too).
for arm in sil oracle; do
    "$py" -m tamrm_regimes rerun "$(find "$tmp/regimes/confirm/E1-det" -path "*/$arm-*" -name seed1.json.gz)"
done
echo "--- experiments: unit tests"
"$py" -m pytest -q -p no:cacheprovider tests

#!/usr/bin/env bash
# Pack the finished raw runs behind docs/reproduction.md into
# docs/reproduction/raw-runs.tar.gz: experiments/runs/ (finished runs only: CSV + JSON
# sidecar, and invocations.jsonl; no partial runs, locks or logs) and experiments/runs-v1/
# (the first report's runs), so that `tar xzf ... -C experiments` restores both.
set -euo pipefail
cd "$(dirname "$0")"
out=../docs/reproduction/raw-runs.tar.gz
list=$(mktemp)
trap 'rm -f "$list"' EXIT
for dir in runs runs-v1; do
    [ -d "$dir" ] || continue
    find "$dir" -name 'seed*.json' | sort | while read -r meta; do
        csv=${meta%.json}.csv
        if [ -f "$csv" ] && grep -q '"complete": true' "$meta"; then
            printf '%s\n%s\n' "$csv" "$meta"
        fi
    done >> "$list"
    [ -f "$dir/invocations.jsonl" ] && echo "$dir/invocations.jsonl" >> "$list"
done
tar czf "$out.tmp" --owner=0 --group=0 --mtime='2026-01-01' -T "$list"
mv "$out.tmp" "$out"
echo "packed $(grep -c 'seed.*csv$' "$list") runs into $out"

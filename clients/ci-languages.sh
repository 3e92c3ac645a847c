#!/usr/bin/env bash
# CI for the service's use from other languages (docs/languages.md), called from .ci/run:
#
# 1. the proto compatibility check: proto/compat/check_compat.py (lint, types, its tests)
#    and the current proto/ against every committed baseline;
# 2. the C++ learner (clients/cpp) and the TypeScript learner (clients/node), built from
#    scratch and run against one release server on a free port, each on a task of its own
#    for 8 envs x 2000 vector steps;
# 3. the server's GetTask stats of each task, read with the Python client, against the
#    learner's last line `episodes E pool_size P pool_version V`: episodes_completed == E,
#    steps_shaped == 8 * 2000, pool_size == P, pool_version == V, no stream left open;
# 4. each learner's error path: a refused Open and a refused CreateTask exit 1 naming the
#    status code.
#
# Installs what is missing itself: g++, cmake, gRPC's C++ packages, protoc, node and npm
# from Debian's packages (root and apt-get), the learner's npm packages from the npm
# registry (npm ci). A toolchain that cannot be installed fails the script.
#
# Env: TAMRM_BIN (default target/release/tamrm, not built here), TAMRM_VENV (default .venv,
# with clients/python[dev] installed: the Python client, pytest, hypothesis, ruff, mypy).
set -euo pipefail
cd "$(dirname "$0")/.."
root=$PWD
bin=${TAMRM_BIN:-$root/target/release/tamrm}
venv=${TAMRM_VENV:-$root/.venv}
py=$venv/bin/python
envs=8
steps=2000
start=$(date +%s)
say() { echo "--- languages: $* ($(( $(date +%s) - start ))s)"; }

for f in "$bin" "$py"; do
    if [[ ! -x "$f" ]]; then
        echo "ci-languages.sh: $f is missing (build the server and the .venv first)" >&2
        exit 1
    fi
done

say "toolchains (Debian's packages where missing)"
missing=()
command -v g++ >/dev/null || missing+=(g++)
command -v cmake >/dev/null || missing+=(cmake)
command -v protoc >/dev/null || missing+=(protobuf-compiler)
command -v grpc_cpp_plugin >/dev/null || missing+=(protobuf-compiler-grpc)
[[ -f /usr/include/grpcpp/grpcpp.h ]] || missing+=(libgrpc++-dev)
[[ -f /usr/include/google/protobuf/message.h ]] || missing+=(libprotobuf-dev)
command -v node >/dev/null || missing+=(nodejs)
command -v npm >/dev/null || missing+=(npm)
if (( ${#missing[@]} )); then
    echo "installing ${missing[*]}"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
        "${missing[@]}" >/dev/null
fi
for tool in g++ cmake protoc grpc_cpp_plugin node npm; do
    command -v "$tool" >/dev/null || { echo "ci-languages.sh: $tool is still missing" >&2; exit 1; }
done
echo "g++ $(g++ -dumpversion), $(cmake --version | head -1), $(protoc --version)," \
    "node $(node --version), npm $(npm --version)"

say "proto compatibility: lint, types, tests of the checker, then proto/ against the baselines"
(
    cd proto/compat
    "$venv/bin/ruff" check .
    "$venv/bin/ruff" format --check .
    "$venv/bin/mypy"
    PYTHONDONTWRITEBYTECODE=1 "$py" -m pytest -q -p no:cacheprovider .
    "$py" check_compat.py
)

tmp=$(mktemp -d)
server_pid=
cleanup() {
    if [[ -n "$server_pid" ]]; then
        kill "$server_pid" 2>/dev/null || true
        wait "$server_pid" 2>/dev/null || true
    fi
    rm -rf "$tmp"
}
trap cleanup EXIT

say "server on a free port"
"$bin" serve --listen 127.0.0.1:0 --port-file "$tmp/port" >"$tmp/server.log" 2>&1 &
server_pid=$!
for _ in $(seq 200); do
    [[ -s "$tmp/port" ]] && break
    kill -0 "$server_pid" 2>/dev/null || { cat "$tmp/server.log"; exit 1; }
    sleep 0.1
done
[[ -s "$tmp/port" ]] || { echo "the server wrote no port file in 20 s" >&2; exit 1; }
addr=$(cat "$tmp/port")
echo "server at $addr"

say "C++ and TypeScript learners, built and run side by side ($envs envs x $steps steps each)"
run_learner() {  # LANG: builds and runs clients/LANG/run.sh on task ci/LANG/<pid>
    local lang=$1 t0=$SECONDS rc=0
    bash "clients/$lang/run.sh" "$addr" --task "ci/$lang/$$" --envs "$envs" --steps "$steps" \
        >"$tmp/$lang.out" 2>"$tmp/$lang.err" || rc=$?
    echo "$rc $(( SECONDS - t0 ))" >"$tmp/$lang.rc"
}
run_learner cpp &
cpp_job=$!
run_learner node &
node_job=$!
wait "$cpp_job" "$node_job"
failed=0
for lang in cpp node; do
    read -r rc secs <"$tmp/$lang.rc"
    echo "$lang: exit $rc after ${secs}s (build included); last line: $(tail -1 "$tmp/$lang.out")"
    if [[ "$rc" != 0 ]]; then
        failed=1
        tail -30 "$tmp/$lang.err" "$tmp/$lang.out"
    fi
done
(( failed == 0 )) || exit 1

say "the server's GetTask stats against each learner's last line (Python client)"
"$py" - "$addr" "$$" "$envs" "$steps" "$tmp/cpp.out" "$tmp/node.out" <<'EOF'
import re
import sys
from pathlib import Path

import tamrm

addr, pid, envs, steps, *outputs = sys.argv[1:]
want_steps = int(envs) * int(steps)
failures = []
with tamrm.Client(addr) as client:
    for out in map(Path, outputs):
        lang = out.stem
        last = out.read_text().splitlines()[-1]
        m = re.fullmatch(r"episodes (\d+) pool_size (\d+) pool_version (\d+)", last)
        if m is None:
            want = "episodes E pool_size P pool_version V"
            failures.append(f"{lang}: last line {last!r} is not {want!r}")
            continue
        episodes, pool_size, pool_version = map(int, m.groups())
        stats = client.get_task(f"ci/{lang}/{pid}").stats
        checks = {
            "episodes_completed == E": (stats.episodes_completed, episodes),
            f"steps_shaped == {envs} * {steps}": (stats.steps_shaped, want_steps),
            "pool_size == P": (stats.pool_size, pool_size),
            "pool_version == V": (stats.pool_version, pool_version),
            "open_streams == 0": (stats.open_streams, 0),
        }
        for name, (got, want) in checks.items():
            status = "ok" if got == want else "FAILED"
            print(f"{lang}: {name}: server {got}, learner {want}: {status}")
            if got != want:
                failures.append(f"{lang}: {name}: server {got}, learner {want}")
        # A learner that ended no episode, or stored none, has not exercised the pool.
        if episodes == 0 or pool_size == 0:
            failures.append(f"{lang}: E = {episodes}, P = {pool_size}: the pool was not used")
if failures:
    sys.exit("\n".join(failures))
EOF

say "error paths: a refused Open and a refused CreateTask exit 1 with the status"
expect_failure() {  # LANG CALL CODE COMMAND...: COMMAND must exit 1 printing "CALL failed: CODE"
    local lang=$1 want="$2 failed: $3" rc=0
    shift 3
    "$@" >"$tmp/err.out" 2>"$tmp/err.err" || rc=$?
    if [[ "$rc" != 1 ]] || ! grep -q "$want" "$tmp/err.err"; then
        echo "FAILED: $* exited $rc, wanted 1 and '$want' on stderr:" >&2
        cat "$tmp/err.err" >&2
        exit 1
    fi
    echo "$lang: exit 1 with $(head -1 "$tmp/err.err")"
}
cpp_bin=clients/cpp/build/tamrm_learner
node_main=clients/node/dist/src/main.js
expect_failure cpp Shape RESOURCE_EXHAUSTED "$cpp_bin" "$addr" --envs 100000
expect_failure cpp CreateTask INVALID_ARGUMENT "$cpp_bin" "$addr" --task "not a task id"
expect_failure node Shape RESOURCE_EXHAUSTED node "$node_main" "$addr" --envs 100000
expect_failure node CreateTask INVALID_ARGUMENT node "$node_main" "$addr" --task "not a task id"

say "done"

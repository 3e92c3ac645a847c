#!/usr/bin/env bash
# Coverage-guided fuzzing with libFuzzer on the stable toolchain (docs/fuzzing.md).
#
#   fuzz/run.sh build                     build the targets (and write missing seed corpora)
#   fuzz/run.sh run SECONDS [TARGET...]   build, then fuzz each target for SECONDS, one
#                                         after the other (default: every target)
#   fuzz/run.sh cpu SECONDS TARGET        build, then fuzz TARGET until it has used SECONDS
#                                         of CPU time (user + system, all its threads), then
#                                         stop it gracefully (SIGUSR1): the long runs, fair
#                                         however busy the machine is
#   fuzz/run.sh replay                    build, then run every input of fuzz/regressions/
#                                         once through its target
#
# Coverage: LLVM SanitizerCoverage through the stable `-C passes=sancov-module` and
# `-C llvm-args` options (what `cargo fuzz` passes, minus the nightly-only `-Z sanitizer`),
# plus debug assertions and overflow checks; `--target` keeps the flags off build scripts
# and proc macros. New inputs go to fuzz/work/<target>/ (not committed), the committed
# corpus fuzz/corpus/<target>/ is read, a crash is written to fuzz/artifacts/<target>/ and
# fails the run; libFuzzer's output is kept in fuzz/logs/<target>.log.
set -euo pipefail
cd "$(dirname "$0")"
all=(shape_stream unary disk)
triple=$(rustc -vV | sed -n 's/^host: //p')
bin=target/$triple/release

build() {
    local t
    export RUSTFLAGS="--cfg fuzzing -C passes=sancov-module \
 -C llvm-args=-sanitizer-coverage-level=4 \
 -C llvm-args=-sanitizer-coverage-inline-8bit-counters \
 -C llvm-args=-sanitizer-coverage-pc-table \
 -C llvm-args=-sanitizer-coverage-trace-compares \
 -C debug-assertions -C overflow-checks"
    cargo build --release --locked --target "$triple" --bins
    for t in "${all[@]}"; do
        if [ ! -d "corpus/$t" ]; then
            mkdir -p "corpus/$t"
            TAMRM_FUZZ_SEEDS="corpus/$t" "$bin/$t" -runs=0 "corpus/$t" > /dev/null 2>&1
        fi
    done
}

# fuzz TARGET SECONDS [CPU_SECONDS]: libFuzzer on TARGET for SECONDS of wall time, or, with
# CPU_SECONDS, until the process has used that much CPU time (then SIGUSR1: libFuzzer
# finishes the input at hand, prints its final stats and exits 0).
fuzz() {
    local t=$1 seconds=$2 cpu=${3:-}
    mkdir -p "work/$t" "artifacts/$t" logs
    "$bin/$t" "work/$t" "corpus/$t" -max_total_time="$seconds" -timeout=20 \
        -rss_limit_mb=2048 -max_len=8192 -print_final_stats=1 \
        -artifact_prefix="artifacts/$t/" > "logs/$t.log" 2>&1 &
    local pid=$! started
    started=$(date +%s)
    if [ -n "$cpu" ]; then
        local tck used
        tck=$(getconf CLK_TCK)
        while kill -0 "$pid" 2> /dev/null; do
            # utime and stime (fields 14, 15 of /proc/PID/stat; the name in field 2 has
            # no blanks here) cover every thread of the process.
            used=$(awk -v t="$tck" '{ print int(($14 + $15) / t) }' "/proc/$pid/stat" 2> /dev/null || echo 0)
            if [ "$used" -ge "$cpu" ]; then
                kill -USR1 "$pid" 2> /dev/null || true
                break
            fi
            sleep 5
        done
    fi
    if ! wait "$pid"; then
        echo "!!! $t failed (a crash, a leak of memory or a timeout):"
        tail -40 "logs/$t.log"
        return 1
    fi
    echo "$t: wall time $(($(date +%s) - started)) s"
    grep -E '^#[0-9]+[[:space:]]+DONE|^stat::(number_of_executed_units|average_exec_per_sec)|exiting as requested' "logs/$t.log" |
        sed "s/^/$t: /"
}

case "${1:-}" in
build) build ;;
run)
    seconds=${2:?usage: fuzz/run.sh run SECONDS [TARGET...]}
    shift 2
    targets=("$@")
    [ ${#targets[@]} -gt 0 ] || targets=("${all[@]}")
    build
    status=0
    for t in "${targets[@]}"; do
        echo "=== fuzzing $t for ${seconds}s"
        fuzz "$t" "$seconds" || status=1
    done
    exit $status
    ;;
cpu)
    cpu=${2:?usage: fuzz/run.sh cpu SECONDS TARGET}
    t=${3:?usage: fuzz/run.sh cpu SECONDS TARGET}
    build
    echo "=== fuzzing $t until it has used ${cpu}s of CPU time"
    # The wall-time cap only guards against a run that never gets the CPU.
    fuzz "$t" $((cpu * 20)) "$cpu"
    ;;
replay)
    build
    for t in "${all[@]}"; do
        if compgen -G "regressions/$t/*" > /dev/null; then
            echo "=== replaying regressions/$t"
            "$bin/$t" regressions/"$t"/* 2>&1 | tail -2
        fi
    done
    ;;
*)
    echo "usage: fuzz/run.sh build | run SECONDS [TARGET...] | cpu SECONDS TARGET | replay" >&2
    exit 2
    ;;
esac

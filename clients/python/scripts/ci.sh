#!/usr/bin/env bash
# CI for the Python client (clients/python). Idempotent; safe to run repeatedly.
#
#   bash clients/python/scripts/ci.sh            # install, then check
#   bash clients/python/scripts/ci.sh install    # the venv and the client only
#   bash clients/python/scripts/ci.sh check      # lint, types and tests of an installed client
#
# - creates (or reuses) the virtualenv $TAMRM_VENV (default: <repo>/.venv),
# - installs the client with its [dev,sb3,trial,pettingzoo,rllib] extras (editable; maturin
#   compiles the native extension, clients/python/native, from source with the Rust
#   toolchain; ray[rllib] pins gymnasium for the whole suite, docs/decisions/
#   rllib-extra-shares-the-ci-venv.md), and the PettingZoo env families the tests and
#   examples run (MPE2, classic's pygame),
# - runs ruff check, ruff format --check, mypy (src/tamrm, strict, generated stubs excluded),
# - runs pytest on clients/python/tests against the real server binary
#   $TAMRM_BIN (default: <repo>/target/release/tamrm).
#
# It does NOT build the Rust binary: run `cargo build --release` first.
set -euo pipefail

CLIENT_DIR="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
REPO_ROOT="$(cd "$CLIENT_DIR/../.." && pwd)"
VENV="${TAMRM_VENV:-$REPO_ROOT/.venv}"
export TAMRM_BIN="${TAMRM_BIN:-$REPO_ROOT/target/release/tamrm}"
PYTHON="${PYTHON:-python3}"
PHASE="${1:-all}"
case "$PHASE" in
    all | install | check) ;;
    *) echo "ci.sh: unknown phase '$PHASE' (all, install or check)" >&2; exit 2 ;;
esac

export PIP_DISABLE_PIP_VERSION_CHECK=1
export PYTHONDONTWRITEBYTECODE=1

step() { printf '\n=== %s ===\n' "$*"; }

if [[ ! -x "$TAMRM_BIN" ]]; then
    echo "ci.sh: server binary not found at TAMRM_BIN=$TAMRM_BIN" >&2
    echo "ci.sh: build it first: (cd $REPO_ROOT && cargo build --release)" >&2
    exit 1
fi

if [[ "$PHASE" != check ]]; then
    step "virtualenv $VENV"
    if [[ ! -x "$VENV/bin/python" ]]; then
        "$PYTHON" -m venv "$VENV"
    fi
    "$VENV/bin/python" --version

    step "pip install -e clients/python[dev,sb3,trial,pettingzoo,rllib]"
    "$VENV/bin/python" -m pip install -q --upgrade pip
    "$VENV/bin/python" -m pip install -q -e "$CLIENT_DIR[dev,sb3,trial,pettingzoo,rllib]"

    step "PettingZoo envs for tests/test_pettingzoo.py and examples/pettingzoo_sb3.py (wheels only)"
    "$VENV/bin/python" -m pip install -q --only-binary=:all: "mpe2>=1.1,<2" "pygame-ce>=2.3"
fi
[[ "$PHASE" == install ]] && exit 0

cd "$CLIENT_DIR"

step "ruff check"
"$VENV/bin/ruff" check .

step "ruff format --check"
"$VENV/bin/ruff" format --check .

step "mypy (strict, src/tamrm)"
"$VENV/bin/mypy"

step "pytest (server: $TAMRM_BIN)"
"$VENV/bin/python" -m pytest tests -q -p no:cacheprovider

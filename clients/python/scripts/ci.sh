#!/usr/bin/env bash
# CI for the Python client (clients/python). Idempotent; safe to run repeatedly.
#
#   bash clients/python/scripts/ci.sh            # install, then check
#   bash clients/python/scripts/ci.sh install    # the wheel, then a venv with it
#   bash clients/python/scripts/ci.sh develop    # a venv with an editable source install
#   bash clients/python/scripts/ci.sh check      # lint, types and tests of an installed client
#
# - install (what CI does, as a user would): builds the wheel and the sdist
#   (scripts/build-wheels.sh, into $TAMRM_DIST, default <repo>/target/dist), then creates
#   the virtualenv $TAMRM_VENV (default: <repo>/.venv) and installs the wheel into it,
#   with its [dev,sb3,trial,pettingzoo,rllib] extras, with no Rust toolchain on PATH;
#   ray[rllib] pins gymnasium for the whole suite
#   (docs/decisions/rllib-extra-shares-the-ci-venv.md); and the PettingZoo env families
#   the tests and examples run (MPE2, classic's pygame),
# - develop: the same venv with the client installed editable instead (maturin compiles
#   the native extension from source with the Rust toolchain), for working on it,
# - check: ruff check, ruff format --check, mypy (src/tamrm, strict, generated stubs
#   excluded), then pytest on clients/python/tests; with the wheel installed, against the
#   server binary inside it (TAMRM_BIN is ignored, and cargo is off PATH), else against
#   $TAMRM_BIN (default: <repo>/target/release/tamrm).
set -euo pipefail

CLIENT_DIR="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
REPO_ROOT="$(cd "$CLIENT_DIR/../.." && pwd)"
VENV="${TAMRM_VENV:-$REPO_ROOT/.venv}"
export TAMRM_BIN="${TAMRM_BIN:-$REPO_ROOT/target/release/tamrm}"
PYTHON="${PYTHON:-python3}"
PHASE="${1:-all}"
case "$PHASE" in
    all | install | develop | check) ;;
    *) echo "ci.sh: unknown phase '$PHASE' (all, install, develop or check)" >&2; exit 2 ;;
esac
DIST="${TAMRM_DIST:-$REPO_ROOT/target/dist}"
# PATH without the Rust toolchain: what a user who installs the wheel has.
NO_RUST_PATH=$(tr ':' '\n' <<<"$PATH" | grep -v -e '/\.cargo/bin' -e '/\.rustup/' | paste -sd: -)

export PIP_DISABLE_PIP_VERSION_CHECK=1
export PYTHONDONTWRITEBYTECODE=1

step() { printf '\n=== %s ===\n' "$*"; }

if [[ ! -x "$TAMRM_BIN" ]]; then
    echo "ci.sh: server binary not found at TAMRM_BIN=$TAMRM_BIN" >&2
    echo "ci.sh: build it first: (cd $REPO_ROOT && cargo build --release)" >&2
    exit 1
fi

if [[ "$PHASE" != check ]]; then
    if [[ "$PHASE" == develop ]]; then
        step "virtualenv $VENV"
        [[ -x "$VENV/bin/python" ]] || "$PYTHON" -m venv "$VENV"
        "$VENV/bin/python" -m pip install -q --upgrade pip
        step "pip install -e clients/python[dev,sb3,trial,pettingzoo,rllib] (compiles the extension)"
        "$VENV/bin/python" -m pip install -q -e "$CLIENT_DIR[dev,sb3,trial,pettingzoo,rllib]"
    else
        step "the wheel and the sdist (scripts/build-wheels.sh -> $DIST)"
        bash "$CLIENT_DIR/scripts/build-wheels.sh" "$DIST"
        wheel=$(ls "$DIST"/tamrm-*.whl)
        step "a fresh virtualenv $VENV with the wheel, no Rust toolchain on PATH"
        rm -rf "$VENV"
        PATH="$NO_RUST_PATH" "$PYTHON" -m venv "$VENV"
        if PATH="$NO_RUST_PATH" command -v cargo >/dev/null; then
            echo "ci.sh: cargo is still on PATH=$NO_RUST_PATH" >&2; exit 1
        fi
        PATH="$NO_RUST_PATH" "$VENV/bin/python" -m pip install -q --upgrade pip
        PATH="$NO_RUST_PATH" "$VENV/bin/python" -m pip install -q --only-binary=tamrm \
            "$wheel[dev,sb3,trial,pettingzoo,rllib]"
    fi
    step "PettingZoo envs for tests/test_pettingzoo.py and examples/pettingzoo_sb3.py (wheels only)"
    "$VENV/bin/python" -m pip install -q --only-binary=:all: "mpe2>=1.1,<2" "pygame-ce>=2.3"
fi
[[ "$PHASE" == install || "$PHASE" == develop ]] && exit 0

cd "$CLIENT_DIR"

step "ruff check"
"$VENV/bin/ruff" check .

step "ruff format --check"
"$VENV/bin/ruff" format --check .

step "mypy (strict, src/tamrm)"
"$VENV/bin/mypy"

wheel_server=$("$VENV/bin/python" -c 'from tamrm._server import installed_binary as b; print(b() or "")')
if [[ -n "$wheel_server" ]]; then
    step "pytest (installed from the wheel; server: $wheel_server; no Rust on PATH)"
    env -u TAMRM_BIN PATH="$NO_RUST_PATH" "$VENV/bin/python" -m pytest tests -q -p no:cacheprovider
else
    step "pytest (source install; server: $TAMRM_BIN)"
    "$VENV/bin/python" -m pytest tests -q -p no:cacheprovider
fi

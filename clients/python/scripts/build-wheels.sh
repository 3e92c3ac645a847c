#!/usr/bin/env bash
# Builds what users install, into OUT (default clients/python/dist):
#
# - the wheel: abi3 (CPython >= 3.10), x86_64 Linux, manylinux_2_17 (the extension is
#   linked by zig against glibc 2.17, from the `ziglang` package on PyPI), with the
#   server inside: the static `tamrm` binary of docker/build.sh, installed by pip as the
#   `tamrm` command (a data script) that `tamrm.local_server()` and `python -m tamrm` run;
# - the sdist: only what building the extension needs (no server binary: built from the
#   sdist, the package is the client alone and finds a server through TAMRM_BIN or PATH).
#
#   bash clients/python/scripts/build-wheels.sh [OUT]
#
# Then it proves the wheel's tag (`auditwheel show`: the extension needs no newer glibc
# symbol than manylinux_2_17 allows; the server binary needs no libc at all) and the
# sdist's size (at most 2 MB). Needs the Rust toolchain and network access to PyPI (the
# build tools go into $WHEEL_TOOLS, default target/wheel-tools) and crates.io.
set -euo pipefail
CLIENT_DIR="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
REPO_ROOT="$(cd "$CLIENT_DIR/../.." && pwd)"
OUT="$(mkdir -p "${1:-$CLIENT_DIR/dist}" && cd "${1:-$CLIENT_DIR/dist}" && pwd)"
TOOLS="${WHEEL_TOOLS:-$REPO_ROOT/target/wheel-tools}"
PYTHON="${PYTHON:-python3}"
MAX_SDIST_BYTES=$((2 * 1024 * 1024))
export PIP_DISABLE_PIP_VERSION_CHECK=1

step() { printf '\n--- build-wheels: %s\n' "$*"; }

step "build tools in $TOOLS (maturin, ziglang, auditwheel)"
[[ -x "$TOOLS/bin/python" ]] || "$PYTHON" -m venv "$TOOLS"
"$TOOLS/bin/python" -m pip install -q "maturin==1.16.0" "ziglang==0.17.1" "auditwheel==6.8.2" "wheel==0.48.0"
maturin="$TOOLS/bin/maturin"
# maturin runs zig as `python -m ziglang`: the tools' python must come first on PATH.
export PATH="$TOOLS/bin:$PATH"
# The commit the server and the extension report (tamrm_build_info, --version).
TAMRM_COMMIT="$(git -C "$REPO_ROOT" rev-parse --short=12 HEAD 2>/dev/null || echo unknown)"
export TAMRM_COMMIT

rm -f "$OUT"/tamrm-*.whl "$OUT"/tamrm-*.tar.gz
cd "$CLIENT_DIR"

step "sdist"
"$maturin" sdist --out "$OUT"
sdist=$(ls "$OUT"/tamrm-*.tar.gz)
size=$(stat -c %s "$sdist")
echo "$(basename "$sdist"): $size bytes"
if (( size > MAX_SDIST_BYTES )); then
    echo "build-wheels: the sdist is $size bytes, over $MAX_SDIST_BYTES: what it holds that a build does not need:" >&2
    tar tzvf "$sdist" | sort -k3 -n -r | head -20 >&2
    exit 1
fi

# The sdist must build on its own: its manifests must name only files it holds (a
# [[bench]] whose file is left out fails the build). The full build from it is
# benchmarks/wheel_cost.py's source install.
unpacked=$(mktemp -d)
tar xzf "$sdist" -C "$unpacked"
"$TOOLS/bin/python" - "$(ls -d "$unpacked"/tamrm-*)" <<'PY'
import sys, tomllib
from pathlib import Path
root = Path(sys.argv[1])
missing = []
for manifest in root.rglob("Cargo.toml"):
    toml = tomllib.loads(manifest.read_text())
    for kind, folder in (("bin", "src/bin"), ("bench", "benches"), ("test", "tests"), ("example", "examples")):
        for target in toml.get(kind, []):
            path = target.get("path") or f"{folder}/{target['name']}.rs"
            if not (manifest.parent / path).exists():
                missing.append(f"{manifest.relative_to(root)}: [[{kind}]] {target['name']} at {path}")
    lib = toml.get("lib", {}).get("path")
    if lib and not (manifest.parent / lib).exists():
        missing.append(f"{manifest.relative_to(root)}: [lib] at {lib}")
if missing:
    sys.exit("build-wheels: the sdist lacks files its manifests name:\n  " + "\n  ".join(missing))
PY
rm -rf "$unpacked"

step "the static server binary (docker/build.sh)"
bin=$(cd "$REPO_ROOT" && TAMRM_BINARY_ONLY=1 bash docker/build.sh)

step "wheel (zig, manylinux2014)"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
"$maturin" build --release --locked --zig --compatibility manylinux2014 --out "$work"
# The server goes in as the data script `tamrm` (pip installs it as the `tamrm` command);
# `wheel pack` writes the RECORD anew with its hash.
"$TOOLS/bin/python" -m wheel unpack --dest "$work/unpacked" "$work"/tamrm-*.whl
tree=$(ls -d "$work"/unpacked/tamrm-*)
scripts="$tree/$(basename "$tree").data/scripts"
mkdir -p "$scripts"
cp "$bin" "$scripts/tamrm"
strip "$scripts/tamrm"
chmod 755 "$scripts/tamrm"
"$TOOLS/bin/python" -m wheel pack --dest-dir "$OUT" "$tree"
wheel=$(ls "$OUT"/tamrm-*.whl)

step "check: $(basename "$wheel")"
"$TOOLS/bin/auditwheel" show "$wheel" | tee "$OUT/auditwheel.txt"
grep -q 'manylinux_2_17_x86_64' "$OUT/auditwheel.txt"
case "$(basename "$wheel")" in
    *-cp310-abi3-*manylinux_2_17_x86_64*.whl) ;;
    *) echo "build-wheels: unexpected wheel tag: $(basename "$wheel")" >&2; exit 1 ;;
esac
listing=$("$TOOLS/bin/python" -m zipfile -l "$wheel")
grep -q 'tamrm-[^/]*\.data/scripts/tamrm ' <<<"$listing" \
    || { echo "build-wheels: the server binary is not in the wheel" >&2; exit 1; }
ls -l "$OUT"

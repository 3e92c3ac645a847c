#!/usr/bin/env bash
# Builds the image tamrm:latest without registry access: a static tamrm (static glibc,
# x86_64) is built on the host, then packed by docker/Dockerfile with
# --build-arg TAMRM_BIN_STAGE=prebuilt (only FROM scratch stages run, so nothing is pulled)
# with podman or docker, whichever works.
#
#   bash docker/build.sh [IMAGE]          # IMAGE defaults to tamrm:latest
#
# Environment:
#   TAMRM_ENGINE      podman | docker (default: podman if `podman info` works, else docker
#                     if `docker info` reaches a daemon)
#   TAMRM_STATIC_BIN  use this prebuilt static binary instead of running cargo
#   TAMRM_BINARY_ONLY=1  only build and check the binary, print its path, build no image
#   CARGO_TARGET_DIR  as for cargo (default: ./target)
# With a registry, `docker build -f docker/Dockerfile .` builds the same image from source
# in the official Rust image (docs/deployment.md).
set -euo pipefail
cd "$(dirname "$0")/.."
image="${1:-tamrm:latest}"
target=x86_64-unknown-linux-gnu

pick_engine() {
    if [[ -n "${TAMRM_ENGINE:-}" ]]; then echo "$TAMRM_ENGINE"; return; fi
    if command -v podman >/dev/null && podman info >/dev/null 2>&1; then echo podman; return; fi
    # A docker client can exist without a daemon: only use it if it reaches one.
    if command -v docker >/dev/null && docker info >/dev/null 2>&1; then echo docker; return; fi
    echo "build.sh: neither podman nor a docker daemon works (apt-get install -y podman runc)" >&2
    return 1
}
[[ "${TAMRM_BINARY_ONLY:-}" == 1 ]] || engine=$(pick_engine)

if [[ -n "${TAMRM_STATIC_BIN:-}" ]]; then
    bin="$TAMRM_STATIC_BIN"
else
    echo "build.sh: building a static tamrm (cargo, --target $target, +crt-static)" >&2
    RUSTFLAGS="-C target-feature=+crt-static" \
        cargo build --release --locked --target "$target" -p tamrm
    bin="${CARGO_TARGET_DIR:-target}/$target/release/tamrm"
fi
[[ -x "$bin" ]] || { echo "build.sh: no executable at $bin" >&2; exit 1; }
# The image has no libc and no loader: refuse a dynamically linked binary.
if LC_ALL=C readelf -l "$bin" 2>/dev/null | grep -q "Requesting program interpreter" \
    || LC_ALL=C readelf -d "$bin" 2>/dev/null | grep -q "(NEEDED)"; then
    echo "build.sh: $bin is dynamically linked; build it with RUSTFLAGS=\"-C target-feature=+crt-static\"" >&2
    exit 1
fi
if [[ "${TAMRM_BINARY_ONLY:-}" == 1 ]]; then realpath "$bin"; exit 0; fi

ctx=$(mktemp -d)
trap 'rm -rf "$ctx"' EXIT
cp "$bin" "$ctx/tamrm"
strip "$ctx/tamrm" 2>/dev/null || true
mkdir "$ctx/data"

echo "build.sh: $engine build -> $image" >&2
args=(--build-arg TAMRM_BIN_STAGE=prebuilt -t "$image")
old=$("$engine" image inspect --format '{{.Id}}' "$image" 2>/dev/null || true)
case "$engine" in
    # --format docker keeps HEALTHCHECK (the OCI image format has no field for it).
    podman) podman build --format docker -f docker/Dockerfile "${args[@]}" "$ctx" ;;
    # BuildKit skips the unused `build` stage; the legacy builder would try to pull it.
    docker) DOCKER_BUILDKIT=1 docker build -f docker/Dockerfile "${args[@]}" "$ctx" ;;
    *) echo "build.sh: unknown engine $engine" >&2; exit 1 ;;
esac
# The image this tag named before, if nothing else uses it, is now only garbage (rmi refuses
# an image with another tag or a container).
new=$("$engine" image inspect --format '{{.Id}}' "$image")
if [[ -n "$old" && "$old" != "$new" ]]; then "$engine" rmi "$old" >/dev/null 2>&1 || true; fi
"$engine" image inspect --format '{{.Size}}' "$new" \
    | awk -v i="$image" '{ printf "build.sh: %s is %.1f MB\n", i, $1 / 1e6 }' >&2

#!/usr/bin/env bash
# Container test of the tamrm image (docs/deployment.md), with podman:
#   build tamrm:latest (docker/build.sh), run it with a named volume on a free port, wait
#   for HEALTHCHECK to pass, create a task and shape episodes through the Python client,
#   find them counted on the metrics endpoint (GET /metrics), stop and start the container and find the pool and task intact, check that the server
#   does not run as root and that the image is at most 20 MB; then run a second container
#   with TLS and an API key file mounted read-only (certificates made by trustme, the key
#   by `tamrm key`), wait for its unchanged HEALTHCHECK, and check that a client with
#   the key and the CA shapes while one without the key, with a wrong key, or without
#   the CA is refused; then remove what it made.
#
#   bash docker/test.sh
#
# Needs podman and runc (installed with apt-get when missing and run as root), the Rust
# toolchain, and a Python environment with the tamrm client ($TAMRM_VENV, default .venv,
# as clients/python/scripts/ci.sh makes it). Environment:
#   TAMRM_STATIC_BIN   pack this static binary instead of building one (docker/build.sh)
#   TAMRM_IMAGE        image tag to build and test (default tamrm:latest)
#   TAMRM_MAX_IMAGE_MB size limit (default 20, in 10^6 bytes)
# In sandboxes where crun and rootless networking fail, the container runs with
# `--runtime runc --network host` and a containers.conf with `default_ulimits = []`
# (written to a temporary file unless CONTAINERS_CONF is set); both also work elsewhere.
# Without systemd, podman logs errors about health-check timers on run/start/stop; those go
# to a file (printed on failure): the test runs the checks itself.
set -euo pipefail
cd "$(dirname "$0")/.."
start=$(date +%s)
say() { echo "docker/test.sh: $* ($(( $(date +%s) - start ))s)" >&2; }
fail() { say "FAIL: $*"; exit 1; }

image="${TAMRM_IMAGE:-tamrm:latest}"
max_mb="${TAMRM_MAX_IMAGE_MB:-20}"
venv="${TAMRM_VENV:-.venv}"
py="$venv/bin/python"
[[ -x "$py" ]] || fail "no Python at $py (run clients/python/scripts/ci.sh, or set TAMRM_VENV)"
"$py" -c "import tamrm" || fail "$py cannot import tamrm"

work=$(mktemp -d)
name="tamrm-test-$$"
vol="tamrm-test-$$"
cleanup() {
    local rc=$?
    if [[ $rc -ne 0 ]]; then
        for c in "$name" "$name-secure"; do
            podman container exists "$c" 2>/dev/null || continue
            echo "--- log of $c" >&2
            podman logs "$c" 2>&1 | tail -n 40 >&2 || true
        done
        echo "--- podman's stderr" >&2
        tail -n 20 "$work/podman.err" >&2 || true
    fi
    podman rm -f -t 0 "$name" >/dev/null 2>&1 || true
    podman rm -f -t 0 "$name-secure" >/dev/null 2>&1 || true
    podman volume rm -f "$vol" >/dev/null 2>&1 || true
    rm -rf "$work"
    exit $rc
}
trap cleanup EXIT
trap 'exit 130' INT TERM
if [[ -z "${CONTAINERS_CONF:-}" ]]; then
    printf '[containers]\ndefault_ulimits = []\n' >"$work/containers.conf"
    export CONTAINERS_CONF="$work/containers.conf"
fi

# podman is installed (when missing) while cargo builds the static binary.
installer=
if ! command -v podman >/dev/null || ! command -v runc >/dev/null; then
    [[ $(id -u) -eq 0 ]] && command -v apt-get >/dev/null \
        || fail "podman and runc are needed (apt-get install -y podman runc)"
    say "installing podman and runc (in the background, log in $work/apt.log)"
    { apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q podman runc; } \
        >"$work/apt.log" 2>&1 &
    installer=$!
fi
say "building the static binary"
bin=$(TAMRM_BINARY_ONLY=1 bash docker/build.sh)
if [[ -n "$installer" ]]; then
    wait "$installer" || { tail -n 20 "$work/apt.log" >&2; fail "apt-get install podman runc failed"; }
    say "podman installed"
fi
say "building $image"
TAMRM_STATIC_BIN="$bin" TAMRM_ENGINE=podman bash docker/build.sh "$image"

say "checking the image"
size=$(podman image inspect --format '{{.Size}}' "$image")
say "image size: $size bytes ($(( size / 1000000 )) MB; limit $max_mb MB)"
(( size <= max_mb * 1000000 )) || fail "image is $size bytes, over $max_mb MB"
user=$(podman image inspect --format '{{.Config.User}}' "$image")
[[ -n "$user" && "${user%%:*}" != 0 && "${user%%:*}" != root ]] || fail "image user is '$user'"
hc=$(podman image inspect --format '{{json .Config.Healthcheck}}' "$image")
[[ "$hc" == *'"/tamrm","healthcheck"'* ]] || fail "image has no HEALTHCHECK /tamrm healthcheck: $hc"

free_port() { "$py" -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }
port=$(free_port)
mport=$(free_port)
[[ "$mport" != "$port" ]] || mport=$(free_port)
podman volume create "$vol" >/dev/null
run() {
    # The hardening of docker/compose.yaml: read-only root, no capabilities.
    podman run -d --runtime runc --network host --name "$name" -v "$vol:/data" \
        --read-only --cap-drop ALL --security-opt no-new-privileges \
        -e TAMRM_LISTEN="127.0.0.1:$port" -e TAMRM_METRICS_LISTEN="127.0.0.1:$mport" \
        "$image" >/dev/null 2>>"$work/podman.err"
}
wait_healthy() {
    # `podman healthcheck run` runs the image's HEALTHCHECK in the container now (the
    # periodic checks need systemd timers, which a CI container may not have).
    local c="${1:-$name}" p="${2:-$port}"
    for _ in $(seq 1 60); do
        [[ $(podman inspect --format '{{.State.Running}}' "$c") == true ]] \
            || fail "the container $c stopped"
        if podman healthcheck run "$c" >/dev/null 2>&1; then
            say "$c healthy on 127.0.0.1:$p"
            return
        fi
        sleep 0.5
    done
    fail "$c not healthy after 30 s"
}
client() { "$py" - "$port" "$work/pool.json" "$@" <<'PY'
import json, sys
import numpy as np
import tamrm

port, snapshot, mode = sys.argv[1], sys.argv[2], sys.argv[3]
client = tamrm.Client(f"127.0.0.1:{port}")

def state() -> dict:
    pool = client.get_pool("docker-test")
    task = client.get_task("docker-test")
    return {
        "pool_version": pool.pool_version,
        "trajectories": [(t.seq, t.score, t.actions.tolist()) for t in pool.trajectories],
        "config": repr(task.config),
    }

if mode == "fill":
    client.create_task("docker-test", num_actions=3, pool_capacity=8, k=2, start_step=0,
                       min_pool_size=1)
    rng = np.random.default_rng(11)
    with client.session("docker-test", 4) as s:
        for i in range(60):
            r = s.step(rng.integers(0, 3, 4), rng.normal(size=4),
                       terminated=np.full(4, i % 6 == 5),
                       values=rng.normal(size=4), next_values=rng.normal(size=4))
            assert np.all(np.isfinite(r.rewards)), r
    got = state()
    assert 0 < len(got["trajectories"]) <= 8, got  # 40 episodes ended; capacity 8
    json.dump(got, open(snapshot, "w"))
    print(f"shaped 240 steps, pool version {got['pool_version']}, {len(got['trajectories'])} trajectories")
else:
    want = json.load(open(snapshot))
    got = json.loads(json.dumps(state()))
    assert got == want, f"pool changed across the restart:\n{got}\n!=\n{want}"
    with client.session("docker-test", 1) as s:  # and it still shapes
        s.step([1], [0.5], terminated=[True], values=[0.0], next_values=[0.0])
    print(f"pool intact after the restart (version {got['pool_version']}), shaping goes on")
client.close()
PY
}

say "running $name (volume $vol)"
run
wait_healthy
[[ $(podman inspect --format '{{.State.Health.Status}}' "$name") == healthy ]] \
    || fail "health status is not healthy"
client fill

say "checking the metrics endpoint on 127.0.0.1:$mport"
"$py" - "$mport" <<'PY' || fail "the metrics do not show the shaping"
import sys, urllib.request
text = urllib.request.urlopen(f"http://127.0.0.1:{sys.argv[1]}/metrics", timeout=10).read().decode()
want = {
    'tamrm_steps_shaped_total{task="docker-test"}': 240.0,
    'tamrm_episodes_completed_total{task="docker-test"}': 40.0,
}
got = {}
for line in text.splitlines():
    series, _, value = line.rpartition(" ")
    if series in want:
        got[series] = float(value)
assert got == want, f"{got} != {want}"
shape = [l for l in text.splitlines()
         if l.startswith("grpc_server_started_total{") and 'grpc_method="Shape"' in l]
assert shape and float(shape[0].rsplit(" ", 1)[1]) >= 1, f"no Shape RPC counted: {shape}"
print("metrics: 240 steps and 40 episodes counted, Shape streams started:", shape[0].rsplit(" ", 1)[1])
PY

say "checking the server process is not root"
pid=$(podman inspect --format '{{.State.Pid}}' "$name")
uid=$(awk '/^Uid:/ { print $2 }' "/proc/$pid/status")
top=$(podman top "$name" user huser | tail -n +2)
say "server pid $pid: uid $uid; podman top user/huser: $top"
[[ "$uid" != 0 ]] || fail "the server runs as root (pid $pid)"
[[ "$(awk '{ print $1 }' <<<"$top")" != root ]] || fail "podman top says the user is root"

say "stopping and starting $name"
podman stop -t 35 "$name" >/dev/null 2>>"$work/podman.err"
[[ $(podman inspect --format '{{.State.ExitCode}}' "$name") == 0 ]] \
    || fail "the server did not exit 0 on SIGTERM"
podman start "$name" >/dev/null 2>>"$work/podman.err"
wait_healthy
client check
podman rm -f -t 0 "$name" >/dev/null 2>&1

say "running $name-secure: TLS and API keys"
secure="$work/secure"
mkdir -p "$secure"
"$py" - "$secure" <<'PY' || fail "could not make the test certificates (trustme)"
import sys
import trustme

out = sys.argv[1]
ca = trustme.CA()
leaf = ca.issue_cert("localhost", "127.0.0.1")
ca.cert_pem.write_to_path(f"{out}/ca.crt")
leaf.private_key_pem.write_to_path(f"{out}/server.key")
# The chain up to the CA (`cat ca.crt >> server.crt`, deployment.md): the unchanged
# HEALTHCHECK trusts the certificates in the server's own file.
with open(f"{out}/server.crt", "wb") as f:
    for blob in leaf.cert_chain_pems:
        f.write(blob.bytes())
    f.write(ca.cert_pem.bytes())
trustme.CA().cert_pem.write_to_path(f"{out}/other-ca.crt")
PY
"$bin" key --tenant acme --role writer >"$secure/key.out"
key=$(sed -n 's/^# key: //p' "$secure/key.out")
[[ "$key" == tamrm_* ]] || fail "tamrm key printed no key: $(cat "$secure/key.out")"
grep -v '^#' "$secure/key.out" >"$secure/keys.toml"
grep -q "$key" "$secure/keys.toml" && fail "the key file holds the key in clear"
# The server (uid 65532) reads them through a read-only bind mount.
chmod 755 "$secure" && chmod 644 "$secure"/*
sport=$(free_port)
smport=$(free_port)
podman run -d --runtime runc --network host --name "$name-secure" \
    -v "$secure:/etc/tamrm:ro" --read-only --cap-drop ALL --security-opt no-new-privileges \
    -e TAMRM_LISTEN="127.0.0.1:$sport" -e TAMRM_METRICS_LISTEN="127.0.0.1:$smport" \
    -e TAMRM_TLS_CERT=/etc/tamrm/server.crt \
    -e TAMRM_TLS_KEY=/etc/tamrm/server.key -e TAMRM_API_KEYS=/etc/tamrm/keys.toml \
    "$image" >/dev/null 2>>"$work/podman.err"
wait_healthy "$name-secure" "$sport"
slog=$(podman logs "$name-secure" 2>&1)
grep -q "TLS on" <<<"$slog" || fail "the secure container's log does not say TLS on"
grep -q "API keys required" <<<"$slog" || fail "the secure container's log does not say API keys required"
"$py" - "$sport" "$secure" "$key" <<'PY' || fail "TLS and API keys in the container"
import sys
import numpy as np
import tamrm

port, secure, key = sys.argv[1], sys.argv[2], sys.argv[3]
addr = f"localhost:{port}"
ca = f"{secure}/ca.crt"
with tamrm.Client(addr, api_key=key, root_certificates=ca) as c:
    c.create_task("secure", num_actions=2, pool_capacity=2, start_step=0)
    with c.session("secure", 2) as s:
        r = s.step(np.array([0, 1]), np.array([1.0, 0.5]), np.array([True, False]))
    assert r.rewards.shape == (2,) and np.all(np.isfinite(r.rewards)), r
    assert c.get_task("secure").stats.episodes_completed == 1
refused = {
    "no key": dict(root_certificates=ca),
    "a wrong key": dict(api_key="tamrm_" + "0" * 64, root_certificates=ca),
    "a CA that did not sign the server": dict(api_key=key, root_certificates=f"{secure}/other-ca.crt"),
}
for what, opts in refused.items():
    try:
        with tamrm.Client(addr, **opts) as c:
            c.list_tasks()
    except tamrm.Unauthenticated:
        assert what != "a CA that did not sign the server", what
    except tamrm.TamrmError as e:
        assert what == "a CA that did not sign the server", (what, e)
    else:
        raise AssertionError(f"a client with {what} was served")
print("TLS and API keys: the keyed TLS client shaped; no key, a wrong key and a wrong CA were refused")
PY
grep -q "$key" <<<"$(podman logs "$name-secure" 2>&1)" && fail "the server logged the API key"

say "ok"

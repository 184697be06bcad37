#!/usr/bin/env bash
# Builds the service image from the Dockerfile with podman (every package from the hashed lock) and checks it:
# readiness and start-up time, one synthesis, one raw-scan fit, gRPC health, the non-root user, the
# HEALTHCHECK, assets baked in (a container without network becomes ready), then the same service through
# docker-compose.yml with podman-compose. One line per check (PASS / FAIL with numbers); exits non-zero on any
# FAIL. With requirements/ray.txt present it also builds the ray target and imports bodyfit and ray in it.
#
# Not part of test.sh: it downloads for minutes (podman, a Debian base made with debootstrap, every locked
# wheel) and needs root on a Debian / Ubuntu machine. Later runs reuse the base image and podman's layer cache.
#   scripts/check_image.sh
# Environment:
#   BODYFIT_REST_PORT / BODYFIT_GRPC_PORT  host ports of the containers under test (default 18000 / 15051, so
#                                          they do not clash with a dev server on 8000 / 50051)
#   BODYFIT_IMAGE_BASE                     the Dockerfile's BASE (default localhost/debian:bookworm, made here
#                                          with debootstrap when missing; python:3.11-slim where a registry
#                                          is reachable)
#   BODYFIT_WHEELS                         a folder with torch's CPU wheel (default: pip's find-links folder
#                                          when it holds one; else the build downloads from TORCH_INDEX)
#   BODYFIT_TORCH_INDEX / PIP_INDEX_URL    passed to the build as TORCH_INDEX / PIP_INDEX_URL when set
#   BODYFIT_CA                             CA bundle for pip inside the build (default: pip's cert setting or
#                                          the system bundle); given as a build secret, never stored in the image
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"

rest_port="${BODYFIT_REST_PORT:-18000}"
grpc_port="${BODYFIT_GRPC_PORT:-15051}"
base="${BODYFIT_IMAGE_BASE:-localhost/debian:bookworm}"
image=localhost/bodyfit:check
ray_image=localhost/bodyfit-ray:check
work="$root/build/check_image"
tools="$root/build/container-tools"
rootfs="$root/build/rootfs-bookworm"
project="bodyfit-check-$$"
c_host="bodyfit-check-host-$$"
c_offline="bodyfit-check-offline-$$"
mkdir -p "$work" "$tools"

fails=0
report() {  # report PASS|FAIL NAME DETAILS...
    local status="$1" name="$2"
    shift 2
    printf '%-4s  %-22s %s\n' "$status" "$name" "$*"
    if [ "$status" = FAIL ]; then fails=$((fails + 1)); fi
}
check() {  # check NAME DETAILS CONDITION...: PASS when the condition command succeeds
    local name="$1" details="$2"
    shift 2
    if "$@"; then report PASS "$name" "$details"; else report FAIL "$name" "$details"; fi
}
now() { date +%s.%N; }
since() { awk -v a="$1" -v b="$(now)" 'BEGIN { printf "%.1f", b - a }'; }
ms_since() { awk -v a="$1" -v b="$(now)" 'BEGIN { printf "%.0f", (b - a) * 1000 }'; }
port_busy() { (exec 3<>"/dev/tcp/127.0.0.1/$1") 2>/dev/null; }
replace_old() {  # replace_old OLD_ID IMAGE: drops the image a rebuild replaced (its layers are 1-2 GB)
    local new
    new=$(pm image inspect --format '{{.Id}}' "$2")
    if [ -n "$1" ] && [ "$1" != "$new" ]; then pm rmi "$1" >/dev/null 2>&1 || true; fi
}
log_tail() { tail -n "${2:-15}" "$1" | sed 's/^/      | /'; }
loopback_only() {  # loopback_only HOST_IP:PORT...: true when there is at least one and all are on 127.0.0.1
    [ $# -gt 0 ] || return 1
    local b
    for b in "$@"; do case "$b" in 127.0.0.1:*) ;; *) return 1 ;; esac; done
}

# --- tools -----------------------------------------------------------------------------------------------------
if ! command -v podman >/dev/null || ! command -v debootstrap >/dev/null || ! [ -x /usr/sbin/runc ]; then
    [ "$(id -u)" = 0 ] || { echo "podman, runc and debootstrap are missing and this is not root" >&2; exit 2; }
    echo "installing podman, runc and debootstrap (apt)" >&2
    apt-get update >"$work/apt.log" 2>&1
    DEBIAN_FRONTEND=noninteractive apt-get install -y podman runc debootstrap >>"$work/apt.log" 2>&1
fi
# Containers in this kind of sandbox start only without default ulimits and with runc (crun refuses hybrid
# cgroups); both are harmless elsewhere.
if [ ! -f /etc/containers/containers.conf ] && [ "$(id -u)" = 0 ]; then
    mkdir -p /etc/containers
    printf '[containers]\ndefault_ulimits = []\n' >/etc/containers/containers.conf
fi
runtime=()
if [ -x /usr/sbin/runc ]; then runtime=(--runtime /usr/sbin/runc); fi
pm() { podman "${runtime[@]}" "$@"; }
if [ ! -x "$tools/venv/bin/podman-compose" ]; then
    echo "installing podman-compose into $tools/venv" >&2
    python3 -m venv "$tools/venv"
    "$tools/venv/bin/python" -m pip install --quiet "podman-compose==1.6.0" >"$work/pip-tools.log" 2>&1
fi
compose() { "$tools/venv/bin/podman-compose" -p "$project" --podman-args="${runtime[*]}" -f docker-compose.yml "$@"; }

cleanup() {
    pm rm -f "$c_host" "$c_offline" >/dev/null 2>&1 || true
    if [ -n "${compose_started:-}" ]; then compose down >/dev/null 2>&1 || true; fi
    rm -rf "$rootfs"
}
trap cleanup EXIT
trap 'exit 130' INT TERM

# --- base image: Debian bookworm (python3 is 3.11), made once with debootstrap -----------------------------------
if ! pm image exists "$base"; then
    if [ "$base" != localhost/debian:bookworm ]; then
        echo "base image $base is missing: pull it first, or unset BODYFIT_IMAGE_BASE" >&2
        exit 2
    fi
    echo "making $base with debootstrap (minutes)" >&2
    t=$(now)
    rm -rf "$rootfs"
    if debootstrap --variant=minbase bookworm "$rootfs" >"$work/debootstrap.log" 2>&1 \
        && rm -rf "$rootfs"/var/cache/apt/archives/*.deb "$rootfs"/var/lib/apt/lists/* \
        && tar -C "$rootfs" -c . | pm import - "$base" >>"$work/debootstrap.log" 2>&1; then
        report PASS base-image "$base made with debootstrap in $(since "$t") s"
    else
        report FAIL base-image "debootstrap or import failed, see $work/debootstrap.log"
        exit 1
    fi
    rm -rf "$rootfs"
fi

# --- build --------------------------------------------------------------------------------------------------------
build_args=(--format docker --network host --build-arg "BASE=$base")  # docker format keeps the HEALTHCHECK
ca="${BODYFIT_CA:-$(python3 -m pip config get global.cert 2>/dev/null || true)}"
ca="${ca:-/etc/ssl/certs/ca-certificates.crt}"
if [ -f "$ca" ]; then build_args+=(--secret "id=ca,src=$ca"); fi
wheels="${BODYFIT_WHEELS:-}"
if [ -z "$wheels" ]; then
    for d in $(python3 -m pip config list 2>/dev/null | sed -n "s/^.*find-links='\(.*\)'$/\1/p"); do
        if ls "$d"/torch-*.whl >/dev/null 2>&1; then wheels="$d"; break; fi
    done
fi
if [ -n "$wheels" ]; then build_args+=(--build-context "torch-wheels=$wheels"); fi
if [ -n "${BODYFIT_TORCH_INDEX:-}" ]; then build_args+=(--build-arg "TORCH_INDEX=$BODYFIT_TORCH_INDEX"); fi
index="${PIP_INDEX_URL:-$(python3 -m pip config get global.index-url 2>/dev/null || true)}"
case "$index" in http*) build_args+=(--build-arg "PIP_INDEX_URL=$index") ;; esac

old=$(pm image inspect --format '{{.Id}}' "$image" 2>/dev/null || true)
t=$(now)
if pm build "${build_args[@]}" --target service -t "$image" . >"$work/build.log" 2>&1; then
    pm tag "$image" localhost/bodyfit:latest  # the compose file's image, so that `up` does not rebuild
    replace_old "$old" "$image"
    report PASS build "$(since "$t") s (torch from ${wheels:-the TORCH_INDEX}; log $work/build.log)"
else
    report FAIL build "see $work/build.log"
    log_tail "$work/build.log"
    exit 1
fi
check image-config "user=$(pm image inspect --format '{{.Config.User}}' "$image"), healthcheck set" \
    test "$(pm image inspect --format '{{.Config.User}}' "$image")" = bodyfit -a \
    -n "$(pm image inspect --format '{{.Config.Healthcheck}}' "$image" | grep -v '^<nil>$')"

# --- the image, on the host network ---------------------------------------------------------------------------------
wait_ready() {  # wait_ready CHECK_COMMAND...: polls up to 300 s, prints the seconds taken
    local t0="$1"
    shift
    for _ in $(seq 600); do
        if "$@" >/dev/null 2>&1; then since "$t0"; return 0; fi
        sleep 0.5
    done
    return 1
}
readyz_host() { [ "$(curl -s -o /dev/null -w '%{http_code}' "http://127.0.0.1:$1/readyz")" = 200 ]; }

for port in "$rest_port" "$grpc_port"; do
    if port_busy "$port"; then
        report FAIL free-port "127.0.0.1:$port is in use: set BODYFIT_REST_PORT / BODYFIT_GRPC_PORT"
        exit 1
    fi
done
t0=$(now)
pm run -d --name "$c_host" --network host \
    -e "BODYFIT_REST_PORT=$rest_port" -e "BODYFIT_GRPC_PORT=$grpc_port" "$image" >"$work/run.log" 2>&1 || true
if startup_s=$(wait_ready "$t0" readyz_host "$rest_port"); then
    report PASS readyz "200 on :$rest_port, startup_s=$startup_s"
else
    startup_s=n/a
    report FAIL readyz "no 200 on :$rest_port within 300 s"
    pm logs "$c_host" >"$work/container.log" 2>&1 || true
    log_tail "$work/container.log"
fi

# One synthesis: npz with the posed vertices.
t=$(now)
code=$(curl -s -o "$work/synth.npz" -w '%{http_code}' --max-time 60 -H 'content-type: application/json' \
    -d '{"coordinates": {"knee_angle_r": 1.0, "hip_flexion_r": 0.5}, "format": "npz"}' \
    "http://127.0.0.1:$rest_port/v1/synthesize" || true)
ms=$(ms_since "$t")
shape=$(python3 - "$work/synth.npz" <<'EOF' 2>/dev/null || true
import ast, sys, zipfile
data = zipfile.ZipFile(sys.argv[1]).read("vertices.npy")
size = 2 if data[6] == 1 else 4
header = ast.literal_eval(data[8 + size:8 + size + int.from_bytes(data[8:8 + size], "little")].decode("latin1"))
print("x".join(map(str, header["shape"])))
EOF
)
check synthesize "HTTP $code, vertices $shape, ${ms} ms" test "$code" = 200 -a -n "$shape"

# One raw-scan fit (a single-view point cloud): the result with its report.
scan=tests/data/scans/pcl_template_alignment_person.pcd
t=$(now)
code=$(curl -s -o "$work/fit.json" -w '%{http_code}' --max-time 600 -H 'accept: application/json' \
    -F "file=@$scan" -F units=auto "http://127.0.0.1:$rest_port/v1/fit/scan" || true)
wall=$(since "$t")
summary=$(python3 - "$work/fit.json" <<'EOF' 2>/dev/null || true
import json, sys
r = json.load(open(sys.argv[1]))
d = r["report"]["distances"]
print(f"fitted_as={r['fitted_as']!r}, mean {d['mean']:.1f} mm, p95 {d['p95']:.1f} mm, "
      f"{len(r['arrays'])} arrays, confident={r['report']['confident']}")
EOF
)
mem=$(pm stats --no-stream --format '{{.MemUsage}}' "$c_host" 2>/dev/null | cut -d/ -f1 | tr -d ' ' || true)
check fit-scan "HTTP $code, $summary, ${wall} s, memory after ${mem:-?}" test "$code" = 200 -a -n "$summary"

# gRPC health, from the host when a client is at hand, else from inside the container.
health_py='import sys, grpc
from grpc_health.v1 import health_pb2, health_pb2_grpc
with grpc.insecure_channel(sys.argv[1]) as ch:
    r = health_pb2_grpc.HealthStub(ch).Check(health_pb2.HealthCheckRequest(service=""), timeout=10)
print(health_pb2.HealthCheckResponse.ServingStatus.Name(r.status))'
if "$root/.venv/bin/python" -c "import grpc_health" 2>/dev/null; then
    how="host .venv"
    status=$("$root/.venv/bin/python" -c "$health_py" "127.0.0.1:$grpc_port" 2>&1 | tail -1 || true)
elif command -v grpc_health_probe >/dev/null; then
    how="grpc_health_probe"
    status=$(grpc_health_probe -addr "127.0.0.1:$grpc_port" 2>&1 | grep -o SERVING || true)
else
    how="client in the container"
    status=$(pm exec "$c_host" python -c "$health_py" "127.0.0.1:$grpc_port" 2>&1 | tail -1 || true)
fi
check grpc-health "$status on :$grpc_port ($how)" test "$status" = SERVING

uid=$(pm exec "$c_host" id -u 2>/dev/null || echo "?")
check non-root "uid=$uid ($(pm exec "$c_host" id -un 2>/dev/null || echo "?"))" test "$uid" != 0 -a "$uid" != "?"

if pm healthcheck run "$c_host" >/dev/null 2>&1; then
    report PASS healthcheck "the image's HEALTHCHECK passes (podman healthcheck run)"
else
    report FAIL healthcheck "the image's HEALTHCHECK fails (podman healthcheck run)"
fi

# --- assets baked in: no network at all, default ports inside its own namespace ------------------------------------
readyz_inside() {
    pm exec "$1" python -c "import sys, urllib.request
sys.exit(urllib.request.urlopen('http://127.0.0.1:8000/readyz', timeout=2).status != 200)"
}
t0=$(now)
pm run -d --name "$c_offline" --network none "$image" >>"$work/run.log" 2>&1 || true
if s=$(wait_ready "$t0" readyz_inside "$c_offline"); then
    report PASS offline-readyz "--network none: ready in ${s} s"
else
    report FAIL offline-readyz "--network none: not ready within 300 s"
    pm logs "$c_offline" >"$work/container-offline.log" 2>&1 || true
    log_tail "$work/container-offline.log"
fi
pm rm -f "$c_host" "$c_offline" >/dev/null 2>&1 || true

# --- docker-compose.yml through podman-compose ----------------------------------------------------------------------
compose_started=1
t0=$(now)
if BODYFIT_REST_PORT="$rest_port" BODYFIT_GRPC_PORT="$grpc_port" compose up -d --no-build >"$work/compose.log" 2>&1 \
    && s=$(wait_ready "$t0" readyz_host "$rest_port"); then
    report PASS compose-up "readyz 200 on 127.0.0.1:$rest_port in ${s} s"
else
    report FAIL compose-up "see $work/compose.log"
    log_tail "$work/compose.log"
fi
cid=$(pm ps -q --filter "label=io.podman.compose.project=$project" 2>/dev/null | head -1 || true)
if [ -n "$cid" ]; then
    limits=$(pm inspect --format '{{.HostConfig.Memory}} {{.HostConfig.NanoCpus}}' "$cid" || echo 0 0)
    read -r mem_b cpu_n <<<"$limits"
    inside=$(pm exec "$cid" sh -c 'cat /sys/fs/cgroup/memory.max 2>/dev/null || cat /sys/fs/cgroup/memory/memory.limit_in_bytes' 2>/dev/null || true)
    check compose-limits "memory $((mem_b / 1048576)) MiB (cgroup ${inside:-?}), cpus $((cpu_n / 1000000000))" \
        test "$mem_b" -gt 0 -a "$cpu_n" -gt 0 -a "${inside:-max}" != max
    binds=$(pm inspect --format '{{range $p, $b := .HostConfig.PortBindings}}{{range $b}}{{.HostIP}}:{{.HostPort}} {{end}}{{end}}' "$cid" || true)
    # shellcheck disable=SC2086  # one argument per binding
    check compose-ports "published on ${binds% }" loopback_only $binds
else
    report FAIL compose-limits "no container from compose"
fi
if compose down >>"$work/compose.log" 2>&1; then
    compose_started=
    report PASS compose-down ""
else
    report FAIL compose-down "see $work/compose.log"
fi

# --- the ray target (Ray head / worker image) -----------------------------------------------------------------------
if [ -f requirements/ray.txt ]; then
    old=$(pm image inspect --format '{{.Id}}' "$ray_image" 2>/dev/null || true)
    t=$(now)
    if pm build "${build_args[@]}" --target ray -t "$ray_image" . >"$work/build-ray.log" 2>&1; then
        replace_old "$old" "$ray_image"
        versions=$(pm run --rm --network none "$ray_image" python -c \
            "import bodyfit, ray, torch; print(f'ray {ray.__version__}, torch {torch.__version__}')" 2>/dev/null || true)
        check ray-image "built in $(since "$t") s; ${versions:-import failed}" test -n "$versions"
    else
        report FAIL ray-image "see $work/build-ray.log"
        log_tail "$work/build-ray.log"
    fi
else
    echo "SKIP  ray-image              requirements/ray.txt is not there"
fi

# --- summary --------------------------------------------------------------------------------------------------------
size=$(pm image inspect --format '{{.Size}}' "$image")
echo "image $image: $(awk -v b="$size" 'BEGIN { printf "%.0f MB (%.2f GiB)", b / 1e6, b / 2^30 }'), startup_s=$startup_s"
if [ "$fails" -gt 0 ]; then
    echo "$fails check(s) FAILED"
    exit 1
fi
echo "all checks passed"

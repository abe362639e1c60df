#!/usr/bin/env bash
# Smoke test of the image without running a container (these machines cannot): export its root
# filesystem, chroot into it as the image's user in a private mount namespace (/proc, /sys, /dev
# mounted there only), start udapose-server with the image's entrypoint on a free loopback port
# pair, wait for /readyz (curl from the host, $READY_TIMEOUT s), then: the image's health check and
# the udapose CLI from inside the chroot, the shared libraries the running server has mapped, and
# one estimate over HTTP whose JSON must carry a pose. Stops the server at the end.
set -euo pipefail
cd "$(dirname "$0")/../.."
UDAPOSE_CACHE=${UDAPOSE_CACHE:-$HOME/.cache/udapose}
VARIANT=${VARIANT:-cpu}
IMAGE=${IMAGE:-localhost/udapose:$VARIANT}
PODMAN=${PODMAN:-podman --storage-driver vfs}
READY_TIMEOUT=${READY_TIMEOUT:-120}
# One SynCar-OOD source image: the second tile of the committed preview strip (a box selects it).
SMOKE_IMAGE=${SMOKE_IMAGE:-reports/syncar-preview/source.png}
SMOKE_QUERY=${SMOKE_QUERY-?bbox=163,0,324,66}
CATEGORY=${CATEGORY:-car}
ROOT=$UDAPOSE_CACHE/image/smoke-$VARIANT
ROOTFS=$ROOT/rootfs
LOG=$ROOT/server.log
SUDO=$([ "$(id -u)" = 0 ] || echo sudo)

step() { printf '\n== %s\n' "$*"; }

step "export the root filesystem of $IMAGE"
$SUDO rm -rf "$ROOT"
mkdir -p "$ROOTFS"
ctr=udapose-smoke-$$
$PODMAN create --quiet --no-healthcheck --name "$ctr" "$IMAGE" >/dev/null
trap '$PODMAN rm --force "$ctr" >/dev/null 2>&1 || true' EXIT
$PODMAN export "$ctr" | $SUDO tar --numeric-owner -xf - -C "$ROOTFS"
$PODMAN rm "$ctr" >/dev/null 2>&1 || true
trap - EXIT
echo "$ROOTFS: $(du -sh "$ROOTFS" | cut -f1)"

step "what takes the space (the exported root filesystem, before the server writes its state)"
( cd "$ROOTFS" && du -xsm opt/udapose/lib opt/udapose/models usr/local/bin usr var etc | sort -rn |
    awk '{ printf "%6d MB  /%s\n", $1, $2 }' )
echo "largest files:"
find "$ROOTFS" -xdev -type f -size +1M -printf '%s %P\n' | sort -rn | head -8 |
    awk '{ printf "%8.1f MB  /%s\n", $1 / 1048576, $2 }'

# The image's configuration: user, entrypoint, working directory, environment.
cfg() { $PODMAN image inspect --format "$1" "$IMAGE"; }
user=$(cfg '{{.Config.User}}')
entrypoint=$(cfg '{{index .Config.Entrypoint 0}}')
workdir=$(cfg '{{.Config.WorkingDir}}')
mapfile -t image_env < <(cfg '{{range .Config.Env}}{{println .}}{{end}}' | sed '/^$/d')
echo "user $user, entrypoint $entrypoint, workdir $workdir, env: ${image_env[*]}"

# Two free loopback ports (adjacent, so the transcript is easy to read).
free() { python3 -c 'import socket, sys; socket.socket().bind(("127.0.0.1", int(sys.argv[1])))' "$1" 2>/dev/null; }
while :; do
    http=$((20000 + RANDOM % 20000)); grpc=$((http + 1))
    free "$http" && free "$grpc" && break
done

# A command in the chroot as the image's user, in a private mount namespace (the mounts vanish
# with it). unshare, env, bash, chroot and sh all exec, so a background job's $! is the command.
IN_IMAGE=($SUDO unshare --mount --propagation private -- env -i "${image_env[@]}" HOME="$workdir" bash -c '
    r=$1; shift
    mkdir -p "$r/proc" "$r/sys" "$r/dev"
    mount -t proc proc "$r/proc"
    mount -t sysfs -o ro sysfs "$r/sys" 2>/dev/null || mount --rbind -o ro /sys "$r/sys"
    mount --bind /dev "$r/dev"
    exec chroot --userspec="$1" "$r" /bin/sh -c "cd \"\$0\" && exec \"\$@\"" "$2" "${@:3}"
' in_image "$ROOTFS" "$user" "$workdir")
in_image() { "${IN_IMAGE[@]}" "$@"; }

step "ldd $entrypoint inside the image"
in_image ldd "$entrypoint"

step "start $entrypoint in the chroot on 127.0.0.1:$http (HTTP) and 127.0.0.1:$grpc (gRPC)"
args=(--http-addr "127.0.0.1:$http" --grpc-addr "127.0.0.1:$grpc" --models /opt/udapose/models --store /var/lib/udapose)
echo "$entrypoint ${args[*]}"
t0=$(date +%s.%N)
"${IN_IMAGE[@]}" "$entrypoint" "${args[@]}" >"$LOG" 2>&1 &
pid=$!
stop() { kill -TERM "$pid" 2>/dev/null && wait "$pid" 2>/dev/null || true; }
trap stop EXIT
until curl -fsS -o /dev/null "http://127.0.0.1:$http/readyz" 2>/dev/null; do
    if ! kill -0 "$pid" 2>/dev/null; then echo "the server exited:"; sed 's/\x1b\[[0-9;]*m//g' "$LOG"; exit 1; fi
    if (($(date +%s) - ${t0%.*} > READY_TIMEOUT)); then echo "not ready after ${READY_TIMEOUT}s:"; sed 's/\x1b\[[0-9;]*m//g' "$LOG" | tail -30; exit 1; fi
    sleep 0.5
done
printf 'GET /readyz: %s after %.1f s\n' "$(curl -sS "http://127.0.0.1:$http/readyz")" "$(awk -v a="$t0" -v b="$(date +%s.%N)" 'BEGIN { print b - a }')"

step "the image's health check (udapose-healthcheck) inside the chroot"
in_image env UDAPOSE_HEALTH_PORT="$http" /usr/local/bin/udapose-healthcheck && echo "healthy (exit 0)"

step "udapose models (the CLI, gRPC) inside the chroot"
in_image /usr/local/bin/udapose --endpoint "127.0.0.1:$grpc" models

step "shared libraries the running server has mapped (/proc/PID/maps)"
server_pid=$pid # sudo (when not root) forks: then the server is its child
[ "$(cat /proc/"$server_pid"/comm)" = udapose-server ] || server_pid=$(pgrep -P "$pid" -x udapose-server)
[ "$(cat /proc/"$server_pid"/comm)" = udapose-server ] || { echo "no udapose-server process"; exit 1; }
# Seen from the host: paths inside the image start with $ROOTFS; anything else came from outside.
all=$(awk '$6 ~ /\.so/ { print $6 }' /proc/"$server_pid"/maps | sort -u)
if grep -v "^$ROOTFS/" <<<"$all"; then echo "^ mapped from outside the image"; exit 1; fi
maps=$(sed "s|^$ROOTFS||" <<<"$all")
echo "$maps"
if [ "$VARIANT" = cpu ]; then
    cuda=$(grep -E '/lib(cu|nv|torch_cuda|c10_cuda|nccl)' <<<"$maps" | grep -Ev '/libcudart\.so|/libcupti\.so' || true)
    if [ -n "$cuda" ]; then echo "cpu image loaded CUDA libraries: $cuda"; exit 1; fi
    echo "no CUDA library loaded but libcudart and libcupti (needed by libtorch_cpu.so)"
fi
outside=$(grep -Ev '^/(opt/udapose/lib|usr/lib/x86_64-linux-gnu|lib/x86_64-linux-gnu)/' <<<"$maps" || true)
if [ -n "$outside" ]; then echo "libraries from outside the image's library directories: $outside"; exit 1; fi

step "one estimate: POST /v1/pose/$CATEGORY$SMOKE_QUERY with $SMOKE_IMAGE"
answer=$(curl -sS --max-time 60 -w '\n%{http_code}' --data-binary @"$SMOKE_IMAGE" "http://127.0.0.1:$http/v1/pose/$CATEGORY$SMOKE_QUERY")
code=${answer##*$'\n'}
answer=${answer%$'\n'*}
[ "$code" = 200 ] || { echo "HTTP $code: $answer"; exit 1; }
python3 - "$answer" <<'PY'
import json, sys
a = json.loads(sys.argv[1])
if not a.get("estimates") or "azimuth" not in a["estimates"][0]:
    sys.exit(f"no pose in the answer: {sys.argv[1][:400]}")
p = a["estimates"][0]
print("pose:", ", ".join(f"{k} {p[k]:.4f}" for k in ("azimuth", "elevation", "theta", "distance", "score")))
print("degrees:", ", ".join(f"{k} {p[k]:.1f}" for k in ("azimuth_deg", "elevation_deg", "theta_deg")))
print("model version:", a["model_version"], "| timings (ms):", a["timings"])
PY

step "stop the server"
stop
trap - EXIT
sed 's/\x1b\[[0-9;]*m//g' "$LOG" | tail -3
echo
echo "smoke test of $IMAGE passed"

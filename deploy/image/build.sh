#!/usr/bin/env bash
# Stages the build context (stage.sh) and builds localhost/udapose:$VARIANT from deploy/Containerfile
# with podman's vfs storage and chroot isolation (no registry: --pull=never, the base image is the
# local import made by base.sh). Docker image format, so the HEALTHCHECK is kept. The image it
# replaces under the same tag is removed, so repeated builds do not pile up.
set -euo pipefail
cd "$(dirname "$0")/../.."
UDAPOSE_CACHE=${UDAPOSE_CACHE:-$HOME/.cache/udapose}
export UDAPOSE_CACHE VARIANT=${VARIANT:-cpu}
IMAGE=${IMAGE:-localhost/udapose:$VARIANT}
PODMAN=${PODMAN:-podman --storage-driver vfs}
# vfs keeps every intermediate layer as a full copy of the filesystem: fine for cpu (~0.6 GB a
# step), ~3.5 GB a step for cuda, which therefore builds without intermediate layers (one layer
# on top of the base, no layer cache). LAYERS=true|false overrides.
LAYERS=${LAYERS:-$([ "$VARIANT" = cuda ] && echo false || echo true)}

deploy/image/stage.sh
old=$($PODMAN image inspect --format '{{.Id}}' "$IMAGE" 2>/dev/null || true)
echo "podman build -f deploy/Containerfile --build-arg VARIANT=$VARIANT -t $IMAGE"
$PODMAN build --isolation chroot --pull=never --format docker --layers="$LAYERS" \
    -f deploy/Containerfile --build-arg VARIANT="$VARIANT" -t "$IMAGE" \
    "$UDAPOSE_CACHE/image/context-$VARIANT" >"$UDAPOSE_CACHE/image/build-$VARIANT.log" 2>&1 ||
    { tail -30 "$UDAPOSE_CACHE/image/build-$VARIANT.log"; exit 1; }
steps=$(grep -c ' STEP ' "$UDAPOSE_CACHE/image/build-$VARIANT.log" || true)
cached=$(grep -c '^--> Using cache' "$UDAPOSE_CACHE/image/build-$VARIANT.log" || true)
echo "built: $steps steps, $cached of them from the layer cache"
new=$($PODMAN image inspect --format '{{.Id}}' "$IMAGE")
if [ -n "$old" ] && [ "$old" != "$new" ]; then $PODMAN rmi "$old" >/dev/null 2>&1 || true; fi
$PODMAN images --format '{{.Repository}}:{{.Tag}} {{.ID}} {{.Size}}' "$IMAGE"
$PODMAN history --format '{{.Size}}\t{{.CreatedBy}}' "$IMAGE" | awk -F'\t' '$1 != "0B" { printf "  layer %-9s %.90s\n", $1, $2 }'

#!/usr/bin/env bash
# The tools `make image` needs, from Debian's packages; installs only what is missing.
#   podman (with buildah inside) builds the image, debootstrap makes the base image,
#   patchelf edits the staged copies of the binaries, curl drives the smoke test.
set -euo pipefail
SUDO=$([ "$(id -u)" = 0 ] || echo sudo)
missing=()
for tool in podman:podman debootstrap:debootstrap patchelf:patchelf curl:curl; do
    command -v "${tool%%:*}" >/dev/null || missing+=("${tool#*:}")
done
# podman's default policy and registries files come with containers-common (a podman dependency).
if ((${#missing[@]})); then
    echo "installing Debian packages: ${missing[*]}"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi

#!/usr/bin/env bash
# Makes the base image localhost/debian:bookworm-slim from Debian's packages, without a registry:
# debootstrap --variant=minbase bookworm, slimmed the way the official debian:*-slim images are
# (no docs, man pages or locales, and dpkg told to keep it so), tarred and `podman import`ed.
# The rootfs and its tarball are cached under $UDAPOSE_CACHE/image/ and reused when present;
# the import is skipped when the image is already in podman's storage. Delete the cache directory
# (or `podman rmi localhost/debian:bookworm-slim`) to make a fresh one.
set -euo pipefail
UDAPOSE_CACHE=${UDAPOSE_CACHE:-$HOME/.cache/udapose}
DIR=$UDAPOSE_CACHE/image/base
SUITE=${DEBIAN_SUITE:-bookworm}
MIRROR=${DEBIAN_MIRROR:-http://deb.debian.org/debian}
BASE_IMAGE=${BASE_IMAGE:-localhost/debian:bookworm-slim}
PODMAN=${PODMAN:-podman --storage-driver vfs}
SUDO=$([ "$(id -u)" = 0 ] || echo sudo)
TARBALL=$DIR/$SUITE-slim.tar

if [ ! -f "$TARBALL" ]; then
    mkdir -p "$DIR"
    $SUDO rm -rf "$DIR/rootfs.tmp"
    echo "debootstrap --variant=minbase $SUITE from $MIRROR (first time: ~2-4 min)"
    $SUDO debootstrap --variant=minbase "$SUITE" "$DIR/rootfs.tmp" "$MIRROR" >"$DIR/debootstrap.log" 2>&1 ||
        { tail -20 "$DIR/debootstrap.log"; exit 1; }
    R=$DIR/rootfs.tmp
    # The official slim images' dpkg excludes (debuerreotype --slimify), so later installs stay slim.
    $SUDO tee "$R/etc/dpkg/dpkg.cfg.d/docker-slim" >/dev/null <<'CFG'
path-exclude /usr/share/doc/*
path-include /usr/share/doc/*/copyright
path-exclude /usr/share/groff/*
path-exclude /usr/share/info/*
path-exclude /usr/share/linda/*
path-exclude /usr/share/lintian/*
path-exclude /usr/share/locale/*
path-exclude /usr/share/man/*
CFG
    $SUDO find "$R/usr/share/doc" -mindepth 1 -not -name copyright -not -type d -delete
    $SUDO find "$R/usr/share/doc" -mindepth 1 -type d -empty -delete
    $SUDO rm -rf "$R"/usr/share/{groff,info,linda,lintian,locale,man}/* \
        "$R"/var/cache/apt/*.bin "$R"/var/cache/apt/archives/*.deb "$R"/var/lib/apt/lists/* \
        "$R"/var/log/*.log "$R"/var/log/apt/* "$R"/tmp/* "$R"/root/.bash_history
    # The host's resolver and hostname must not leak into the image.
    $SUDO rm -f "$R/etc/hostname" "$R/etc/resolv.conf"
    : | $SUDO tee "$R/etc/resolv.conf" >/dev/null
    echo "deb $MIRROR $SUITE main" | $SUDO tee "$R/etc/apt/sources.list" >/dev/null
    $SUDO tar --numeric-owner --xattrs -C "$R" -cf "$TARBALL.tmp" .
    $SUDO mv "$TARBALL.tmp" "$TARBALL"
    $SUDO rm -rf "$DIR/rootfs"
    $SUDO mv "$R" "$DIR/rootfs"
fi

if ! $PODMAN image exists "$BASE_IMAGE"; then
    echo "podman import $TARBALL as $BASE_IMAGE"
    $PODMAN import --quiet \
        --change 'CMD ["bash"]' \
        --change "LABEL org.opencontainers.image.description=Debian $SUITE minbase (debootstrap), slimmed; made by deploy/image/base.sh" \
        "$TARBALL" "$BASE_IMAGE" >/dev/null
fi
$PODMAN images --format '{{.Repository}}:{{.Tag}} {{.Size}}' "$BASE_IMAGE"

#!/usr/bin/env bash
# A stand-in for the base image the Dockerfile names (python:3.11-slim-bookworm) where
# no registry is reachable: a debootstrap minbase Debian bookworm with python3.11, venv,
# pip and the host's CA certificates, imported under that name. The root file system is
# cached as a tarball (COVSLAM_BASE_CACHE), so only the first run pays for debootstrap.
#   DOCKER_HOST=unix:///tmp/docker.sock docker/base-image.sh
set -euo pipefail
name="${COVSLAM_BASE_IMAGE:-python:3.11-slim-bookworm}"
cache="${COVSLAM_BASE_CACHE:-/var/cache/covslam/bookworm-python311-rootfs.tar}"
mirror="${COVSLAM_DEBIAN_MIRROR:-http://deb.debian.org/debian}"
if docker image inspect "$name" >/dev/null 2>&1; then
    exit 0
fi
if [ ! -s "$cache" ]; then
    root="$(mktemp -d /tmp/covslam-rootfs.XXXXXX)"
    trap 'rm -rf "$root"' EXIT
    debootstrap --variant=minbase --include=python3.11,python3.11-venv,python3-pip,ca-certificates \
        bookworm "$root" "$mirror" >/dev/null
    # The host's CA bundle (it may hold a proxy's certificate pip must trust).
    cp /etc/ssl/certs/ca-certificates.crt "$root/etc/ssl/certs/ca-certificates.crt"
    # Look like the official image: `python` and `pip` on PATH, pip may install.
    ln -sf python3 "$root/usr/bin/python"
    ln -sf pip3 "$root/usr/bin/pip"
    rm -f "$root"/usr/lib/python3*/EXTERNALLY-MANAGED
    rm -rf "$root"/var/cache/apt/archives/*.deb "$root"/var/lib/apt/lists/* \
        "$root"/usr/share/doc/* "$root"/usr/share/man/* "$root"/usr/share/locale/*
    mkdir -p "$(dirname "$cache")"
    tar -C "$root" --numeric-owner -cf "$cache.tmp" . && mv "$cache.tmp" "$cache"
fi
docker import --change 'ENV LANG=C.UTF-8' --change 'CMD ["python3"]' "$cache" "$name" >/dev/null

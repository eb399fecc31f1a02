#!/usr/bin/env bash
# Makes sure the image docker/Dockerfile starts from (debian:bookworm-slim)
# exists. Where no container registry can be reached it is built locally from
# the Debian mirror this machine already uses:
#   debootstrap --variant=minbase bookworm DIR MIRROR; tar -C DIR -c . | docker import
# trimmed like the official slim image (no docs, man pages or locales).
#   BASE_IMAGE   image name (default debian:bookworm-slim)
#   DEBIAN_MIRROR  mirror URL (default: the first URIs line of
#                  /etc/apt/sources.list.d/debian.sources, else deb.debian.org)
set -euo pipefail
DOCKER=${DOCKER:-docker}
if [ -x /usr/bin/docker ]; then DOCKER=/usr/bin/docker; fi
image=${BASE_IMAGE:-debian:bookworm-slim}
if "$DOCKER" image inspect "$image" >/dev/null 2>&1; then
  exit 0
fi
if [ "${FLATSERVE_BASE_PULL:-0}" = 1 ] && "$DOCKER" pull "$image"; then
  exit 0
fi
mirror=${DEBIAN_MIRROR:-}
if [ -z "$mirror" ] && [ -r /etc/apt/sources.list.d/debian.sources ]; then
  mirror=$(awk '/^URIs:/ {print $2; exit}' /etc/apt/sources.list.d/debian.sources)
fi
if [ -z "$mirror" ] && [ -r /etc/apt/sources.list ]; then
  mirror=$(awk '$1 == "deb" && $3 ~ /^bookworm/ {print $2; exit}' /etc/apt/sources.list)
fi
mirror=${mirror:-http://deb.debian.org/debian}
command -v debootstrap >/dev/null || { echo "debootstrap is not installed (bash scripts/install-system-deps.sh --docker)" >&2; exit 1; }
SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO=sudo; fi
root=$(mktemp -d /var/tmp/flatserve-base.XXXXXX)
chmod 755 "$root"  # becomes the image's /
trap '$SUDO rm -rf "$root"' EXIT
echo "building $image with debootstrap from $mirror"
$SUDO debootstrap --variant=minbase bookworm "$root" "$mirror"
# As the official slim image: keep docs, man pages and locales out of later
# package installs, never start services, no apt caches.
$SUDO sh -c "
  printf '%s\n' 'path-exclude /usr/share/doc/*' 'path-include /usr/share/doc/*/copyright' \
    'path-exclude /usr/share/man/*' 'path-exclude /usr/share/groff/*' 'path-exclude /usr/share/info/*' \
    'path-exclude /usr/share/locale/*' 'path-include /usr/share/locale/locale.alias' \
    'path-exclude /usr/share/lintian/*' 'path-exclude /usr/share/linda/*' > '$root/etc/dpkg/dpkg.cfg.d/docker'
  printf '#!/bin/sh\nexit 101\n' > '$root/usr/sbin/policy-rc.d' && chmod +x '$root/usr/sbin/policy-rc.d'
  find '$root/usr/share/doc' -mindepth 1 -not -name copyright -not -type d -delete 2>/dev/null || true
  rm -rf '$root/usr/share/man/'* '$root/usr/share/info/'* '$root/usr/share/locale/'* \
    '$root/var/cache/apt/archives/'*.deb '$root/var/lib/apt/lists/'* '$root/var/log/'*.log '$root/tmp/'*
"
$SUDO tar -C "$root" -c . | "$DOCKER" import \
  --change 'CMD ["bash"]' --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
  - "$image"
"$DOCKER" image ls "$image"

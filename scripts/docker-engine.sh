#!/usr/bin/env bash
# Starts the Docker engine if it is installed but not running, and waits until
# `docker info` answers. On these machines there is no init system and often no
# kernel overlay support or iptables: vfs storage, no bridge, no iptables, and
# containers/builds use `--network host`.
#   FLATSERVE_DOCKERD_LOG  where dockerd logs (default /var/log/flatserve-dockerd.log)
set -euo pipefail
DOCKER=${DOCKER:-docker}
# Prefer the client that came with the engine (Debian's docker.io): a newer
# stand-alone client may insist on the buildx plugin for BuildKit builds.
if [ -x /usr/bin/docker ]; then DOCKER=/usr/bin/docker; fi
if "$DOCKER" info >/dev/null 2>&1; then
  exit 0
fi
if ! command -v dockerd >/dev/null 2>&1; then
  echo "dockerd is not installed (bash scripts/install-system-deps.sh --docker)" >&2
  exit 1
fi
SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO=sudo; fi
log=${FLATSERVE_DOCKERD_LOG:-/var/log/flatserve-dockerd.log}
echo "starting dockerd (log: $log)"
# its own session: an interrupt of the caller (make, pytest) does not stop it
$SUDO setsid -f sh -c "exec dockerd --storage-driver=vfs --iptables=false --bridge=none >>'$log' 2>&1 </dev/null"
for _ in $(seq 1 120); do
  if "$DOCKER" info >/dev/null 2>&1; then
    echo "dockerd is up"
    exit 0
  fi
  sleep 1
done
echo "dockerd did not answer within 120 s; the end of $log:" >&2
$SUDO tail -n 40 "$log" >&2 || true
exit 1

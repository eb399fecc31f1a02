#!/usr/bin/env bash
# Installs the Debian packages flatserve needs to build and run.
# Used by the Makefile, .ci/run and docker/Dockerfile alike.
#   --build    compilers + CGAL/Eigen headers (default)
#   --runtime  only what the built extension and the service need at run time
#   --browser  Debian's chromium + chromedriver for the viewer test
#   --docker   Debian's Docker engine (docker.io) + debootstrap, for the image
#              tests (scripts/docker-engine.sh starts the engine,
#              scripts/docker-base.sh builds the base image without a registry)
#   --postgres Debian's PostgreSQL server (binaries in /usr/lib/postgresql/15/bin),
#              for the tests and benchmarks of the PostgreSQL backend: they start
#              their own throwaway clusters (tests/harness/pgcluster.py), never
#              the system's own cluster
#   --bench    wrk, the HTTP load generator of the service benchmarks
set -euo pipefail
mode=build
extra=()
for arg in "$@"; do
  case "$arg" in
    --build) mode=build ;;
    --runtime) mode=runtime ;;
    --browser) extra+=(chromium chromium-driver) ;;
    --docker) extra+=(docker.io debootstrap ca-certificates) ;;
    --postgres) extra+=(postgresql) ;;
    --bench) extra+=(wrk) ;;
    *) echo "unknown option $arg" >&2; exit 2 ;;
  esac
done
if [ "$mode" = build ]; then
  # libcgal-demo ships data.tar.gz with the Stanford bunny used by the light-field demo;
  # curl: the README's examples (tests/test_readme.py runs them).
  pkgs=(build-essential cmake ninja-build libcgal-dev libeigen3-dev libgmp-dev libmpfr-dev libcgal-demo python3-venv python3-dev curl)
else
  pkgs=(python3 libgmp10 libmpfr6 libgomp1 libstdc++6)
fi
pkgs+=("${extra[@]}")
missing=()
for p in "${pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ "${#missing[@]}" -eq 0 ]; then
  exit 0
fi
echo "installing Debian packages: ${missing[*]}"
SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO=sudo; fi
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
$SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"

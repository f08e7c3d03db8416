#!/usr/bin/env bash
# Install what ccrp and its tests need on a Debian/Ubuntu machine, then the package in .venv.
# Idempotent: installs only what is missing. Run as root (or with sudo).
set -euo pipefail
cd "$(dirname "$0")/.."

APT_PACKAGES=(
  openvpn            # the real VPN used by tests and simulated robots
  cloud-init         # `cloud-init schema` validates every rendered user-data
  iproute2 iptables  # network namespaces and firewall rules in end-to-end tests
  openssl            # certificate checks
  python3-venv
  docker.io          # the local default backend (Docker Hub is not needed)
  mmdebstrap         # builds the base image from Debian packages
  chromium chromium-driver  # the dashboard's browser test (headless, driven by selenium)
)

. scripts/apt-missing.sh
apt_install_missing "ccrp setup" "${APT_PACKAGES[@]}"

if [ ! -x .venv/bin/python ]; then
  python3 -m venv .venv
fi
.venv/bin/python -m pip install -q --upgrade pip >/dev/null
.venv/bin/python -m pip install -q -e '.[dev]'
echo "ccrp setup: ready ($(.venv/bin/ccrp --version))" >&2

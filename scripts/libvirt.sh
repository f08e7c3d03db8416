#!/usr/bin/env bash
# The libvirt backend's host: libvirt and QEMU from Debian's packages, the tools that make golden
# volumes and seeds, the Python binding (pip extra `libvirt`, built against libvirt-dev), then
# virtlogd and libvirtd started (through systemd when it runs, else directly, as in a container).
# Idempotent: installs only what is missing, starts only what is not running. Run as root.
# Prints the pids of the daemons it started directly (none when they were running), one per line.
#   PYTHON=<venv python> bash scripts/libvirt.sh     (default: .venv/bin/python of the repo)
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-.venv/bin/python}

APT_PACKAGES=(
  libvirt-daemon-system  # libvirtd, virtlogd, the QEMU driver, NAT networks (iptables)
  qemu-system-x86        # the hypervisor: KVM where it works, TCG where it does not
  qemu-utils             # qemu-img: qcow2 golden volumes and overlays
  dnsmasq-base           # DHCP on the fleets' NAT networks
  genisoimage            # the NoCloud seed (an ISO labelled cidata)
  e2fsprogs              # mkfs.ext4 -d: the golden volume's file system from a directory
  tini                   # reaps what libvirtd leaves behind where no init does (see below)
  libvirt-dev pkg-config gcc python3-dev  # to build libvirt-python (PyPI has no wheel of it)
)
# Without recommends: they add LVM, parted, the Xen/VirtualBox/LXC drivers and more, none of which ccrp uses.
. scripts/apt-missing.sh
apt_install_missing "ccrp libvirt" "${APT_PACKAGES[@]}"

if [ -x "$PYTHON" ] && ! "$PYTHON" -c 'import libvirt' 2>/dev/null; then
  echo "ccrp libvirt: building the Python binding (pip extra libvirt)" >&2
  # The extra's requirements as pyproject.toml lists them (not `pip install -e .[libvirt]`, which would
  # re-point an editable install of ccrp at this checkout).
  mapfile -t reqs < <("$PYTHON" -c 'import tomllib; print("\n".join(tomllib.load(open("pyproject.toml", "rb"))["project"]["optional-dependencies"]["libvirt"]))')
  "$PYTHON" -m pip install -q "${reqs[@]}" >/dev/null
fi

# /dev/kvm as Debian's udev rule leaves it (root:kvm 0660), where no udev ran: QEMU runs as
# libvirt-qemu (group kvm). Whether KVM then really works is for the provider's probe to find.
if [ -c /dev/kvm ] && [ "$(stat -c %G:%a /dev/kvm)" != "kvm:660" ]; then
  chgrp kvm /dev/kvm && chmod 0660 /dev/kvm
fi

answers() { virsh -c qemu:///system version >/dev/null 2>&1; }
if answers; then exit 0; fi
if [ -d /run/systemd/system ]; then
  systemctl start virtlogd.socket libvirtd.service >/dev/null
else
  # No systemd (a container): virtlogd daemonises itself and writes its pid file.
  if ! { [ -s /run/virtlogd.pid ] && kill -0 "$(cat /run/virtlogd.pid)" 2>/dev/null; }; then
    virtlogd --daemon
    sleep 0.2
    echo "$(cat /run/virtlogd.pid)"
  fi
  if ! { [ -s /run/libvirtd.pid ] && kill -0 "$(cat /run/libvirtd.pid)" 2>/dev/null; }; then
    # libvirtd daemonises QEMU and dnsmasq, which become orphans, and waits for them to be gone when
    # it stops them. Where PID 1 reaps no orphans (this sandbox's init does not), they stay zombies,
    # and libvirtd hung in its first QEMU capability probe (virProcessKillPainfully on a zombie).
    # So libvirtd runs in the foreground under tini as a subreaper: the orphans are tini's to reap.
    mkdir -p /var/log/libvirt
    LIBVIRT_LOG_OUTPUTS="3:file:/var/log/libvirt/libvirtd.log" setsid tini -s -- libvirtd \
      </dev/null >>/var/log/libvirt/libvirtd.log 2>&1 &
    echo $!  # tini: stopping it stops libvirtd
    for _ in $(seq 1 50); do [ -s /run/libvirtd.pid ] && break; sleep 0.1; done
  fi
fi
for _ in $(seq 1 60); do
  answers && exit 0
  sleep 0.5
done
echo "ccrp libvirt: libvirtd did not answer on qemu:///system" >&2
exit 1

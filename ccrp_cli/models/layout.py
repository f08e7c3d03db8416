"""A clone's layout: the paths, users, ports and marks that the renderers (render/), the providers and
the core agree on. It imports nothing, so any of them may import it without a cycle. The agents
(ccrp_cli/agent/, standalone files run on the clone) keep their own copies of what they use;
tests/unit/test_import_contract.py pins those copies to these values."""

from __future__ import annotations

# Paths on the clone.
VPN_DIR = "/etc/openvpn/server/ccrp"
# What ccrp pushes after boot (keys, certificates, CRL, password hash), never on the clone's root
# disk, so no snapshot of any kind can capture it: a tmpfs on clouds (mounted at every boot by
# the user-data's bootcmd), the clone's own volume on Docker (which `docker commit` leaves out).
SECRETS_DIR = f"{VPN_DIR}/keys"
# OpenVPN's management socket, in a root-only runtime directory made by ccrp-openvpn.service (the
# unit sets it, and agent/health.py has its own copy of the path: it runs on the clone, stdlib only).
MGMT_SOCKET = "/run/ccrp-openvpn/mgmt.sock"
CCRP_ETC = "/etc/ccrp"
# What the clone's autostop agent leaves when it powers the clone off: this file on the clone's
# disk (read from a stopped Docker clone) and the same line on the console (kept by the clouds),
# after the mark. At start it writes AUTOSTOP_BOOT_LINE after the mark, so a console that keeps
# every boot tells a stop of this boot from an earlier one (providers/base.py autostop_note).
# agent/autostop.py has its own copy of all three.
AUTOSTOP_NOTE = "/var/lib/ccrp/autostop.note"
AUTOSTOP_MARK = "ccrp-autostop: "
AUTOSTOP_BOOT_LINE = "watching this boot"
CCRP_LIB = "/usr/local/lib/ccrp"
# The topic relay runs as its own user: it reads only relay.key and ca.crt in SECRETS_DIR.
RELAY_USER = "ccrp-relay"
# The API manager (docs/services.md) runs as its own user: it reads only its backend's key in
# SECRETS_DIR (google-vision), and its config and status file.
API_USER = "ccrp-api"
# The operator's login on a cloud clone (sudo, the fleet's operator key), created by the clone's
# user-data on every cloud: the base images' own users differ (admin on AWS, debian on OpenStack,
# none on GCP). Docker clones have no login user.
LOGIN_USER = "ccrp"
# The knowledge agent (docs/services.md) runs as its own user: it reads the relay's TLS files (as a
# supplementary member of RELAY_USER's group) and writes only its datasets and runtime directory.
KNOWLEDGE_USER = "ccrp-knowledge"
# The power agent (agent/power.py) runs as its own user, listening on the clone's VPN address at
# POWER_PORT for the robot's power device, the one peer the firewall lets reach it.
POWER_USER = "ccrp-power"
POWER_PORT = 11400
# The fleet's own software (workloads.py): its install space (catkin) / build output, in the snapshot.
WORKSPACE = "/opt/ccrp/workspace"

# What a clone image holds beyond its recipe, on every backend (the Docker build and the clouds' bake):
# The locale of every clone image, set by templates/docker/Dockerfile.j2 and the clouds' bake (both
# run this same command): generated once in the image and recorded in /etc/default/locale, so
# cloud-init's locale module finds it set and no clone runs locale-gen at boot (seconds of CPU each).
LOCALE = "en_US.UTF-8"
LOCALE_SETUP = (f"sed -i 's/^# *\\({LOCALE} UTF-8\\)/\\1/' /etc/locale.gen && locale-gen >/dev/null "
                f"&& update-locale LANG={LOCALE}")

# A ROS 2 subscriber's UDP socket gets the kernel's default receive buffer (rmw_fastrtps sizes none
# on its own): 208 KB holds three of an image's four 64 KB datagrams, and the kernel drops the
# fourth whenever the node is slower to read than the burst. With 4 MB, the last hop of the relay
# dropped none (docs/ros2.md). rmem_max lets the relay agent's profile ask for its 2 MB (doubled).
# A clone with its own kernel gets them from its user-data; `ccrp doctor` checks Docker's host.
ROS2_SYSCTL = "/etc/sysctl.d/60-ccrp-ros2.conf"
ROS2_RMEM = 4_194_304

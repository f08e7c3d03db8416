"""The GCP startup-script (templates/gcp/startup-script) for real, in a Debian 12 container that has
no cloud-init, as Debian's own GCE images have none: the script installs cloud-init from Debian and
runs its stages, and the `snapshot bake` builder user-data then installs the debian-bookworm recipe.

What stands in for GCE here: the container is started by hand (no Google guest agent runs the
script), and the user-data comes from a NoCloud seed, with a config file that outranks the
script's `datasource_list: [ GCE, None ]`, instead of GCE's metadata server. Everything else is
Debian's: its archive, its cloud-init 22.4, its OpenVPN, and PyPI for the relay's Zenoh.
Needs Docker, mmdebstrap (once, for the image) and network access to deb.debian.org and PyPI.
"""

from __future__ import annotations

import secrets
import shutil
import subprocess
from pathlib import Path

import pytest

from tests.conftest import ROOT
from tests.e2e.fleet import NO_DOCKER

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(NO_DOCKER is not None, reason=f"needs a running Docker engine ({NO_DOCKER})"),
]

docker = pytest.importorskip("docker")

from ccrp_cli.loader import load_inventory  # noqa: E402
from ccrp_cli.render.cloudinit import builder_user_data, dump, login_user  # noqa: E402
from ccrp_cli.services.registry import image_agents  # noqa: E402

# Debian 12 minbase with what Debian's GCE image has and ccrp relies on (systemd, CA certificates,
# sshd, sudo), and no cloud-init: kept between runs.
IMAGE = "ccrp-test/debian-12-no-cloud-init:2"
TOKEN = secrets.token_hex(8)
KEY = "ssh-ed25519 AAAAC3NzaC1lZDI1NTE5AAAAIKz9iKHWxQ7rTnGpOLtuJ6LZ1R0s6cE4lqbEe5vDzEbh"

# The test's own steps around the script: this machine's egress CAs (PyPI through a proxy that
# signs with them), the NoCloud seed, the script, then the checks.
HARNESS = """#!/bin/sh
set -e
if ls /extra-ca/*.crt >/dev/null 2>&1; then cp /extra-ca/*.crt /usr/local/share/ca-certificates/; fi
update-ca-certificates >/dev/null 2>&1
if command -v cloud-init; then echo "the image has cloud-init already"; exit 3; fi
mkdir -p /etc/cloud/cloud.cfg.d /var/lib/cloud/seed/nocloud
printf 'datasource_list: [ NoCloud, None ]\\n' > /etc/cloud/cloud.cfg.d/99-test-nocloud.cfg
cp /t/user-data /t/meta-data /var/lib/cloud/seed/nocloud/
set +e
sh /t/startup-script > /t/first.log 2>&1; echo "first-rc=$?"
cloud-init status --long; echo "status-rc=$?"
# As at a later boot: cloud-init's systemd generator marked the boot, so the script does nothing.
mkdir -p /run/cloud-init && touch /run/cloud-init/enabled
sh /t/startup-script > /t/second.log 2>&1; echo "second-rc=$?"
cat /etc/cloud/cloud.cfg.d/95-ccrp-gce.cfg /etc/default/instance_configs.cfg /etc/default/locale
locale -a | grep -x en_US.utf8
python3 -c 'import zenoh; print("zenoh-imports")'
openvpn --version | head -1
dpkg-query -W -f='${Status} ${Package}\\n' ros-core python3-rospy cloud-init
test -x /usr/local/lib/ccrp/relay.py && echo relay-agent-present
echo "machine-id-bytes=$(wc -c < /etc/machine-id)"
# The snapshot's users: ccrp's login user without key or sudo, not the image's default user.
id -un ccrp && echo "builder-made-ccrp"
getent passwd debian >/dev/null && echo "image-default-user-present"
grep -rl ccrp /etc/sudoers.d/ && echo "ccrp-has-sudo-on-the-builder"
grep -s "^ssh-" /home/ccrp/.ssh/authorized_keys && echo "ccrp-has-keys-on-the-builder"
# A clone's first boot from that image: a new instance whose user-data gives the user its key and
# sudo. All four stages, as systemd runs them at boot (the local one finds the new instance).
rm -rf /run/cloud-init  # /run is empty at a boot
printf 'instance-id: gce-startup-script-clone\nlocal-hostname: cri-nao1\n' > /var/lib/cloud/seed/nocloud/meta-data
cp /t/clone-user-data /var/lib/cloud/seed/nocloud/user-data
(cloud-init init --local && cloud-init init && cloud-init modules --mode config && cloud-init modules --mode final) \
    > /t/clone.log 2>&1
echo "clone-rc=$?"
sudo -l -U ccrp | grep -q "NOPASSWD: ALL" && echo "clone-ccrp-sudo"
grep -q "clone-test-key" /home/ccrp/.ssh/authorized_keys && echo "clone-ccrp-key"
"""


@pytest.fixture(scope="module")
def image():
    client = docker.from_env()
    try:
        client.images.get(IMAGE)
        return IMAGE
    except docker.errors.ImageNotFound:
        pass
    if shutil.which("mmdebstrap") is None:
        pytest.skip(f"{IMAGE} is missing and mmdebstrap is not installed to build it")
    deb = subprocess.Popen(["mmdebstrap", "--variant=minbase", "--include=ca-certificates,systemd,systemd-sysv,openssh-server,sudo",
                            "bookworm", "-"], stdout=subprocess.PIPE)
    imp = subprocess.run(["docker", "import", "--change", "LABEL ccrp-test=gce-startup-script", "-", IMAGE],
                         stdin=deb.stdout, capture_output=True, check=False)
    deb.stdout.close()
    assert deb.wait() == 0 and imp.returncode == 0, imp.stderr.decode()[-500:]
    return IMAGE


def test_startup_script_installs_cloud_init_which_bakes_the_recipe(image, tmp_path: Path):
    inv = load_inventory(ROOT / "inventories" / "gcp.yaml")
    (tmp_path / "user-data").write_text(builder_user_data(inv, TOKEN, image_agents()))
    (tmp_path / "meta-data").write_text("instance-id: gce-startup-script-test\nlocal-hostname: ccrp-builder\n")
    shutil.copy(ROOT / "templates" / "gcp" / "startup-script", tmp_path / "startup-script")
    (tmp_path / "clone-user-data").write_text(dump({"users": [login_user([f"{KEY} clone-test-key"])]}))
    (tmp_path / "harness").write_text(HARNESS)
    volumes = {str(tmp_path): {"bind": "/t", "mode": "rw"}}
    if Path("/usr/local/share/ca-certificates").is_dir():
        volumes["/usr/local/share/ca-certificates"] = {"bind": "/extra-ca", "mode": "ro"}
    client = docker.from_env()
    container = client.containers.run(image, ["sh", "/t/harness"], detach=True, tty=True, volumes=volumes,
                                      labels={"ccrp-test": "gce-startup-script"})
    try:
        result = container.wait(timeout=1500)
        out = container.logs().decode(errors="replace")
    finally:
        container.remove(force=True)
    first = (tmp_path / "first.log").read_text(errors="replace")
    assert result["StatusCode"] == 0, out[-2000:]
    assert "first-rc=0" in out and "status: done" in out and "status-rc=0" in out, out[-2000:] + first[-2000:]
    # The builder's proofs and final message, as the bake reads them on the serial console.
    for proof in ("apt", "locale", "pip"):
        assert f"ccrp-bake {TOKEN} {proof}-ok" in first, first[-2000:]
    assert f"ccrp-bake {TOKEN} finished after" in first
    assert "datasource_list: [ GCE, None ]" in out and "set_host_keys = false" in out
    assert "LANG=en_US.UTF-8" in out and "en_US.utf8" in out
    assert "zenoh-imports" in out and "relay-agent-present" in out
    assert "OpenVPN 2.6." in out  # data-ciphers in the rendered server.conf needs 2.5 or newer
    assert "install ok installed ros-core" in out and "install ok installed cloud-init" in out
    assert "machine-id-bytes=0" in out  # every clone of the snapshot gets its own
    # Once cloud-init runs at boot by itself, the script steps aside.
    assert "second-rc=0" in out and (tmp_path / "second.log").read_text() == ""
    # The snapshot holds ccrp's user without key or sudo and no default user of the image; a clone's
    # user-data then gives that user the operator key and sudo.
    assert "builder-made-ccrp" in out and "image-default-user-present" not in out
    assert "ccrp-has-sudo-on-the-builder" not in out and "ccrp-has-keys-on-the-builder" not in out
    clone = (tmp_path / "clone.log").read_text(errors="replace")
    assert "clone-rc=0" in out and "clone-ccrp-sudo" in out and "clone-ccrp-key" in out, out[-1500:] + clone[-1500:]

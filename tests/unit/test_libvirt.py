"""The libvirt backend without libvirt: its inventory settings, the XML it hands libvirt (parsed
back: names, ownership metadata, disks and backing files, NICs, console), the NoCloud seed, the
golden volume's layer, and the one-line error when the binding is missing."""

from __future__ import annotations

import ipaddress
import json
import shutil
import re
import sys
import time
import xml.etree.ElementTree as ET

import pytest
import yaml

from ccrp_cli.errors import CcrpError, InputError
from ccrp_cli.loader import load_inventory
from ccrp_cli.providers import REGISTRY
from ccrp_cli.providers.base import Ability, CloneState, owner_labels
from ccrp_cli.providers.libvirt import client, goldens, images, provider, seed, xmldefs


def inventory(tmp_path, **settings):
    data = {"fleet": "vmlab", "provider": {"kind": "libvirt", **settings}, "robots": [{"name": "nao1"}]}
    path = tmp_path / "ccrp.yaml"
    path.write_text(yaml.safe_dump(data))
    return load_inventory(path)


def domain_spec(**over) -> xmldefs.DomainSpec:
    base = dict(name="ccrp-vmlab-cri-nao1", title="ccrp clone of robot nao1 (fleet vmlab)",
                labels=owner_labels("vmlab", "clone", "nao1"), common_ip="10.90.0.10", accel="tcg", memory_mb=2048,
                vcpus=2, pool="ccrp", disk="ccrp-vmlab-cri-nao1.qcow2", seed="ccrp-vmlab-cri-nao1-seed.iso",
                kernel="/pool/ccrp-vmlab-golden-20261126040000.vmlinuz",
                initrd="/pool/ccrp-vmlab-golden-20261126040000.initrd",
                console_log="/pool/ccrp-vmlab-cri-nao1.console",
                nics=(xmldefs.Nic("ccrp-vmlab-public", "52:54:00:aa:bb:cc"),
                      xmldefs.Nic("ccrp-vmlab-common", "52:54:00:dd:ee:ff")))
    return xmldefs.DomainSpec(**(base | over))


# -- settings -------------------------------------------------------------------------------------------

def test_settings_defaults_and_registry(tmp_path):
    inv = inventory(tmp_path)
    p = inv.provider
    assert (p.kind, p.uri, p.accel, p.memory_mb, p.vcpus, p.pool) == ("libvirt", "qemu:///system", "auto", 2048, 2, "ccrp")
    assert p.public_cidr == ipaddress.IPv4Network("192.168.150.0/24")
    info = REGISTRY["libvirt"]
    assert info.factory == ".libvirt.provider:LibvirtProvider" and ("libvirt", "libvirt") in info.sdk_modules
    assert info.platform == "debian-bookworm" and info.abilities == {Ability.LOCAL_BUILD, Ability.ROBOT_ATTACH}


@pytest.mark.parametrize("field,value", [
    ("uri", "qemu:///system; rm -rf /"), ("uri", "not a uri"), ("accel", "hvf"), ("memory_mb", 64),
    ("vcpus", 0), ("pool", "../etc"), ("pool_dir", "relative/dir"), ("pool_dir", "/var/../etc"),
])
def test_bad_settings_are_one_line_errors(tmp_path, field, value):
    with pytest.raises(InputError) as err:
        inventory(tmp_path, **{field: value})
    assert "\n" not in err.value.one_line() and "provider" in err.value.one_line()


def test_inventory_rules_come_from_the_backends_declarations(tmp_path):
    """The NAT network is checked against the VPN pool like Docker's public network, and a platform
    baked from the user's own image is refused as on Docker (libvirt bakes nothing): the rules are
    the settings' networks() and the registry's abilities, not a branch per kind."""
    with pytest.raises(InputError, match="overlaps provider.public_cidr"):
        inventory(tmp_path, public_cidr="10.80.4.0/24")
    data = {"fleet": "vmlab", "provider": {"kind": "libvirt"}, "ros": {"distro": "jazzy", "platform": "ubuntu-noble-ros"},
            "robots": [{"name": "nao1"}]}
    (tmp_path / "ccrp.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(InputError, match="is for clouds .* libvirt clones run debian-bookworm"):
        load_inventory(tmp_path / "ccrp.yaml")


def test_remote_uri_accepted(tmp_path):
    assert inventory(tmp_path, uri="qemu+ssh://ops@lab1.example/system", accel="tcg").provider.uri.startswith("qemu+ssh://")


@pytest.mark.parametrize("uri", [
    "qemu:///system", "qemu+unix:///system", "qemu:///session", "qemu+ssh://ops@lab1.example/system",
    "qemu+ssh://root@127.0.0.1:2222/system?keyfile=/root/.ssh/lab_ed25519", "qemu+ssh://lab1/system?mode=direct&proxy=native",
    "qemu+tls://lab1.example/system", "qemu://lab1.example/system", "qemu+ssh://ops@[fd00::5]/system",
])
def test_uris_ccrp_opens_load(tmp_path, uri):
    assert inventory(tmp_path, uri=uri).provider.uri == uri


@pytest.mark.parametrize("uri,line", [
    # Issue 39: opening these ran a program of the inventory's, or took the host unverified.
    ("qemu+ext:///system?command=/tmp/x", "transport qemu+ext is refused"),
    ("qemu+tcp://10.0.0.5/system", "transport qemu+tcp is refused"),
    ("qemu+libssh://lab1/system", "transport qemu+libssh is refused"),
    ("qemu+ssh://h/system?command=./x", "parameter command is refused: it runs a program on this machine"),
    ("qemu+ssh://h/system?netcat=/tmp/nc", "parameter netcat is refused"),
    ("qemu+ssh://h/system?keyfile=/k&socket=/tmp/s", "parameter socket is refused"),
    ("qemu+unix:///system?socket=/tmp/s", "parameter socket is refused"),
    ("qemu+ssh://h/system?no_verify=1", "parameter no_verify is refused: it turns off the check"),
    ("qemu+tls://h/system?no_verify=1", "parameter no_verify is refused"),
    ("qemu+ssh://h/system?No_Verify=1", "parameter No_Verify is refused"),  # libvirt reads names in any case
    ("qemu+ssh://h/system?no_tty=1", "parameter no_tty is refused"),
    ("qemu+ssh://h/system?known_hosts_verify=ignore", "parameter known_hosts_verify is refused"),
    ("qemu+ssh://h/system?sshauth=password", "parameter sshauth is refused"),
    ("qemu+tls://h/system?pkipath=/tmp/pki", "parameter pkipath is refused"),
    ("qemu+tls://h/system?tls_priority=NORMAL", "parameter tls_priority is refused"),
    ("qemu+ssh://h/system?name=qemu/system", "parameter name is refused"),
    ("qemu+ssh://h/system?frobnicate=1", "parameter frobnicate is refused: ccrp does not know it"),
    ("qemu+ssh://h/system?mode=x", "mode=x: give one of auto, direct, legacy"),
    ("qemu+ssh://h/system?keyfile", "parameter keyfile has no value"),
    ("qemu+ssh://h/system?keyfile=-oProxyCommand=x", "give the key's absolute path"),
    ("qemu+ssh:///system", "qemu+ssh needs a host"),
    ("qemu+unix://h/system", "qemu+unix is this machine's socket"),
    ("qemu:///embed", "path /embed is not"),
    ("qemu+ssh://-oProxyCommand/system", "is not a libvirt URI"),  # a host ssh would read as an option
    ("qemu+ssh://-F.x@h/system", "is not a libvirt URI"),
    ("qemu+ssh://h/system?command=%2Ftmp%2Fx", "is not a libvirt URI"),  # no escapes to hide a name or value in
    ("qemu+ssh://h/system;command=/x", "is not a libvirt URI"),
])
def test_uris_that_run_programs_or_skip_checks_are_refused_in_one_line(tmp_path, uri, line):
    with pytest.raises(InputError) as err:
        inventory(tmp_path, uri=uri)
    text = err.value.one_line()
    assert "\n" not in text and "provider.uri" in text and line in text, text


def test_fleet_validate_refuses_a_uri_that_names_a_program(tmp_path):
    """What issue 39 tried: `fleet validate` accepted it and `ccrp status` ran the script."""
    import subprocess

    ran = tmp_path / "ran"
    script = tmp_path / "x"
    script.write_text(f"#!/bin/sh\ntouch {ran}\n")
    script.chmod(0o755)
    data = {"fleet": "vmlab", "provider": {"kind": "libvirt", "uri": f"qemu+ext:///system?command={script}"},
            "robots": [{"name": "nao1"}]}
    (tmp_path / "ccrp.yaml").write_text(yaml.safe_dump(data))
    env = {k: v for k, v in __import__("os").environ.items() if k != "CCRP_INVENTORY"} | {"CCRP_HOME": str(tmp_path / "home")}
    for argv in (["fleet", "validate"], ["status"]):
        out = subprocess.run([sys.executable, "-m", "ccrp_cli", *argv, "-i", str(tmp_path / "ccrp.yaml")],
                             capture_output=True, text=True, env=env, timeout=120)
        assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1, out.stderr
        assert "transport qemu+ext is refused" in out.stderr and "Traceback" not in out.stderr
    assert not ran.exists()


def test_the_operators_uri_parameters_come_from_the_environment(tmp_path, monkeypatch):
    """A wrapper ssh (the remote e2e test's) is this machine's: added from CCRP_LIBVIRT_URI_PARAMS
    to the inventory's URI when the connection is opened, never read from the inventory."""
    from types import SimpleNamespace

    from ccrp_cli.providers.libvirt.settings import URI_PARAMS_ENV, connect_uri

    assert connect_uri("qemu+ssh://h/system", {}) == "qemu+ssh://h/system"
    assert connect_uri("qemu+ssh://h/system?keyfile=/k", {URI_PARAMS_ENV: "command=/opt/ssh"}) == \
        "qemu+ssh://h/system?keyfile=/k&command=/opt/ssh"
    with pytest.raises(InputError, match=URI_PARAMS_ENV):
        connect_uri("qemu+ssh://h/system", {URI_PARAMS_ENV: "command=/opt/ssh -v"})
    opened = []
    monkeypatch.setattr(client, "_sdk", lambda: SimpleNamespace(open=opened.append, libvirtError=Exception))
    monkeypatch.setenv(URI_PARAMS_ENV, "command=/opt/ssh-pinned")
    inv = inventory(tmp_path, uri="qemu+ssh://ops@lab1/system")
    provider.LibvirtProvider(inv, tmp_path)
    assert opened == ["qemu+ssh://ops@lab1/system?command=/opt/ssh-pinned"]


# -- domain XML ------------------------------------------------------------------------------------------

def test_domain_xml_round_trip():
    text = xmldefs.domain(domain_spec())
    info = xmldefs.domain_info(text)
    assert info.name == "ccrp-vmlab-cri-nao1"
    assert info.labels == {"ccrp-managed": "true", "ccrp-fleet": "vmlab", "ccrp-role": "clone", "ccrp-robot": "nao1"}
    assert info.common_ip == "10.90.0.10"
    assert info.macs == {"ccrp-vmlab-public": "52:54:00:aa:bb:cc", "ccrp-vmlab-common": "52:54:00:dd:ee:ff"}
    assert info.volumes == ("ccrp-vmlab-cri-nao1.qcow2", "ccrp-vmlab-cri-nao1-seed.iso")
    assert (info.memory_mb, info.vcpus) == (2048, 2)


def test_domain_xml_devices():
    dom = ET.fromstring(xmldefs.domain(domain_spec()))
    # TCG: every instruction set QEMU emulates (the ROS 2 wheels' native code needs more than qemu64's)
    assert dom.get("type") == "qemu" and dom.find("cpu").get("mode") == "maximum"
    assert dom.findtext("os/kernel").endswith(".vmlinuz") and dom.findtext("os/initrd").endswith(".initrd")
    assert "root=/dev/vda" in dom.findtext("os/cmdline") and "console=ttyS0" in dom.findtext("os/cmdline")
    disks = dom.findall("devices/disk")
    assert [(d.find("target").get("dev"), d.find("driver").get("type"), d.find("readonly") is not None)
            for d in disks] == [("vda", "qcow2", False), ("vdb", "raw", True)]
    assert all(d.find("source").get("pool") == "ccrp" for d in disks)
    assert dom.find("devices/serial/log").get("file") == "/pool/ccrp-vmlab-cri-nao1.console"
    assert dom.find("devices/rng/backend").text == "/dev/urandom"
    assert dom.find("devices/channel/target").attrib == {"type": "virtio", "name": "org.qemu.guest_agent.0"}
    assert dom.findtext("on_poweroff") == "destroy" and dom.find("features/acpi") is not None
    kvm = ET.fromstring(xmldefs.domain(domain_spec(accel="kvm")))
    assert kvm.get("type") == "kvm" and kvm.find("cpu").get("mode") == "host-passthrough"


def test_names_are_elements_not_markup():
    """A name is text in an element: markup in it stays text (names are checked before, too)."""
    text = xmldefs.domain(domain_spec(title="a</title><devices/>"))
    assert ET.fromstring(text).findtext("title") == "a</title><devices/>"
    assert len(ET.fromstring(text).findall("devices")) == 1


def test_domain_without_metadata_is_nobodys():
    info = xmldefs.domain_info("<domain type='kvm'><name>other</name><memory unit='KiB'>1048576</memory></domain>")
    assert info.labels == {} and info.common_ip is None and info.memory_mb == 1024


def test_overlay_volume_names_its_backing_file():
    vol = ET.fromstring(xmldefs.volume("ccrp-vmlab-cri-nao1.qcow2", 8 << 30, "qcow2",
                                       backing="/pool/ccrp-vmlab-golden-20261126040000.qcow2"))
    assert vol.findtext("name") == "ccrp-vmlab-cri-nao1.qcow2"
    assert vol.find("capacity").text == str(8 << 30) and vol.find("capacity").get("unit") == "bytes"
    assert vol.find("target/format").get("type") == "qcow2"
    assert vol.findtext("backingStore/path") == "/pool/ccrp-vmlab-golden-20261126040000.qcow2"
    assert vol.find("backingStore/format").get("type") == "qcow2"
    assert ET.fromstring(xmldefs.volume("seed.iso", 1000, "raw")).find("backingStore") is None


def test_networks():
    cidr = ipaddress.IPv4Network("192.168.150.0/24")
    nat = ET.fromstring(xmldefs.nat_network("ccrp-vmlab-public", xmldefs.bridge_name("vmlab", "public"), cidr))
    assert nat.findtext("name") == "ccrp-vmlab-public" and nat.find("forward").get("mode") == "nat"
    assert nat.find("ip").get("address") == "192.168.150.1" and nat.find("ip").get("netmask") == "255.255.255.0"
    assert (nat.find("ip/dhcp/range").get("start"), nat.find("ip/dhcp/range").get("end")) == ("192.168.150.2", "192.168.150.238")
    iso = ET.fromstring(xmldefs.isolated_network("ccrp-vmlab-common", xmldefs.bridge_name("vmlab", "common")))
    assert iso.find("forward") is None and iso.find("ip") is None  # no route out, no host address
    names = {xmldefs.bridge_name(f, r) for f in ("vmlab", "a" * 31, "vmlab2") for r in ("public", "common")}
    assert len(names) == 6 and all(len(n) <= 15 for n in names)


def test_macs_are_stable_local_and_distinct():
    a = xmldefs.mac_address("vmlab", "nao1", "public")
    assert a == xmldefs.mac_address("vmlab", "nao1", "public") and a.startswith("52:54:00:")
    assert len({a, xmldefs.mac_address("vmlab", "nao1", "common"), xmldefs.mac_address("vmlab", "nao2", "public")}) == 3


def test_probe_domain_has_no_disk_and_ends_itself():
    dom = ET.fromstring(xmldefs.probe_domain("ccrp-vmlab-kvm-probe", "/k", "/i", "/pool/p.console"))
    assert dom.get("type") == "kvm" and dom.find("devices/disk") is None
    assert "panic=-1" in dom.findtext("os/cmdline") and dom.findtext("on_reboot") == "destroy"


# -- seed ------------------------------------------------------------------------------------------------

def test_network_config_names_interfaces_by_mac():
    cfg = yaml.safe_load(seed.network_config("52:54:00:00:00:01", "52:54:00:00:00:02", "10.90.0.10",
                                             ipaddress.IPv4Network("10.90.0.0/24")))
    assert cfg["version"] == 2
    assert cfg["ethernets"]["public"] == {"match": {"macaddress": "52:54:00:00:00:01"}, "set-name": "public",
                                          "dhcp4": True}
    common = cfg["ethernets"]["common"]
    assert common["set-name"] == "common"  # the names the golden's networkd drop-ins are for
    assert common["match"] == {"macaddress": "52:54:00:00:00:02"} and common["addresses"] == ["10.90.0.10/24"]
    assert "gateway4" not in common and "routes" not in common


def test_meta_data():
    assert yaml.safe_load(seed.meta_data("vmlab-nao1-1", "cri-nao1")) == {"instance-id": "vmlab-nao1-1",
                                                                           "local-hostname": "cri-nao1"}


@pytest.mark.skipif(not any(shutil.which(t[0]) for t in seed.ISO_TOOLS), reason="neither genisoimage nor xorriso installed")
def test_seed_iso_is_labelled_cidata_and_holds_the_files():
    iso = seed.seed_iso("#cloud-config\nhostname: cri-nao1\n", "vmlab-nao1-1", "cri-nao1", "version: 2\n")
    pvd = iso[16 * 2048:17 * 2048]  # ISO 9660's primary volume descriptor
    assert pvd[1:6] == b"CD001" and pvd[40:72].decode().strip() == "cidata"
    assert b"#cloud-config\nhostname: cri-nao1\n" in iso and b"instance-id: vmlab-nao1-1" in iso


def test_no_iso_tool_is_one_line(monkeypatch):
    monkeypatch.setattr(seed.shutil, "which", lambda name: None)
    with pytest.raises(CcrpError, match="genisoimage"):
        seed.seed_iso("#cloud-config\n", "i", "h", "version: 2\n")


# -- provider pieces that need no libvirt -------------------------------------------------------------------

def test_every_libvirt_state_has_a_ccrp_state():
    assert set(provider.WORDS) == set(provider.STATES)
    assert provider.STATES["shutoff"] is CloneState.STOPPED and provider.STATES["running"] is CloneState.RUNNING
    assert CloneState.UNKNOWN not in provider.STATES.values()


@pytest.mark.parametrize("name,fleet,robot", [
    ("ccrp-vmlab-golden-20261126040000.qcow2", "vmlab", None),
    ("ccrp-vmlab-golden-nao1-20261126040000.qcow2", "vmlab", "nao1"),
    ("ccrp-vmlab-golden-20261126040000.vmlinuz", None, None),
    ("ccrp-vmlab-cri-nao1.qcow2", None, None),
])
def test_golden_volume_names(name, fleet, robot):
    m = images.GOLDEN.match(name)
    assert (m["fleet"] if m else None, m["robot"] if m else None) == (fleet, robot)


def test_missing_binding_is_one_line(tmp_path, monkeypatch):
    from ccrp_cli.providers import get_provider

    monkeypatch.setitem(sys.modules, "libvirt", None)  # import libvirt -> ImportError
    with pytest.raises(CcrpError) as err:
        get_provider(inventory(tmp_path), tmp_path)
    assert "libvirt Python binding" in err.value.message and "ccrp[libvirt]" in err.value.hint


# -- golden volume ---------------------------------------------------------------------------------------

def test_golden_layer_and_cloud_config():
    text = goldens.dockerfile("ccrp/vmlab-clone:20261126040000")
    assert text.splitlines()[1] == "FROM ccrp/vmlab-clone:20261126040000"
    assert "linux-image-cloud-amd64" in text and "rm -f /etc/ssh/ssh_host_*" in text
    cfg = yaml.safe_load(goldens.CLOUD_CFG)
    # libvirt's NoCloud seed first; the same golden boots on Nova from its config drive, cloud-init
    # running whatever ds-identify guessed, the drive's drivers in the initramfs (docs/openstack.md).
    assert cfg["datasource_list"] == ["NoCloud", "ConfigDrive", "None"]
    assert yaml.safe_load(goldens.DS_IDENTIFY_CFG) == {"policy": "enabled"}
    assert "COPY ds-identify.cfg /etc/cloud/ds-identify.cfg" in text
    assert set(goldens.INITRAMFS_MODULES.split()) == {"ata_piix", "sr_mod"}
    assert text.index("/usr/share/initramfs-tools/modules.d/") < text.index("linux-image-cloud-amd64")
    # The host keys on the console as soon as they are made: ccrp's login overlaps the later stages.
    init = cfg["cloud_init_modules"]
    assert init.index("keys-to-console") == init.index("ssh") + 1 and "keys-to-console" not in cfg["cloud_final_modules"]
    assert "bootcmd" in cfg["cloud_init_modules"]  # the secrets tmpfs (render/cloudinit.py every_boot_bootcmd)
    assert cfg["system_info"]["network"]["renderers"] == ["networkd"] and "network" not in cfg
    assert goldens.FSTAB.split()[:3] == ["/dev/vda", "/", "ext4"]
    # No wait for IPv6 router advertisements on the NICs seed.py names.
    for name in seed.NIC_NAMES:
        assert f"COPY no-ra.conf /etc/systemd/network/10-cloud-init-{name}.network.d/90-ccrp-no-ra.conf" in text
    assert "IPv6AcceptRA=no" in goldens.NO_RA_DROPIN
    # A resolver (the DHCP server's DNS, through resolved's stub), with no LLMNR or mDNS responder.
    assert "systemd-resolved" in goldens.VM_PACKAGES and "systemd-resolved.service" in text
    assert "/etc/systemd/resolved.conf.d/" in text
    assert {"LLMNR=no", "MulticastDNS=no"} <= set(goldens.RESOLVED_CONF.splitlines())
    # QEMU's guest agent, for the clock only: every RPC the installed agent lists is blocked but these.
    assert "qemu-guest-agent" in goldens.VM_PACKAGES
    [line] = [x for x in text.splitlines() if "qemu-ga --block-rpcs=help" in x]
    allowed = set(re.search(r"grep -vxE '([^']+)'", line).group(1).split("|"))
    assert allowed == {"guest-sync-delimited", "guest-sync", "guest-ping", "guest-info", "guest-get-time", "guest-set-time"}


def golden_tree(tmp_path):
    root = tmp_path / "root"
    (root / "boot").mkdir(parents=True)
    (root / "usr/lib/linux").mkdir(parents=True)
    (root / "usr/lib/linux/vmlinuz-6.1.0-28-cloud-amd64").write_bytes(b"kernel of the tree")
    (root / "boot/initrd.img-6.1.0-28-cloud-amd64").write_bytes(b"initramfs of the tree")
    secret = tmp_path / "ca.key"  # outside the tree, as the fleet's CA key would be
    secret.write_bytes(b"PRIVATE KEY")
    return root, secret


@pytest.mark.parametrize("link", ["/usr/lib/linux/vmlinuz-6.1.0-28-cloud-amd64",  # absolute: the tree's path
                                  "../usr/lib/linux/vmlinuz-6.1.0-28-cloud-amd64",
                                  "../../../../../../usr/lib/linux/vmlinuz-6.1.0-28-cloud-amd64"])  # .. stops at the root
def test_boot_files_follow_links_inside_the_golden_tree_only(tmp_path, link):
    root, _ = golden_tree(tmp_path)
    (root / "boot/vmlinuz-6.1.0-28-cloud-amd64").symlink_to(link)
    out = tmp_path / "out"
    out.mkdir()
    kernel, initrd = goldens._boot_files(root, out)
    assert kernel.read_bytes() == b"kernel of the tree" and initrd.read_bytes() == b"initramfs of the tree"
    assert not kernel.is_symlink()


@pytest.mark.parametrize("case", ["absolute", "relative", "boot-dir", "fifo"])
def test_a_boot_file_leading_out_of_the_golden_tree_is_refused_in_one_line(tmp_path, case):
    """Issue 39: a package of the build pointed boot/vmlinuz-* at a file of the host (the fleet's CA
    key), which was copied out as the kernel and uploaded to the pool."""
    root, secret = golden_tree(tmp_path)
    kernel = root / "boot/vmlinuz-6.1.0-28-cloud-amd64"
    if case == "absolute":
        kernel.symlink_to(secret)
    elif case == "relative":
        kernel.symlink_to("../" * 12 + str(secret).lstrip("/"))
    elif case == "boot-dir":  # boot itself a link to a directory of the host holding a kernel
        outside = tmp_path / "host-boot"
        outside.mkdir()
        (outside / "vmlinuz-6.1").write_bytes(b"PRIVATE KEY")
        (outside / "initrd.img-6.1").write_bytes(b"PRIVATE KEY")
        shutil.rmtree(root / "boot")
        (root / "boot").symlink_to(outside)
    else:  # a FIFO (or a device node: tar extracts them as root) would be read as the kernel
        import os

        os.mkfifo(kernel)
    out = tmp_path / "out"
    out.mkdir()
    with pytest.raises(CcrpError) as err:
        goldens._boot_files(root, out)
    assert "\n" not in err.value.one_line() and "golden tree" in err.value.message
    assert not any(p.read_bytes() == b"PRIVATE KEY" for p in out.iterdir())


def test_tree_paths_stay_in_the_tree(tmp_path):
    root, _ = golden_tree(tmp_path)
    host_etc = tmp_path / "host-etc"  # resolv.conf is replaced in the tree's /etc, never in one of the host's
    host_etc.mkdir()
    (root / "etc").symlink_to(host_etc)
    assert goldens.tree_path(root, "etc") == root / str(host_etc).lstrip("/")
    assert goldens.tree_path(root, "usr/lib/../../../..") == root
    (root / "loop").symlink_to("/loop")
    with pytest.raises(CcrpError, match="more than 40 links"):
        goldens.tree_path(root, "loop/x")


def test_golden_needs_its_tools(monkeypatch, tmp_path):
    monkeypatch.setattr(goldens.shutil, "which", lambda name: None if name == "qemu-img" else f"/usr/bin/{name}")
    with pytest.raises(CcrpError) as err:
        goldens.build(object(), "ccrp/vmlab-clone:1", tmp_path)
    assert "qemu-img" in err.value.message and "qemu-utils" in err.value.hint


# -- what the fleet owns, against a stand-in connection (names and metadata as libvirt returns them) -----

class _Vol:
    def __init__(self, name, allocation=0):
        self._name, self.allocation = name, allocation

    def name(self):
        return self._name

    def info(self):  # virStorageVolInfo: type, capacity, allocation (bytes)
        return [0, 8 << 30, self.allocation]


class _Pool:
    def __init__(self, names, capacity=100 << 30, available=50 << 30):
        # a name, or (name, allocation in bytes) for an overlay whose writes count
        self.vols = [_Vol(*((n,) if isinstance(n, str) else n)) for n in names]
        self.capacity, self.available, self.refreshed = capacity, available, 0

    def refresh(self, flags):
        self.refreshed += 1
        return 0

    def isActive(self):
        return True

    def info(self):  # virStoragePoolInfo: state, capacity, allocation, available (bytes)
        return [2, self.capacity, self.capacity - self.available, self.available]

    def listAllVolumes(self, flags):
        return self.vols

    def storageVolLookupByName(self, name):
        found = [v for v in self.vols if v.name() == name]
        if not found:
            raise _LibvirtError(_SDK.VIR_ERR_NO_STORAGE_VOL)
        return found[0]


class _Dom:
    def __init__(self, name, labels, uuid, memory_mb=2048, vcpus=2, active=True):
        self._xml = xmldefs.domain(domain_spec(name=name, labels=labels, memory_mb=memory_mb, vcpus=vcpus))
        self._name, self._uuid = name, uuid
        self.memory_kib, self.vcpus, self.active = memory_mb * 1024, vcpus, active

    def name(self):
        return self._name

    def info(self):  # virDomainInfo: state, max memory (KiB), memory (KiB), vCPUs, CPU time
        return [self.state(0)[0], self.memory_kib, self.memory_kib if self.active else 0, self.vcpus, 0]

    def state(self, flags):  # running or shut off, and a reason
        return [1 if self.active else 5, 1]

    def isActive(self):
        return self.active

    def memoryStats(self):  # KiB; rss: the QEMU process's resident set
        return {"actual": self.memory_kib, "rss": self.memory_kib // 4}

    def UUIDString(self):
        return self._uuid

    def XMLDesc(self, flags):
        return self._xml


class _Net(_Vol):
    def XMLDesc(self, flags):
        return xmldefs.nat_network(self._name, "virbr9", ipaddress.IPv4Network("192.168.150.0/24"))


class _LibvirtError(Exception):
    def __init__(self, code):
        super().__init__(f"error {code}")
        self.code = code

    def get_error_code(self):
        return self.code

    def get_error_message(self):
        return str(self)


# The constants of the binding the provider reads (their values are libvirt's).
_SDK = type("sdk", (), {"libvirtError": _LibvirtError, "VIR_CONNECT_LIST_DOMAINS_ACTIVE": 1,
                        "VIR_ERR_NO_STORAGE_POOL": 49, "VIR_ERR_NO_STORAGE_VOL": 50, "VIR_ERR_NO_NETWORK": 43, "VIR_ERR_RPC": 7,
                        "VIR_DOMAIN_RUNNING": 1, "VIR_DOMAIN_DESTROY_GRACEFUL": 1,
                        "VIR_ERR_NO_DOMAIN": 42})


class _Conn:
    def __init__(self, doms, pool, nets, memory_mb=16384, cpus=2):
        self.doms, self.pool, self.nets = doms, pool, nets
        self.memory_mb, self.cpus = memory_mb, cpus

    def getInfo(self):  # virNodeInfo: model, memory (MiB), CPUs, MHz, NUMA nodes, sockets, cores, threads
        return ["x86_64", self.memory_mb, self.cpus, 2445, 1, 1, self.cpus, 1]

    def listAllDomains(self, flags):
        return [d for d in self.doms if d.active] if flags & _SDK.VIR_CONNECT_LIST_DOMAINS_ACTIVE else self.doms

    def listAllNetworks(self, flags):
        return self.nets

    def networkLookupByName(self, name):
        found = [n for n in self.nets if n.name() == name]
        if not found:
            raise _LibvirtError(_SDK.VIR_ERR_NO_NETWORK)
        return found[0]

    def storagePoolLookupByName(self, name):
        if self.pool is None:
            raise _LibvirtError(_SDK.VIR_ERR_NO_STORAGE_POOL)
        return self.pool


def stand_in(tmp_path, volumes, domains, networks, settings=None, **host):
    inv = inventory(tmp_path, **(settings or {}))
    c = object.__new__(client.LibvirtClient)
    c.inv, c.fleet, c.workdir, c.settings = inv, inv.fleet, tmp_path, inv.provider
    c.libvirt = _SDK
    c.conn = _Conn(domains, volumes if isinstance(volumes, _Pool) or volumes is None else _Pool(volumes),
                   [_Net(n) for n in networks], **host)
    c._docker = False  # no simulated robots: this host's Docker engine is not asked
    p = object.__new__(provider.LibvirtProvider)
    p.inv, p.fleet, p.workdir, p.settings, p.client = inv, inv.fleet, tmp_path, inv.provider, c
    return p


def test_list_owned_and_the_leak_rule(tmp_path):
    from ccrp_cli.ops.gc import find_leaks
    from ccrp_cli.models.state import FleetState

    golden = "ccrp-vmlab-golden-20261126040000"
    p = stand_in(tmp_path, volumes=[
        f"{golden}.qcow2", f"{golden}.vmlinuz", f"{golden}.initrd",  # a snapshot and its boot files
        "ccrp-vmlab-golden-20250101000000.initrd",  # a boot file whose snapshot is gone
        "ccrp-vmlab-cri-nao1.qcow2", "ccrp-vmlab-cri-nao1-seed.iso", "ccrp-vmlab-cri-nao1.console",
        "ccrp-vmlab-cri-nao2.qcow2",  # left by a robot that has no clone
        "ccrp-vmlab2-cri-nao1.qcow2", "debian.qcow2",  # another fleet's, not ccrp's
    ], domains=[
        _Dom("ccrp-vmlab-cri-nao1", owner_labels("vmlab", "clone", "nao1"), "uuid-1"),
        _Dom("ccrp-vmlab-cri-nao3", owner_labels("other", "clone", "nao3"), "uuid-3"),  # labels of another fleet
        _Dom("mine", owner_labels("vmlab", "clone", "nao1"), "uuid-4"),  # not named as ccrp names them
    ], networks=["ccrp-vmlab-public", "ccrp-vmlab-common", "ccrp-vmlab2-public", "default"])
    owned = p.list_owned()
    assert [(r.kind, r.name, r.robot) for r in owned] == [
        ("instance", "ccrp-vmlab-cri-nao1", "nao1"),
        ("volume", "ccrp-vmlab-golden-20250101000000.initrd", None),
        ("volume", "ccrp-vmlab-cri-nao1.qcow2", "nao1"), ("volume", "ccrp-vmlab-cri-nao1-seed.iso", "nao1"),
        ("volume", "ccrp-vmlab-cri-nao1.console", "nao1"), ("volume", "ccrp-vmlab-cri-nao2.qcow2", "nao2"),
        ("network", "ccrp-vmlab-public", None), ("network", "ccrp-vmlab-common", None),
        ("image", f"{golden}.qcow2", None),
    ]
    state = FleetState.model_validate({"fleet": "vmlab", "robots": {"nao1": {"index": 1, "provider_id": "uuid-1", "phase": "ready"}}})
    state.snapshot = {"image": f"{golden}.qcow2", "id": f"{golden}.qcow2"}
    leaks = find_leaks(state, owned, [])
    assert sorted(r.name for r in leaks) == ["ccrp-vmlab-cri-nao2.qcow2", "ccrp-vmlab-golden-20250101000000.initrd"]
    assert p.leftovers() == [f"{'domain' if r.kind == 'instance' else r.kind} {r.name}" for r in owned if r.kind != "image"]


class _LateListener(_Dom):
    """A guest early in its boot: the power button does nothing until press number `hears` (never
    when 0: a hung guest), whose power can be cut."""

    presses, hears, cut = 0, 3, None

    def shutdown(self):
        self.presses += 1
        self.active = self.presses != self.hears

    def destroyFlags(self, flags):
        self.cut, self.active = flags, False


def test_stop_presses_the_power_button_again_until_the_guest_listens(tmp_path, monkeypatch):
    import threading

    monkeypatch.setattr(provider, "PRESS_AGAIN", 0.01)
    dom = _LateListener("ccrp-vmlab-cri-nao1", owner_labels("vmlab", "clone", "nao1"), "uuid-1")
    p = stand_in(tmp_path, volumes=[], domains=[dom], networks=[])
    p._lock, p._emulated = threading.Lock(), {"nao1": False}
    forgot = []
    p.transport = type("SshStandIn", (), {"forget": lambda _self, robot: forgot.append(robot)})()
    assert p.stop_instance("nao1") is True
    assert dom.presses == 3 and not dom.active and forgot == ["nao1"] and dom.cut is None
    assert p.stop_instance("nao1") is False  # stopped already: no press
    assert dom.presses == 3


def test_stop_cuts_the_power_of_a_guest_that_never_listens(tmp_path, monkeypatch):
    import threading

    monkeypatch.setattr(provider, "PRESS_AGAIN", 0.01)
    monkeypatch.setattr(provider, "PRESS_FOR", 1.2)
    dom = _LateListener("ccrp-vmlab-cri-nao1", owner_labels("vmlab", "clone", "nao1"), "uuid-1")
    dom.hears = 0
    p = stand_in(tmp_path, volumes=[], domains=[dom], networks=[])
    p._lock, p._emulated = threading.Lock(), {"nao1": False}
    p.transport = type("SshStandIn", (), {"forget": lambda _self, robot: None})()
    assert p.stop_instance("nao1") is True
    assert dom.presses >= 2 and dom.cut == _SDK.VIR_DOMAIN_DESTROY_GRACEFUL and not dom.active


class _Undefined(_Dom):
    """A domain listed, then undefined before its XML is read (another robot's rollback)."""

    def XMLDesc(self, flags):
        raise _LibvirtError(_SDK.VIR_ERR_NO_DOMAIN)


def test_a_domain_gone_between_listing_and_reading_is_not_an_error(tmp_path):
    p = stand_in(tmp_path, volumes=[], networks=[], domains=[
        _Undefined("ccrp-vmlab-cri-nao2", owner_labels("vmlab", "clone", "nao2"), "uuid-2"),
        _Dom("ccrp-vmlab-cri-nao1", owner_labels("vmlab", "clone", "nao1"), "uuid-1")])
    assert [d.name() for d, _info in p.client.domains()] == ["ccrp-vmlab-cri-nao1"]


def test_ssh_is_let_in_from_the_host_on_the_nat_network(tmp_path, ccrp_home):
    """The clone's firewall admits SSH from provider.operator_cidr only: by default the libvirt host's
    address on the fleet's NAT network (ccrp's SSH comes from there)."""
    from ccrp_cli.fleet import Fleet, clone_view
    from ccrp_cli.render.network import firewall_rules

    inv = inventory(tmp_path, public_cidr="192.168.151.0/24")
    assert inv.provider.operator_cidr == ipaddress.IPv4Network("192.168.151.1/32")
    assert inventory(tmp_path, operator_cidr="203.0.113.0/24").provider.operator_cidr == ipaddress.IPv4Network("203.0.113.0/24")
    fleet = Fleet.open(tmp_path / "ccrp.yaml")
    rules, _ = firewall_rules(clone_view(fleet, fleet.store.load_state(), "nao1"))
    assert "-A INPUT -p tcp -s 203.0.113.0/24 --dport 22 -j ACCEPT" in rules


def test_public_address_is_reserved_at_the_common_offset(tmp_path):
    p = stand_in(tmp_path, [], [], [])
    p.inv = p.client.inv = inventory(tmp_path, public_cidr="192.168.151.0/24")
    p.settings = p.client.settings = p.inv.provider
    assert p.public_ip("10.90.0.10") == "192.168.151.10"  # common.cidr 10.90.0.0/24, clone k at .9 + k
    with pytest.raises(CcrpError, match="no counterpart"):
        p.public_ip("10.90.1.10")
    host = ET.fromstring(xmldefs.dhcp_host("52:54:00:00:00:01", "192.168.151.10", "cri-nao1"))
    assert host.attrib == {"mac": "52:54:00:00:00:01", "name": "cri-nao1", "ip": "192.168.151.10"}
    net = ET.fromstring(xmldefs.nat_network("n", "b", ipaddress.IPv4Network("192.168.151.0/24")))
    net.find("ip/dhcp").append(host)
    assert xmldefs.dhcp_hosts(ET.tostring(net, encoding="unicode")) == {"52:54:00:00:00:01": "192.168.151.10"}


def test_snapshot_bake_on_libvirt_refuses_in_one_line_and_names_build(ccrp, tmp_path):
    """libvirt makes its golden volume on this machine (`snapshot build`): `bake` says so before any
    connection is made."""
    inv = tmp_path / "lv.yaml"
    inv.write_text("fleet: lvtest\nprovider:\n  kind: libvirt\nros:\n  distro: noetic\nrobots:\n  - name: nao1\n")
    proc = ccrp("snapshot", "bake", "-i", str(inv))
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert "the libvirt provider cannot do snapshot bake" in proc.stderr and "ccrp snapshot build" in proc.stderr


def test_build_snapshot_builds_the_recipes_image_turns_it_into_a_golden_volume_and_removes_the_image(monkeypatch, tmp_path):
    """The recipe's image from the Docker backend's own build (same recipe, software, labels), the
    golden volume from it, uploaded; the intermediate image removed also when the upload fails."""
    from types import SimpleNamespace

    from ccrp_cli.providers.docker import images
    from ccrp_cli.providers import sdk
    from ccrp_cli.providers.libvirt import images as lv_images

    calls: list = []
    removed: list = []
    client = SimpleNamespace(ping=lambda: True, close=lambda: None,
                             images=SimpleNamespace(remove=lambda tag, force: removed.append(tag)))
    monkeypatch.setattr(sdk, "docker_module", lambda: SimpleNamespace(from_env=lambda timeout: client,
                                                                      errors=__import__("docker").errors))
    monkeypatch.setattr(images, "build_snapshot_image", lambda c, repo, fleet, distro, base, plat, agents, software, bare, labels,
                        progress: calls.append(("image", repo, fleet, base, agents, bare, labels["ccrp-software"])) or f"{repo}:1")
    golden = SimpleNamespace(qcow2=tmp_path / "g.qcow2", kernel=tmp_path / "k", initrd=tmp_path / "i", virtual_size=8)
    golden.qcow2.write_bytes(b"q")
    monkeypatch.setattr(goldens, "build", lambda c, tag, out, progress: calls.append(("golden", tag)) or golden)
    fake = SimpleNamespace(fleet="vmlab", settings=SimpleNamespace(pool="ccrp"), pool=lambda create: calls.append("pool"))
    monkeypatch.setattr(lv_images, "import_golden", lambda *a: calls.append(("import", a[4])) or "record")
    build = lv_images.build_snapshot
    assert build(fake, "ccrp/vmlab-clone", "noetic", None, ("relay",), None, "none", False, print) == "record"
    assert calls == [("image", "ccrp/vmlab-clone", "vmlab", images.DEFAULT_BASE, ("relay",), False, "none"),
                     ("golden", "ccrp/vmlab-clone:1"), "pool", ("import", 8)]
    assert removed == ["ccrp/vmlab-clone:1"]

    monkeypatch.setattr(lv_images, "import_golden", lambda *a: (_ for _ in ()).throw(CcrpError("upload failed")))
    with pytest.raises(CcrpError, match="upload failed"):
        build(fake, "ccrp/vmlab-clone", "noetic", None, ("relay",), None, "none", False, print)
    assert removed == ["ccrp/vmlab-clone:1"] * 2

# -- quotas from the host: memory, vCPUs, the pool's disk (the stand-in's numbers as libvirt gives them) ---

MIB = 1 << 20


def host(tmp_path, pool="default", settings=None, **kw):
    """A host of 2 CPUs and 16 GiB running another fleet's 2-vCPU, 2 GiB domain beside a stopped one,
    whose pool (100 GiB, 50 GiB free) holds two overlays and a golden volume."""
    doms = [_Dom("ccrp-other-cri-x", owner_labels("other", "clone", "x"), "u1"),
            _Dom("ccrp-vmlab-cri-nao1", owner_labels("vmlab", "clone", "nao1"), "u2", memory_mb=4096, vcpus=4, active=False)]
    if pool == "default":
        pool = _Pool([("ccrp-vmlab-cri-nao1.qcow2", 24 * MIB),  # a booted overlay: owes 1000 MiB more
                      ("ccrp-other-cri-x.qcow2", 3 << 30),  # past overlay_mb already: owes nothing
                      ("ccrp-vmlab-golden-20261126040000.qcow2", 1 << 30), ("ccrp-vmlab-cri-nao1-seed.iso", MIB),
                      ("debian.qcow2", 0)])
    return stand_in(tmp_path, pool, doms, ["ccrp-vmlab-public"], settings=settings, **kw)


def test_quotas_are_the_hosts_memory_vcpus_and_pool_disk(tmp_path):
    p = host(tmp_path)
    mem, cpu, disk = p.quotas(["nao2", "nao3"])
    scope = "libvirt host qemu:///system"
    assert (mem.name, mem.scope, mem.limit, mem.used, mem.per_clone) == ("memory (MiB)", scope, 16384, 2048, 2048)
    # running domains only: the stopped clone's 4 vCPUs and 4 GiB are not taken
    assert (cpu.name, cpu.limit, cpu.used, cpu.per_clone) == ("vCPUs (2 CPUs x vcpu_overcommit 4)", 8, 2, 2)
    assert disk.name == "disk (MiB) of storage pool ccrp" and (disk.limit, disk.per_clone) == (102400, 1024)
    # 50 GiB used on the file system, plus what nao1's overlay has not written yet of its 1024 MiB
    assert disk.used == 51200 + 1000 and disk.free == 50200
    assert p.client.conn.pool.refreshed >= 1  # allocations as they are now, not as libvirt last saw them
    assert [q.need(["nao2", "nao3"]) for q in (mem, cpu, disk)] == [4096, 4, 2048]


def test_quota_settings_and_a_host_without_the_pool(tmp_path):
    p = host(tmp_path, pool=None, settings={"vcpu_overcommit": 1.5, "vcpus": 1, "overlay_mb": 512, "memory_mb": 1024})
    mem, cpu = p.quotas(["nao2"])  # no pool yet: no golden volume either, nothing to hold disk against
    assert (cpu.name, cpu.limit, cpu.per_clone, mem.per_clone) == ("vCPUs (2 CPUs x vcpu_overcommit 1.5)", 3, 1, 1024)
    for bad in ({"vcpu_overcommit": 0.5}, {"vcpu_overcommit": "4"}, {"overlay_mb": 10}):
        with pytest.raises(InputError):
            inventory(tmp_path, **bad)


def test_growth_past_the_hosts_vcpus_or_disk_is_refused_in_one_line(tmp_path, ccrp_home):
    """`fleet up`'s gate (quotas.check_growth) on the stand-in host: 6 vCPUs free of 8, three new
    2-vCPU clones fit, four do not; the line names the quota, its numbers and the settings."""
    from ccrp_cli.fleet import Fleet
    from ccrp_cli.ops import quotas

    p = host(tmp_path)
    data = yaml.safe_load((tmp_path / "ccrp.yaml").read_text())
    data["robots"] = [{"name": n} for n in ("nao1", "nao2", "nao3", "nao4", "nao5")]
    (tmp_path / "ccrp.yaml").write_text(yaml.safe_dump(data))
    fleet = Fleet.open(tmp_path / "ccrp.yaml")
    said: list[str] = []
    robots = [r.name for r in fleet.inventory.robots]
    assert quotas.check_growth(fleet, p, robots[:4], said.append)  # nao1 has a clone: 3 new ones fit
    with pytest.raises(quotas.QuotaError) as err:
        quotas.check_growth(fleet, p, robots, said.append)
    line = err.value.one_line()
    assert "\n" not in line and said == []
    assert err.value.message == ("libvirt quota vCPUs (2 CPUs x vcpu_overcommit 4) in libvirt host qemu:///system: "
                                 "6 free, this needs 8")
    assert "raise provider.vcpu_overcommit" in err.value.hint and "at most 3 of the 4 new clones" in err.value.hint
    # the pool's disk short too: both named, the smaller fit given
    p.client.conn.pool.available = 2 * 1024 * MIB
    with pytest.raises(quotas.QuotaError) as err:
        quotas.check_growth(fleet, p, robots, said.append)
    assert "disk (MiB) of storage pool ccrp in libvirt host qemu:///system: 1048 free, this needs 4096" in err.value.message
    assert "at most 1 of the 4 new clones" in err.value.hint and "lower provider.overlay_mb" in err.value.hint


def test_doctor_shows_the_hosts_quotas(tmp_path, ccrp_home):
    from ccrp_cli.fleet import Fleet
    from ccrp_cli.ops import doctor

    p = host(tmp_path, memory_mb=3072)  # 1 GiB free after the running domain: nao1's 2 GiB clone does not fit
    p.client.conn.doms.pop(1)  # nao1 has no clone yet
    checks = {c.check: c for c in doctor._quotas(Fleet.open(tmp_path / "ccrp.yaml"), p)}
    mem = checks["quota memory (MiB) in libvirt host qemu:///system"]
    assert mem.status == doctor.FAIL and "limit 3072, used 2048; the fleet's 1 clone(s) not created yet need 2048" in mem.detail
    assert checks["quota vCPUs (2 CPUs x vcpu_overcommit 4) in libvirt host qemu:///system"].status == doctor.OK
    assert checks["quota disk (MiB) of storage pool ccrp in libvirt host qemu:///system"].status == doctor.OK


def test_doctor_runs_on_a_libvirt_fleet(tmp_path, ccrp_home, monkeypatch):
    """`ccrp doctor` on libvirt: the connection, the accelerator and the host's quotas; the Docker
    backend's snapshot-image census is not asked of a provider without an engine client (it failed
    with AttributeError before)."""
    from ccrp_cli import providers
    from ccrp_cli.fleet import Fleet
    from ccrp_cli.ops import doctor

    p = host(tmp_path)
    p.client.conn.getLibVersion = lambda: 9_000_000
    p.client.conn.getHostname = lambda: "lab1"
    monkeypatch.setattr(providers, "get_provider", lambda inv, *a: p)
    # the fake connection stands in for the SDK, which CI's setup does not install (libvirt-dev)
    monkeypatch.setattr(doctor, "_installed", lambda module: True)
    checks = {c.check: c for c in doctor.run(Fleet.open(tmp_path / "ccrp.yaml"))}
    assert checks["credentials"].detail.startswith("libvirt 9.0.0 on lab1 (qemu:///system), accel auto")
    assert {n for n in checks if n.startswith("quota ")} == {
        f"quota {q} in libvirt host qemu:///system" for q in
        ("memory (MiB)", "vCPUs (2 CPUs x vcpu_overcommit 4)", "disk (MiB) of storage pool ccrp")}
    assert "snapshot images" not in checks


def test_a_host_without_room_refuses_before_the_golden_volume_is_built(tmp_path, ccrp_home, monkeypatch):
    """`fleet up`, `clone create` and `fleet scale` of a fleet with no snapshot build one first
    (snapshots.ensure_snapshot: minutes, a GB of pool): the quotas are checked before that build,
    for the clones the command would create (measured: `fleet up` built the golden volume, 116 s,
    and only then refused)."""
    from ccrp_cli.fleet import Fleet
    from ccrp_cli.ops import quotas, snapshots
    from ccrp_cli.ops.fleet import fleet_scale

    built: list = []
    monkeypatch.setattr(snapshots, "build", lambda *a, **k: built.append(a))
    p = host(tmp_path, settings={"vcpu_overcommit": 1.0})  # 2 CPUs: the other fleet's domain takes both
    data = yaml.safe_load((tmp_path / "ccrp.yaml").read_text())
    data["template"] = {"prefix": "sim", "max": 8}
    (tmp_path / "ccrp.yaml").write_text(yaml.safe_dump(data))
    p.client.conn.doms.pop(1)
    fleet = Fleet.open(tmp_path / "ccrp.yaml")
    for call, needs in ((lambda: snapshots.ensure_snapshot(fleet, p, print), 2),
                        (lambda: snapshots.ensure_snapshot(fleet, p, print, robots=["nao1"]), 2),
                        (lambda: fleet_scale(fleet, p, 3, print), 6)):  # nao1, sim1, sim2
        with pytest.raises(quotas.QuotaError, match=f"0 free, this needs {needs}$"):
            call()
    assert built == [] and set(fleet.store.load_state().robots) == {"nao1"}
    p.client.conn.doms.clear()  # room again: the build goes ahead
    monkeypatch.setattr(snapshots, "retain", lambda *a: None)
    monkeypatch.setattr(snapshots, "build", lambda *a, **k: built.append(a) or type("R", (), {"name": "g"}))
    snapshots.ensure_snapshot(fleet, p, print)
    assert len(built) == 1


def test_footprint_is_the_overlays_allocation_and_the_domains_rss(tmp_path):
    p = host(tmp_path)
    p.client.conn.doms[1].active = True
    assert p.footprint("nao1") == {"overlay_mb": 25.2, "rss_mib": 1024.0}  # 24 MiB written; 4 GiB domain, rss 1/4
    p.client.conn.doms[1].active = False
    assert p.footprint("nao1") == {"overlay_mb": 25.2}
    assert p.footprint("nao9") == {}


def test_gc_runs_on_a_libvirt_fleet(tmp_path, monkeypatch):
    """`ccrp gc` on libvirt lists the fleet's leaks (here: a clone no state records, an overlay of a robot with none);
    the Docker snapshot-image census is not asked of it (it failed with AttributeError before)."""
    from ccrp_cli import providers
    from tests.inprocess_cli import run_ccrp_inprocess

    p = host(tmp_path)
    p.client.conn.pool.vols.append(_Vol("ccrp-vmlab-cri-nao7.qcow2", MIB))
    monkeypatch.setattr(providers, "get_provider", lambda inv, *a: p)
    code, out, err = run_ccrp_inprocess("gc", "--dry-run", "--json", "-i", str(tmp_path / "ccrp.yaml"), home=tmp_path / "home")
    assert code == 0, err
    leaks = {(r["kind"], r["name"], r["action"]) for r in json.loads(out)}
    # no state records nao1's clone either; the golden volume is within snapshots.keep
    assert leaks == {("instance", "ccrp-vmlab-cri-nao1", "leak"), ("volume", "ccrp-vmlab-cri-nao1.qcow2", "leak"),
                     ("volume", "ccrp-vmlab-cri-nao1-seed.iso", "leak"), ("volume", "ccrp-vmlab-cri-nao7.qcow2", "leak")}


class _AgentDom(_Dom):
    """A domain whose guest agent answers from its third call, its clock `behind` seconds late; a
    time sent is applied `late` seconds after it was read, as over a busy emulated guest's agent."""

    def __init__(self, behind, late=0.0, **kw):
        super().__init__("ccrp-vmlab-cri-nao1", {}, "u1", **kw)
        self.behind, self.late, self.calls, self.set = behind, late, 0, []

    def getTime(self, flags):
        self.calls += 1
        if self.calls < 3:
            raise _LibvirtError(86)  # VIR_ERR_AGENT_UNRESPONSIVE: the agent has not started yet
        t = time.time() - self.behind
        return {"seconds": int(t), "nseconds": int(t % 1 * 1e9)}

    def setTime(self, t, flags):
        sent = t["seconds"] + t["nseconds"] / 1e9
        self.set.append(sent)
        self.behind = time.time() + self.late - sent


def test_the_host_sets_a_vm_clones_clock_through_its_guest_agent(tmp_path, monkeypatch):
    p = stand_in(tmp_path, [], [], [])
    monkeypatch.setattr(provider.time, "sleep", lambda s: None)
    dom = _AgentDom(behind=0.8, late=0.06)
    monkeypatch.setattr(p.client, "domain", lambda robot: (dom, None))
    behind = p.sync_clock("nao1", timeout=30)
    assert 0.75 < behind < 0.85
    # The first time sent was the host's; the guest took it 60 ms late, so the next one led by that.
    assert len(dom.set) == 2 and abs(dom.set[0] - time.time()) < 1.0 and abs(dom.behind) < 0.005

    # A domain defined before the agent (no port in its XML) keeps its clock: nothing is asked.
    old = _AgentDom(behind=0.8)
    old._xml = old._xml.replace("org.qemu.guest_agent.0", "org.example.other")
    monkeypatch.setattr(p.client, "domain", lambda robot: (old, None))
    assert p.sync_clock("nao1") is None and old.calls == 0

    # An agent that never answers (a golden volume without it): None once the time is up.
    mute = _AgentDom(behind=0.8)
    mute.calls = -10**9
    monkeypatch.setattr(p.client, "domain", lambda robot: (mute, None))
    assert p.sync_clock("nao1", timeout=0) is None and mute.calls == -10**9 + 1 and mute.set == []


def test_libvirts_passing_refusals_are_retried_and_its_real_answers_are_not():
    from ccrp_cli.providers.libvirt.client import transient

    cgroup = ("Unable to read from '/var/lib/docker/overlay2/45bd/merged/sys/fs/cgroup/unified/machine/"
              "qemu-84-ccrp-ct-cri-robot2.libvirt-qemu/cgroup.controllers': No such file or directory")
    tasks = ("Unable to write to '/var/lib/docker/overlay2/a0c4/merged/sys/fs/cgroup/cpu/machine/"
             "qemu-125-ccrp-ct-cri-robot5.libvirt-qemu/tasks': No such file or directory")
    assert transient(cgroup) and transient(tasks) and transient("x", rpc=True)
    assert transient("cannot refresh pool: asynchronous jobs running")
    assert not transient("Unable to read from '/dev/sda': Permission denied")
    assert not transient("Requested operation is not valid: domain is already running")

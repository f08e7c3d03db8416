"""Servers that really boot, for any cloud fake: one local container per server.

A cloud fake that keeps its API in memory (openstack_cloud.py; the GCP and AWS fakes could too)
hands each server it creates to a `CloudBoot`, which plays the hypervisor:

- The image is a "Debian 12 generic cloud image" as a local Docker image (`DEBIAN_12`), built
  once if missing from Debian packages (mmdebstrap + `docker import`: Docker Hub is not needed),
  with systemd as PID 1, cloud-init reading the NoCloud datasource, sshd, sudo and apt. Like the
  official image it holds no SSH host keys: cloud-init generates them at first boot and prints
  their fingerprints on the console. Its cloud-init default user is the image's own (`debian`).
- `boot()` writes the user-data and meta-data into the NoCloud seed (what a config drive or a
  metadata service gives a VM) and starts the container with a TTY: systemd's and cloud-init's
  console output (StandardOutput=journal+console) go to /dev/console, so `console()` (docker logs)
  is the server's serial console, host-key fingerprints block included.
- Networks are Docker bridge networks created by `ensure_network(name, cidr)` with the CIDR the
  cloud's API gave out; the first host address is the bridge's gateway (the host side), as a
  cloud reserves it for its router. A server's interfaces get exactly the addresses the API
  allocated (`attach`). The fake only ever creates and dials addresses of these networks.
- `capture()` is a snapshot of the boot disk (`docker commit`): what a process mounted inside
  (a tmpfs) is not in it, as on a cloud.

- One full install per recipe and test run: a `snapshot bake` builder installs the whole recipe
  on the stock image (Debian's ROS packages, the wheels: minutes), and a test run bakes the same
  recipe on every fake cloud. `warm_bake` does it once per run on the stock image, checks every
  install proof on its console and keeps its disk (`ccrp-fake-baked=<key>`); a later builder of the
  run whose user-data is the same (its token aside) boots from that disk instead, where the same
  user-data runs again, finds each package in place and prints every proof for real.

Everything carries the label ccrp-fake=<run>; `cleanup()` (also the context manager's exit)
removes every container, network and captured image of the run, whatever happened.
The base images carry ccrp-fake-image=<name> and are kept between runs (built once).
"""

from __future__ import annotations

import gzip
import hashlib
import io
import ipaddress
import os
import re
import secrets
import shutil
import subprocess
import tarfile
import tempfile
import threading
import time
import warnings
from pathlib import Path

import docker
import docker.errors

from tests.locks import host_lock

LABEL = "ccrp-fake"               # = run id, on everything a run creates
IMAGE_LABEL = "ccrp-fake-image"   # on the base images, kept between runs
DEBIAN_12 = "ccrp-fake/debian-12-genericcloud:2"  # 2: trusts this machine's egress CAs
DEBIAN_12_ROOTFS = "ccrp-fake/debian-12-rootfs:latest"
SEED_DIR = "var/lib/cloud/seed/nocloud"

# What the generic cloud image needs for this job: systemd as init, cloud-init (and its python3),
# sshd, sudo, apt with TLS, a locale, the ip tool. No kernel, no bootloader, no ifupdown (Docker
# configures the interfaces, so cloud-init's network rendering is switched off below).
PACKAGES = ["systemd", "systemd-sysv", "dbus", "cloud-init", "openssh-server", "sudo", "ca-certificates", "python3",
            "iproute2", "locales", "netbase", "procps", "less", "gnupg"]

# The layer over the rootfs: NoCloud only (no metadata service to probe for), no network
# configuration by cloud-init, no baked host keys, cloud-init's units and sshd enabled, consoles
# without a getty (the console is the log), en_US.UTF-8 generated once here (cloud-init's locale
# module would run locale-gen at every first boot otherwise). The CAs this machine adds for its
# egress (/usr/local/share/ca-certificates) are trusted too: the fake cloud's servers reach PyPI
# through the same network as the host, as a cloud's servers reach the internet.
DOCKERFILE = """FROM {rootfs}
ENV container=docker
COPY extra-ca/ /usr/local/share/ca-certificates/
RUN update-ca-certificates >/dev/null \
 && printf 'datasource_list: [ NoCloud, None ]\\n' > /etc/cloud/cloud.cfg.d/90-ccrp-fake-datasource.cfg \\
 && printf 'network:\\n  config: disabled\\n' > /etc/cloud/cloud.cfg.d/99-ccrp-fake-network.cfg \\
 && rm -f /etc/ssh/ssh_host_* \\
 && mkdir -p /{seed} \\
 && systemctl enable cloud-init-local.service cloud-init.service cloud-config.service cloud-final.service ssh.service \\
 && systemctl mask getty@tty1.service console-getty.service serial-getty@console.service >/dev/null 2>&1 \\
 && sed -i 's/^# *\\(en_US.UTF-8 UTF-8\\)/\\1/' /etc/locale.gen && locale-gen >/dev/null \\
 && update-locale LANG=en_US.UTF-8 \\
 && rm -rf /var/lib/apt/lists/* /var/lib/cloud/instance /var/lib/cloud/instances \\
 && : > /etc/machine-id
STOPSIGNAL SIGRTMIN+3
CMD ["/lib/systemd/systemd"]
"""


BAKED = "ccrp-fake-baked"        # = install key, on a builder's disk kept for the run's later builders
BAKED_RUN = "ccrp-fake-testrun"  # = the test run it belongs to
_OWN_RUN = secrets.token_hex(8)


def test_run() -> str:
    """One id for the whole test run, parallel workers included (tests/conftest.py sets it)."""
    return os.environ.get("PYTEST_XDIST_TESTRUNUID") or _OWN_RUN
BAKE_TOKEN = re.compile(rb"ccrp-bake ([0-9a-f]{16}) finished")


def install_key(user_data: bytes) -> str | None:
    """A builder's user-data (it ends in `ccrp-bake <token> finished`) without its token, hashed;
    None for any other user-data."""
    if user_data[:2] == b"\x1f\x8b":
        user_data = gzip.decompress(user_data)
    found = BAKE_TOKEN.search(user_data)
    if not found:
        return None
    # Its login user aside too: a bake with software: gives that user the fleet's key and sudo (to
    # build over SSH after cloud-init), which changes nothing cloud-init installs, and cloud-init
    # applies them to the kept disk's existing user.
    import json

    import yaml

    data = yaml.safe_load(user_data.replace(found.group(1), b""))
    data.pop("users", None)
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()[:16]


def baked_disk(client, key: str) -> str | None:
    """The run's kept builder disk for this install key, if `warm_bake` made it. Matched on its own
    run label too: a snapshot captured from a server booted from the disk inherits its other
    labels, and a later builder started from that snapshot made one cloud's images children of
    another's (their cleanups then met Docker's 409)."""
    found = client.images.list(filters={"label": [f"{BAKED}={key}", f"{BAKED_RUN}={test_run()}",
                                                  f"{LABEL}=testrun-{test_run()}"]})
    return found[0].id if found else None


def warm_bake(user_data: bytes, timeout: float = 1800, client=None, progress=print) -> str:
    """The run's one full install of the builder user-data's recipe on the stock image, its disk kept
    (labelled with its install key and the test run); returns that image. Parallel workers wait on a
    lock file and take the first one's. Fails with the console's tail when an install proof is missing."""
    client = client or docker.from_env(timeout=300)
    key = install_key(user_data)
    token = BAKE_TOKEN.search(user_data).group(1).decode()
    with host_lock(f"bake-{key}"):
        disk = baked_disk(client, key)
        if disk:
            return disk
        for old in client.images.list(filters={"label": f"{BAKED}={key}"}):  # an earlier run's
            try:
                client.images.remove(old.id, force=True)
            except docker.errors.APIError:  # 409: a killed run left a snapshot made from it; never ours
                pass
        with CloudBoot(client=client, progress=progress) as boot:
            net, cidr = boot.claim_network("bake", "172.24.0.0/16")
            ip = str(list(ipaddress.IPv4Network(cidr).hosts())[1])
            progress(f"cloudboot: the run's full install of the recipe ({key}) on {DEBIAN_12}")
            boot.boot("warm-bake", "ccrp-builder", DEBIAN_12, user_data, [(net, ip)])
            deadline = time.monotonic() + timeout
            while b"ccrp-bake %s finished" % token.encode() not in boot.console("warm-bake").encode():
                if time.monotonic() > deadline or boot.state("warm-bake") != "running":
                    raise RuntimeError(f"warm bake: no final message within {timeout:.0f} s: "
                                       f"{boot.console('warm-bake')[-1500:]}")
                time.sleep(5)
            console = boot.console("warm-bake")
            proofs = re.findall(rb"ccrp-bake \$0 ([a-z]+)-ok", user_data)  # the token is the script's $0
            missing = [p.decode() for p in proofs if f"ccrp-bake {token} {p.decode()}-ok" not in console]
            if missing or not proofs:
                raise RuntimeError(f"warm bake: proofs {missing or 'none'} missing: {console[-1500:]}")
            container = boot._container("warm-bake")
            container.stop(timeout=30)
            # A commit takes the container's labels: its run's label is replaced, or the cleanup
            # of this CloudBoot would remove the disk with the rest of the run.
            image = container.commit(repository="ccrp-fake/baked", tag=key, conf={"Labels": {
                LABEL: f"testrun-{test_run()}", BAKED: key, BAKED_RUN: test_run()}})
            return image.id


def remove_baked(client) -> None:
    """Remove the builder disks this test run kept (at the end of the run)."""
    for image in client.images.list(filters={"label": f"{BAKED_RUN}={test_run()}"}):
        try:
            client.images.remove(image.id, force=True)
        except docker.errors.NotFound:
            pass


def vendor_data_default_user(name: str) -> bytes:
    """Vendor-data (what a cloud's operator adds beside the user's user-data; lower priority)
    renaming the image's default user, with the official images' sudo rights: `ubuntu` makes
    "default" in user-data the login user of an Ubuntu cloud image while the image stays Debian's."""
    return (f"#cloud-config\nsystem_info:\n  default_user:\n    name: {name}\n    lock_passwd: true\n"
            f"    gecos: {name.capitalize()}\n    groups: [adm, sudo]\n    sudo: ['ALL=(ALL) NOPASSWD:ALL']\n"
            f"    shell: /bin/bash\n").encode()


def image_buildable() -> bool:
    """The Debian 12 cloud image is here, or mmdebstrap can build it."""
    if shutil.which("mmdebstrap"):
        return True
    client = docker.from_env(timeout=30)
    try:
        client.images.get(DEBIAN_12)
        return True
    except docker.errors.DockerException:
        return False
    finally:
        client.close()


def docker_available() -> str | None:
    """None when a Docker engine answers; else why not (for a skip reason)."""
    try:
        client = docker.from_env(timeout=10)
        try:
            client.ping()
        finally:
            client.close()
    except Exception as exc:  # noqa: BLE001 - any failure means "no engine here"
        return str(exc) or type(exc).__name__
    return None


# What a fake network must not shadow on this machine (Docker refuses overlaps with its own
# networks by itself, but not with the host's routes and DNS servers): the same rule `ccrp init`
# follows for a new fleet's pools.
from ccrp_cli.ops.init import host_ranges  # noqa: E402


def _tar(files: list[tuple[str, bytes, int]]) -> bytes:
    """A tar of (path, data, mode), parent directories included."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        dirs: set[str] = set()
        for path, data, mode in files:
            parts = path.strip("/").split("/")
            for i in range(1, len(parts)):
                d = "/".join(parts[:i])
                if d not in dirs:
                    dirs.add(d)
                    info = tarfile.TarInfo(d)
                    info.type, info.mode = tarfile.DIRTYPE, 0o755
                    tar.addfile(info)
            info = tarfile.TarInfo(path.strip("/"))
            info.size, info.mode, info.mtime = len(data), mode, int(time.time())
            tar.addfile(info, io.BytesIO(data))
    return buf.getvalue()


def build_debian_12(client, progress=print, force: bool = False) -> str:
    """The Debian 12 generic cloud image (DEBIAN_12), built unless present. About 1-2 minutes."""
    if not force:
        try:
            client.images.get(DEBIAN_12)
            return DEBIAN_12
        except docker.errors.ImageNotFound:
            pass
    try:
        if force:
            raise docker.errors.ImageNotFound("rebuild")
        client.images.get(DEBIAN_12_ROOTFS)
    except docker.errors.ImageNotFound:
        if shutil.which("mmdebstrap") is None:
            raise RuntimeError(f"{DEBIAN_12} is missing and mmdebstrap is not installed to build it") from None
        progress(f"cloudboot: building {DEBIAN_12_ROOTFS} with mmdebstrap (Debian bookworm, minbase)")
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp) / "rootfs.tar"
            argv = ["mmdebstrap", "--variant=minbase", f"--include={','.join(PACKAGES)}", "bookworm", str(out)]
            proc = subprocess.run(argv, capture_output=True, text=True, check=False)
            if proc.returncode != 0:
                raise RuntimeError(f"mmdebstrap failed: {proc.stderr.strip()[-800:]}")
            repo, _, tag = DEBIAN_12_ROOTFS.rpartition(":")
            with open(out, "rb") as fh:
                client.api.import_image_from_data(fh, repository=repo, tag=tag, changes=[
                    'CMD ["/lib/systemd/systemd"]', f"LABEL {IMAGE_LABEL}=debian-12-rootfs"])
    progress(f"cloudboot: building {DEBIAN_12}")
    extra_ca = [(f"extra-ca/{p.name}", p.read_bytes(), 0o644) for p in sorted(Path("/usr/local/share/ca-certificates").glob("*.crt"))]
    context = _tar([("Dockerfile", DOCKERFILE.format(rootfs=DEBIAN_12_ROOTFS, seed=SEED_DIR).encode(), 0o644),
                    ("extra-ca/.keep", b"", 0o644), *extra_ca])
    for chunk in client.api.build(fileobj=io.BytesIO(context), custom_context=True, tag=DEBIAN_12, rm=True,
                                  forcerm=True, decode=True, labels={IMAGE_LABEL: "debian-12-genericcloud"}):
        if "error" in chunk:
            raise RuntimeError(f"building {DEBIAN_12}: {chunk['error'].strip()}")
    return DEBIAN_12


class CloudBoot:
    """Containers as servers, Docker networks as the cloud's networks, commits as snapshots.

    Thread-safe: a cloud fake boots servers from background threads."""

    def __init__(self, run_id: str | None = None, client=None, progress=print) -> None:
        self.run = run_id or secrets.token_hex(4)
        self.client = client or docker.from_env(timeout=300)
        self.progress = progress
        self.labels = {LABEL: self.run}
        self.lock = threading.RLock()
        self.containers: dict[str, object] = {}    # server id -> container
        self.networks: dict[str, object] = {}      # docker network name -> network
        self.attached: dict[str, dict[str, str]] = {}  # server id -> {docker network name: ip}
        self.images: set[str] = set()               # image refs captured by this run
        self._base_lock = threading.Lock()
        self.closed = False  # set by cleanup(): what a late thread creates is removed at once

    # -- images ---------------------------------------------------------------------------------
    def base_image(self) -> str:
        """DEBIAN_12, built once if missing (one build even when servers boot concurrently)."""
        try:
            self.client.images.get(DEBIAN_12)
            return DEBIAN_12  # the usual case: no lock taken at every boot
        except docker.errors.ImageNotFound:
            pass
        with self._base_lock, host_lock("fake-debian-12"):  # threads here, other workers of the run
            return build_debian_12(self.client, self.progress)

    # -- networks -------------------------------------------------------------------------------
    def network_name(self, name: str) -> str:
        return f"{LABEL}-{self.run}-{name}"[:60]

    def ensure_network(self, name: str, cidr: str, gateway: str | None = None) -> str:
        """A bridge network for `cidr` (gateway: its first host unless given), created once;
        returns its Docker name. Refused (docker's own error) when the range overlaps another
        Docker network on this machine."""
        net_name = self.network_name(name)
        with self.lock:
            if net_name in self.networks:
                return net_name
            self._check_open()
            subnet = ipaddress.IPv4Network(cidr)
            ours = {f"br-{n.id[:12]}" for n in self.networks.values()}  # Docker's names of its bridges
            for other, what in host_ranges().items():
                if subnet.overlaps(ipaddress.IPv4Network(other)) and what.removeprefix("route via ") not in ours:
                    raise RuntimeError(f"network {name}: {cidr} overlaps {other} ({what}) of this machine; "
                                       f"pick another range")
            gw = gateway or str(next(subnet.hosts()))
            ipam = docker.types.IPAMConfig(pool_configs=[docker.types.IPAMPool(subnet=str(subnet), gateway=gw)])
            self.networks[net_name] = self.client.networks.create(
                net_name, driver="bridge", ipam=ipam, labels={**self.labels, f"{LABEL}-cidr": str(subnet)},
                check_duplicate=True)
            return net_name

    def claim_network(self, name: str, within: str, prefix: int = 24) -> tuple[str, str]:
        """A network on the first /prefix of `within` that no Docker network uses yet (created
        here, so another run picks another): (docker name, cidr)."""
        taken = [ipaddress.IPv4Network(c["Subnet"]) for n in self.client.networks.list()
                 for c in ((self.client.api.inspect_network(n.id).get("IPAM") or {}).get("Config") or [])
                 if "Subnet" in c and ":" not in c["Subnet"]]
        taken += [ipaddress.IPv4Network(r) for r in host_ranges()]
        for candidate in ipaddress.IPv4Network(within).subnets(new_prefix=prefix):
            if any(candidate.overlaps(t) for t in taken):
                continue
            try:
                return self.ensure_network(name, str(candidate)), str(candidate)
            except docker.errors.APIError as exc:
                if "overlap" not in str(exc):
                    raise
        raise RuntimeError(f"no free /{prefix} left in {within} for network {name}")

    def remove_network(self, name: str) -> None:
        net_name = self.network_name(name)
        with self.lock:
            net = self.networks.pop(net_name, None)
        if net is not None:
            try:
                net.remove()
            except docker.errors.NotFound:
                pass

    # -- servers --------------------------------------------------------------------------------
    def boot(self, server_id: str, name: str, image: str, user_data: bytes,
             networks: list[tuple[str, str]], public_keys: list[str] = (), vendor_data: bytes | None = None) -> None:
        """Create and start the server's container: the NoCloud seed (user-data; meta-data with
        instance-id = server id, local-hostname = name, the key pair's public keys; vendor-data
        if given), then one interface per (docker network name, ip), the first one at create time."""
        if image == DEBIAN_12:
            self.base_image()
            key = install_key(user_data)
            image = (baked_disk(self.client, key) if key else None) or image  # the run's installed recipe
        hostname = "".join(c if c.isalnum() or c == "-" else "-" for c in name)[:63].strip("-") or "server"
        endpoints = {net: self.client.api.create_endpoint_config(ipv4_address=ip) for net, ip in networks[:1]}
        host_config = self.client.api.create_host_config(
            # systemd as PID 1, as ccrp's Docker backend runs its clones: cgroups, /run on tmpfs,
            # SYS_ADMIN (mounts: cloud-init's bootcmd tmpfs), TUN for OpenVPN.
            cap_add=["NET_ADMIN", "SYS_ADMIN"], devices=["/dev/net/tun:/dev/net/tun:rwm"],
            tmpfs={"/run": "", "/run/lock": "", "/tmp": ""},
            binds={"/sys/fs/cgroup": {"bind": "/sys/fs/cgroup", "mode": "ro"}},
            security_opt=["seccomp=unconfined", "apparmor=unconfined"],
            network_mode=networks[0][0] if networks else "none")
        created = self.client.api.create_container(
            image, name=f"{LABEL}-{self.run}-{hostname}-{server_id[:8]}"[:100], hostname=hostname, labels=self.labels,
            detach=True, tty=True, stop_signal="SIGRTMIN+3", host_config=host_config,
            networking_config=self.client.api.create_networking_config(endpoints) if endpoints else None)
        container = self.client.containers.get(created["Id"])
        with self.lock:
            if self.closed:  # cleaned up while this was being created
                container.remove(force=True, v=True)
                self._check_open()
            self.containers[server_id] = container
            self.attached[server_id] = dict(networks[:1])
        for net, ip in networks[1:]:
            self.attach(server_id, net, ip)
        meta = f"instance-id: {server_id}\nlocal-hostname: {hostname}\n"
        if public_keys:
            meta += "public-keys:\n" + "".join(f"  - {k.strip()}\n" for k in public_keys)
        seed = [(f"{SEED_DIR}/meta-data", meta.encode(), 0o600), (f"{SEED_DIR}/user-data", user_data, 0o600),
                (f"{SEED_DIR}/vendor-data", vendor_data or b"", 0o600)]  # empty: none (a snapshot's is replaced)
        container.put_archive("/", _tar(seed))
        container.start()

    def _check_open(self) -> None:
        if self.closed:
            raise RuntimeError(f"cloudboot run {self.run} was cleaned up")

    def _container(self, server_id: str):
        with self.lock:
            if server_id not in self.containers:
                raise KeyError(f"no container for server {server_id}")
            return self.containers[server_id]

    def has(self, server_id: str) -> bool:
        with self.lock:
            return server_id in self.containers

    def attach(self, server_id: str, network: str, ip: str) -> None:
        """Another interface with address `ip` on a docker network (a created or running container)."""
        container = self._container(server_id)
        with self.lock:
            if self.attached[server_id].get(network) == ip:
                return
            if network in self.attached[server_id]:
                self.detach(server_id, network)
            self.networks[network].connect(container, ipv4_address=ip)
            self.attached[server_id][network] = ip

    def detach(self, server_id: str, network: str) -> None:
        container = self._container(server_id)
        with self.lock:
            if self.attached[server_id].pop(network, None) is not None:
                try:
                    self.networks[network].disconnect(container, force=True)
                except docker.errors.NotFound:
                    pass

    def attachments(self, server_id: str) -> dict[str, str]:
        with self.lock:
            return dict(self.attached.get(server_id, {}))

    def state(self, server_id: str) -> str:
        """Docker's word for the container: created, running, exited..."""
        container = self._container(server_id)
        container.reload()
        return container.status

    def console(self, server_id: str) -> str:
        """Everything the server printed on its console since it was created (all its boots)."""
        return self._container(server_id).logs().decode(errors="replace")

    def stop(self, server_id: str, timeout: int = 20) -> None:
        self._container(server_id).stop(timeout=timeout)  # SIGRTMIN+3: systemd shuts down

    def start(self, server_id: str) -> None:
        self._container(server_id).start()

    def delete(self, server_id: str) -> None:
        with self.lock:
            container = self.containers.pop(server_id, None)
            self.attached.pop(server_id, None)
        if container is not None:
            try:
                container.remove(force=True, v=True)
            except docker.errors.NotFound:
                pass

    def capture(self, server_id: str, image_name: str) -> str:
        """A snapshot of the server's disk as an image (`docker commit`); returns its reference.
        Mounts made inside the server (tmpfs) are not part of it, nor is the NoCloud seed's
        meaning: the next boot from it gets a seed of its own."""
        container = self._container(server_id)
        repo = f"{LABEL}/{self.run}-{''.join(c if c.isalnum() or c in '-_.' else '-' for c in image_name.lower())}"[:120]
        tag = secrets.token_hex(4)
        # Its run's label, and not the kept disk's marks it would inherit (baked_disk).
        container.commit(repository=repo, tag=tag, conf={"Labels": {**self.labels, BAKED: "", BAKED_RUN: ""}})
        ref = f"{repo}:{tag}"
        with self.lock:
            if self.closed:
                self.client.images.remove(ref, force=True)
                self._check_open()
            self.images.add(ref)
        return ref

    def remove_image(self, ref: str) -> None:
        with self.lock:
            self.images.discard(ref)
        try:
            self.client.images.remove(ref, force=True)
        except docker.errors.NotFound:
            pass

    # -- cleanup --------------------------------------------------------------------------------
    def leftovers(self) -> list[str]:
        """What of this run still exists on the engine (containers, networks, images)."""
        f = {"label": f"{LABEL}={self.run}"}
        return ([f"container {c.name}" for c in self.client.containers.list(ignore_removed=True, all=True, filters=f)]
                + [f"network {n.name}" for n in self.client.networks.list(filters=f)]
                + [f"image {i.id[:19]}" for i in self.client.images.list(filters=f)])

    def cleanup(self) -> None:
        """Remove every container, network and image labelled with this run, even ones this
        object lost track of (a crash between create and bookkeeping)."""
        with self.lock:
            self.closed = True
        f = {"label": f"{LABEL}={self.run}"}
        for c in self.client.containers.list(ignore_removed=True, all=True, filters=f):
            try:
                c.remove(force=True, v=True)
            except docker.errors.NotFound:
                pass
        for n in self.client.networks.list(filters=f):
            try:
                n.remove()
            except docker.errors.NotFound:
                pass
        # Newest first: an image committed from a server booted from one of this run's images is
        # that image's child, and Docker refuses to remove a parent before its children (409
        # "image has dependent child images"), whatever order it lists them in.
        for i in sorted(self.client.images.list(filters=f), key=lambda i: i.attrs.get("Created", ""), reverse=True):
            self._remove_image_tree(i.id)
        with self.lock:
            self.containers.clear()
            self.networks.clear()
            self.attached.clear()
            self.images.clear()

    def _remove_image_tree(self, image_id: str) -> None:
        """Remove one of this run's images and, first, its children of this run; a child of
        another owner keeps it, which is said (naming the children) rather than failing the
        teardown of a test that passed."""
        try:
            self.client.images.remove(image_id, force=True)
        except docker.errors.NotFound:
            pass
        except docker.errors.APIError as exc:
            if exc.status_code != 409:
                raise
            children = [c for c in self.client.images.list(all=True) if c.attrs.get("Parent") == image_id]
            warnings.warn(f"cloudboot run {self.run}: image {image_id[:19]} kept, it has child images "
                          f"{[(c.id[:19], c.labels.get(LABEL)) for c in children]}", stacklevel=1)

    def __enter__(self) -> CloudBoot:
        return self

    def __exit__(self, *exc) -> None:
        self.cleanup()


def main(argv: list[str] | None = None) -> int:
    """python -m tests.fakes.cloudboot [--list | --cleanup RUN...]: what runs left behind."""
    import argparse
    from collections import Counter

    parser = argparse.ArgumentParser(prog="python -m tests.fakes.cloudboot")
    parser.add_argument("--cleanup", nargs="+", metavar="RUN", help="remove everything of these runs")
    args = parser.parse_args(argv)
    client = docker.from_env(timeout=120)
    if args.cleanup:
        for run in args.cleanup:
            boot = CloudBoot(run, client)
            boot.cleanup()
            print(f"run {run}: left {boot.leftovers() or 'nothing'}")
        return 0
    runs: Counter = Counter()
    for kind in (client.containers.list(ignore_removed=True, all=True, filters={"label": LABEL}), client.networks.list(filters={"label": LABEL}),
                 client.images.list(filters={"label": LABEL})):
        for obj in kind:
            runs[(obj.attrs.get("Config") or obj.attrs).get("Labels", {}).get(LABEL)] += 1
    for run, n in sorted(runs.items()):
        print(f"run {run}: {n} container(s)/network(s)/image(s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

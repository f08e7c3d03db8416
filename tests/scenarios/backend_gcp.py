"""The GCP backend for scenarios: `ccrp` as the user types it, against the in-memory GCE of the
contract suite whose instances really boot (tests/fakes/gce_boot.py: containers from the Debian 12
cloud image with the user-data ccrp sent, Docker networks for the subnetwork and the internet,
images as `docker commit`).

The fake's clients are autospecced mocks in this process, so `ccrp` runs here too
(scenarios/inprocess.py: the console entry point with the user's argv, stdout and stderr apart);
the GCP provider's client factory (Clients.connect, what Application Default Credentials would
feed) answers the fake's clients. Everything else is the real path: inventory file, CCRP_HOME,
the provider's retries and waits, SSH to the instances with host keys pinned from their serial
console.

The fleet is behind its entry gateway (provider.entry: gateway, GCP's default) in a project of one
reserved address and one external IP in use, fewer than its robots: the gateway holds them, the
clones none (SSH reaches them through the gateway). The Debian-12 snapshot's builder takes that
address while it bakes and gives it back.

Faults (each a context manager): "quota" refuses the next instance insert (HTTP 403 quotaExceeded,
Quota 'CPUS' exceeded), "zone"
exhausts the first zone (ZONE_RESOURCE_POOL_EXHAUSTED), "storm" answers a fifth of all calls
(operation polls included) 429 or 503.
"""

from __future__ import annotations

import contextlib
from contextlib import contextmanager
from pathlib import Path
from unittest import mock

from ccrp_cli.providers.base import LABEL_FLEET, LABEL_MANAGED

from .backend import Backend, inventory_text
from .inprocess import InProcessCcrp

COMMON_RANGE = "10.214.0.0/16"  # the fleet's subnetwork: a free /24 of it (a Docker network while the run lasts)
VPN_POOL = "10.84.0.0/16"       # inside the clones only (their tun devices)
MACHINE_TYPE = "e2-medium"
STORM = 0.2


def provider_block(project: str, region: str, zones: list[str], operator_cidr: str) -> str:
    return (f"  kind: gcp\n  project: {project}\n  region: {region}\n  zones: [{', '.join(zones)}]\n"
            f"  machine_type: {MACHINE_TYPE}\n  operator_cidr: {operator_cidr}\n")


def owned(fake, fleet: str) -> list[str]:
    """What the fake holds carrying the fleet's marks ("kind id"), snapshot images left out: labels on
    instances (the clones, the entry gateway), the ownership line on networks, subnetworks, firewall
    rules (the gateway's too), routes (the robots' VPN subnets, the clones' way out through the
    gateway) and reserved external addresses (the gateway's)."""
    with fake.lock:
        return sorted(f"{kind} {rid}" for kind, rid, marks in fake.marks()
                      if kind != "image" and marks.get(LABEL_MANAGED) == "true" and marks.get(LABEL_FLEET) == fleet)


def _delete_gateway(fake, fleet: str) -> str:
    """What an operator's `gcloud compute instances delete` of the fleet's gateway does, through the
    fake's API (its reserved address and route stay); its address, for the test to compare."""
    from tests.contract.harness_gcp import PROJECT

    with fake.lock:
        [(zone, name)] = [key for key, inst in fake.instances.items() if inst.labels.get(LABEL_FLEET) == fleet
                          and inst.labels.get("ccrp-role") == "gateway"]
        address = fake.instances[(zone, name)].network_interfaces[0].access_configs[0].nat_i_p
    fake.clients.instances.delete(project=PROJECT, zone=zone, instance=name).result(timeout=120)
    return address


@contextmanager
def open_backend(tmp_path: Path, fleet: str, echo: bool = False):
    """A Backend over a booting fake GCE project; on exit every container, Docker network and
    captured image of the run is removed, whatever happened. `echo` copies ccrp's stderr to this
    process's stderr as it comes (progress under `pytest -s`)."""
    from google.cloud import compute_v1  # noqa: F401 - the SDK first: its absence is a skip, not a leak

    from ccrp_cli.providers.gcp.client import Clients
    from tests.contract.harness_gcp import PROJECT, REGION, ZONES
    from tests.fakes.cloudboot import CloudBoot
    from tests.fakes.gce_boot import BootingProject

    boot = CloudBoot(progress=lambda m: print(m, flush=True))
    try:
        fake = BootingProject(boot)
        with fake.lock:  # fewer addresses than robots: only the gateway's fits
            fake.address_quota = fake.in_use_address_quota = 1
        common = fake.reserve_subnet(COMMON_RANGE)
        inventory = tmp_path / f"{fleet}.yaml"
        # SSH is allowed from the operator's CIDR: this host reaches the instances from its address on
        # the fake's internet (the network's gateway), so that network is the operator's.
        inventory.write_text(inventory_text(fleet, provider_block(PROJECT, REGION, ZONES[:2], fake.internet_cidr),
                                            common, VPN_POOL))
        home = tmp_path / "ccrp-home"

        def patches():
            # What ADC would give the provider: clients of the fake's project.
            return mock.patch.object(Clients, "connect", classmethod(lambda cls, *a, **k: fake.clients))

        @contextmanager
        def quota():
            fake.quota_once(1)
            try:
                yield
            finally:
                with fake.lock:
                    fake.quota_refusals = 0

        @contextmanager
        def zone():
            with fake.lock:
                fake.exhausted.add(ZONES[0])
            try:
                yield
            finally:
                with fake.lock:
                    fake.exhausted.discard(ZONES[0])

        @contextmanager
        def storm():
            with fake.lock:
                fake.throttled = STORM
            try:
                yield
            finally:
                with fake.lock:
                    fake.throttled = 0.0

        runner = InProcessCcrp({"CCRP_HOME": str(home)}, patches, echo_stderr=echo)
        backend = Backend(kind="gcp", inventory=inventory, home=home, owned=lambda: owned(fake, fleet),
                          faults={"quota": quota, "zone": zone, "storm": storm}, runner=runner,
                          sim_network=fake.internet_net,  # simulated robots dial public IPs from there
                          labels=[f"ccrp-fake={boot.run}"], gateway=lambda: _delete_gateway(fake, fleet))
        backend.fake = fake  # type: ignore[attr-defined] - for tests that look inside
        try:
            yield backend
        finally:
            with contextlib.suppress(Exception):
                fake.wait_idle(60)
    finally:
        boot.cleanup()

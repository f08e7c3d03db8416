"""The fleet's entry gateway (provider.entry: gateway), made or mended by `fleet up` before the clones:
render/gateway.py says what it is, the provider makes the instance (Gateways, like a clone with the
role "gateway"), this module keeps it in line with the fleet.

The gateway is cattle: what it runs comes from the inventory and the address plan, so a missing or
broken one is made again from them. Its public address is the provider's to keep across that (it is
reserved apart from the instance), and the state records it for the robots' bundles."""

from __future__ import annotations

import ipaddress
from typing import TYPE_CHECKING, Callable

from ..errors import CcrpError
from ..fleet import Fleet, snapshot_image
from ..models.addressing import entry_port, gateway_ip
from ..models.state import FleetState, GatewayRecord
from ..probe import files_current
from ..providers.base import GATEWAY, GATEWAY_ROLE, CloneSpec, Origin
from ..render import gateway as render
from ..render.files import BundleFile

if TYPE_CHECKING:
    from ..providers.base import CloneRecord, Provider

Progress = Callable[[str], None]


def in_use(fleet: Fleet) -> bool:
    return fleet.inventory.provider.entry == "gateway"


def endpoint(fleet: Fleet, state: FleetState, robot: str) -> str | None:
    """HOST:PORT the robot dials: the gateway's address at the robot's port; None before the gateway exists."""
    if state.gateway is None or robot not in state.robots:
        return None
    return f"{state.gateway.public_ip}:{entry_port(fleet.inventory, state.robots[robot].index)}"


def _operator(fleet: Fleet) -> str:
    network = fleet.inventory.provider.operator_network()
    if network is None:  # settings.py of every backend with Ability.ENTRY_GATEWAY requires one
        raise CcrpError(f"the {fleet.inventory.provider.kind} settings name no operator_cidr for the gateway's SSH")
    return str(network)


def ensure(fleet: Fleet, provider: Provider, state: FleetState, progress: Progress) -> CloneRecord:
    """Make the gateway, start it, or reuse it; wait until it serves; give it the current robots'
    ports (a robot added or removed since changes its rules, loaded in place: no tunnel drops).
    Records its address in `state` (the caller holds the fleet lock and saves it)."""
    inv, operator = fleet.inventory, _operator(fleet)
    entries = render.entries(inv, fleet.plan(state).values())
    rules = BundleFile("gateway.rules", render.rules(inv, entries, operator), 0o600, render.RULES_PATH)
    spec = CloneSpec(
        robot=GATEWAY, hostname=f"ccrp-{fleet.name}-gateway", image=snapshot_image(state),
        user_data=render.user_data(inv, entries, operator, provider.login_keys() or []),
        instance_id=f"{fleet.name}-gateway", common_ip=str(gateway_ip(inv)), role=GATEWAY_ROLE,
    )
    record = provider.run_instance(spec)
    if record.origin is not Origin.REUSED:
        progress(f"entry gateway {record.provider_id}: {record.origin.value if record.origin else 'found'}, booting")
    provider.wait_ready(GATEWAY, timeout=300)
    if not files_current(provider, GATEWAY, [rules]):
        provider.transport.push_files(GATEWAY, [rules], restart=[])
        rc, out = provider.transport.exec(GATEWAY, ["systemctl", "reload-or-restart", render.UNIT], timeout=60)
        if rc != 0:
            raise CcrpError(f"the entry gateway did not load its rules: {' '.join(out.split())[-300:]}",
                            hint="run `ccrp fleet up` again; a gateway that stays broken can be deleted in the "
                                 "cloud: the next `fleet up` makes it again with the same address")
        progress(f"entry gateway {record.public_ip}: {len(entries)} robots' ports forwarded")
    if not record.public_ip:
        raise CcrpError(f"the entry gateway {record.provider_id} has no public address")
    # Made now: from this spec's image; found: from the one recorded when it was made, if it is the same.
    before = state.gateway if state.gateway and state.gateway.provider_id == record.provider_id else None
    image = spec.image if record.origin is Origin.CREATED else before.image if before else None
    state.gateway = GatewayRecord(provider_id=record.provider_id, public_ip=ipaddress.IPv4Address(record.public_ip),
                                  image=image)
    return record


def retire(fleet: Fleet, provider: Provider, state: FleetState, progress: Progress) -> None:
    """The fleet went back to provider.entry: per-clone: its gateway and the address it held go
    (each clone gets its own, and its robot a new bundle)."""
    if state.gateway is None:
        return
    progress(f"entry gateway {state.gateway.public_ip}: no longer used (provider.entry: per-clone), deleting it")
    provider.terminate(GATEWAY)
    state.gateway = None

"""The libvirt backend: a clone is a VM (KVM where it really works, QEMU's TCG where it does not)
booted from a qcow2 overlay of the fleet's golden volume, with a NoCloud seed carrying the same
user-data the clouds get; the SDK (libvirt-python) is imported when the provider is made."""

from ..base import Ability, InitSection, ProviderInfo
from .settings import LibvirtSettings

INFO = ProviderInfo(
    kind="libvirt",
    settings=LibvirtSettings,
    factory=".libvirt.provider:LibvirtProvider",
    # `snapshot build` makes the golden volume on this machine (LibvirtProvider.build_snapshot: the
    # recipe's image on the local Docker engine, then a qcow2 of it); there is no builder VM to bake.
    # `robot sim` puts its containers on the fleet's NAT bridge (LibvirtProvider.attach_robot).
    abilities=frozenset({Ability.LOCAL_BUILD, Ability.ROBOT_ATTACH}),
    user_data_limit=262_144,  # the NoCloud seed is ours: kept at GCE's size, as Docker's
    user_data_gzip=False,
    snapshots_running=False,
    sdk_modules=(("libvirt", "libvirt"), ("paramiko", "libvirt")),
    init=InitSection(
        lines="  kind: libvirt                 # clones are VMs on this host's libvirt (docs/libvirt.md)\n"
              "  uri: qemu:///system           # or qemu+ssh://user@host/system\n"
              "  accel: auto                   # kvm when a probe VM boots with it, else tcg (emulated, several times slower)\n"
              "  memory_mb: 2048               # per clone; `ccrp doctor` shows the host's room (memory, vCPUs, disk)\n"
              "  vcpus: 2\n"
              "  public_cidr: {public}     # the fleet's NAT network: the host is .1, clones at their common offset\n"
              "  # vpn_forward:                 # robots on the LAN reach their clones' VPN port through this host\n"
              "  #   address: 192.168.1.20     # the host's address there; each clone at base_port + its slot\n"
              "  #   base_port: 11940",
        public_pool=True),
    host_networks=".libvirt.host_networks:defined",
)

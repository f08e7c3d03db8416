"""The libvirt backend: a clone is a VM (KVM where it really works, QEMU's TCG where it does not)
booted from a qcow2 overlay of the fleet's golden volume, with a NoCloud seed carrying the same
user-data the clouds get; the SDK (libvirt-python) is imported when the provider is made."""

from ..base import ProviderInfo
from .settings import LibvirtSettings

INFO = ProviderInfo(
    kind="libvirt",
    settings=LibvirtSettings,
    factory="libvirt.provider:LibvirtProvider",
    # Neither ability yet: the golden volume is made from the Docker snapshot image by
    # LibvirtProvider.import_snapshot (docs/libvirt.md); `snapshot build` does not call it so far.
    abilities=frozenset(),
    user_data_limit=262_144,  # the NoCloud seed is ours: kept at GCE's size, as Docker's
    user_data_gzip=False,
    sdk_modules=(("libvirt", "libvirt"), ("paramiko", "libvirt")),
)

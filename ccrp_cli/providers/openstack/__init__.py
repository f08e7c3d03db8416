"""OpenStack backend (openstacksdk, clouds.yaml / OS_CLOUD); the SDK is imported on construction."""

from ..base import Ability, InitSection, ProviderInfo
from .settings import OpenStackSettings

INFO = ProviderInfo(
    kind="openstack",
    settings=OpenStackSettings,
    factory=".openstack.provider:OpenStackProvider",
    abilities=frozenset({Ability.BAKE, Ability.ENTRY_GATEWAY}),
    user_data_limit=49_149,  # Nova: 65,535 bytes once base64-encoded
    user_data_gzip=True,
    sdk_modules=(("openstack", "openstack"), ("paramiko", "openstack")),
    quota_hint="ask the cloud's admin to raise it (`openstack quota show`)",
    # Debian's generic cloud image, uploaded to Glance under the name of its file.
    bake_base="debian-12-genericcloud-amd64",
    bake_base_hint="upload Debian 12's generic cloud image to Glance under that name: `openstack image create "
                   "--disk-format qcow2 --file debian-12-genericcloud-amd64.qcow2 debian-12-genericcloud-amd64` (from "
                   "https://cloud.debian.org/images/cloud/bookworm/latest/), or name another Debian 12 image in "
                   "provider.image or --base-image",
    init=InitSection(
        "  kind: openstack\n"
        "  cloud: {cloud:<22} # your entry in clouds.yaml (or set OS_CLOUD)\n"
        "  flavor: {flavor}\n"
        "  external_network: {external_network:<11} # floating IPs come from here\n"
        "  operator_cidr: {operator_cidr} # SSH to clones only from here: {operator_note}",
        discover=".openstack.discover:init_values",
        values=(("cloud", "mycloud"), ("flavor", "m1.medium"), ("external_network", "public"),
                ("operator_cidr", "203.0.113.0/24"), ("operator_note", "put your own address range"))),
)

"""Google Compute Engine backend (google-cloud-compute, Application Default Credentials).

The SDK is imported when the provider is constructed, never at `ccrp` start-up (~1.5 s)."""

from ..base import Ability, InitSection, ProviderInfo
from .settings import GcpSettings

INFO = ProviderInfo(
    kind="gcp",
    settings=GcpSettings,
    factory=".gcp.provider:GcpProvider",
    abilities=frozenset({Ability.BAKE, Ability.ENTRY_GATEWAY}),
    user_data_limit=262_144,  # GCE: 256 KiB per metadata value
    user_data_gzip=False,
    sdk_modules=(("google.cloud.compute_v1", "gcp"), ("paramiko", "gcp")),
    image_ref="name",
    quota_hint="request more in the console (IAM & Admin > Quotas)",
    bake_base="projects/debian-cloud/global/images/family/debian-12",  # Debian's public image family
    bake_base_hint="pass --base-image projects/debian-cloud/global/images/family/debian-12 or another Debian 12 image",
    init=InitSection(
        "  kind: gcp\n"
        "  project: my-robotics-project  # your project\n"
        "  region: europe-west2\n"
        "  zones: [europe-west2-a, europe-west2-b]   # a zone without capacity falls back to the next\n"
        "  machine_type: e2-medium\n"
        "  operator_cidr: 203.0.113.0/24 # SSH to clones only from here: put your own address range"),
)

"""The compute_v1 clients the provider talks through. Tests hand the provider autospecced ones
(tests/contract/harness_gcp.py) or real ones on a mocked wire (tests/unit/test_gcp_wire.py)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ...errors import CcrpError
from .errors import LOGIN_HINT


def sdk():
    """google.cloud.compute_v1, imported on first use (it costs ~1.5 s)."""
    try:
        from google.cloud import compute_v1
    except ImportError:
        raise CcrpError("the Google Cloud SDK (google-cloud-compute) is not installed",
                        hint="pip install 'ccrp[gcp]'") from None
    return compute_v1


def default_credentials():
    """Application Default Credentials (gcloud ADC file, GOOGLE_APPLICATION_CREDENTIALS, or the
    metadata server); ccrp never reads credential files itself."""
    import google.auth
    from google.auth.exceptions import DefaultCredentialsError

    try:
        credentials, _project = google.auth.default(scopes=["https://www.googleapis.com/auth/compute"])
    except DefaultCredentialsError as exc:
        first_sentence = str(exc).split(". ")[0].strip().rstrip(".")
        raise CcrpError(f"no Google Cloud credentials found ({first_sentence[:160]})", hint=LOGIN_HINT) from None
    return credentials


@dataclass
class Clients:
    instances: Any
    networks: Any
    subnetworks: Any
    firewalls: Any
    routes: Any
    addresses: Any
    images: Any
    regions: Any
    machine_types: Any

    @classmethod
    def connect(cls, credentials=None, client_options: dict | None = None) -> "Clients":
        compute_v1 = sdk()
        kw = {"credentials": credentials or default_credentials(), "client_options": client_options}
        return cls(
            instances=compute_v1.InstancesClient(**kw), networks=compute_v1.NetworksClient(**kw),
            subnetworks=compute_v1.SubnetworksClient(**kw), firewalls=compute_v1.FirewallsClient(**kw),
            routes=compute_v1.RoutesClient(**kw), addresses=compute_v1.AddressesClient(**kw), images=compute_v1.ImagesClient(**kw),
            regions=compute_v1.RegionsClient(**kw), machine_types=compute_v1.MachineTypesClient(**kw),
        )

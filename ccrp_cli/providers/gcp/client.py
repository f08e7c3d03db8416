"""The GCP backend's client: the compute_v1 clients (Clients; tests hand the provider autospecced
ones, tests/contract/harness_gcp.py, or real ones on a mocked wire, tests/unit/test_gcp_wire.py), every
SDK call through retry.call (the SDK's own retry switched off), every mutation waited for as its
ExtendedOperation, SDK failures translated into one-line CcrpErrors, and the lookups the other
modules of the backend share (the fleet's instances)."""

from __future__ import annotations

import builtins
import logging
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

from ...errors import CcrpError, translated
from ...models.inventory import Inventory
from ...retry import Backoff, ErrorClass, call
from ..base import LABEL_ROBOT
from .errors import LOGIN_HINT, as_ccrp_error, classify
from .ownership import Names, tail
from .settings import GcpSettings

log = logging.getLogger(__name__)


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


class GcpClient:
    backoff = Backoff()
    op_timeout = 600.0  # seconds to wait for one GCE operation

    def __init__(self, inv: Inventory, workdir: Path, clients: Clients | None = None) -> None:
        self.compute = sdk()
        from google.api_core import exceptions

        self.NotFound, self.Conflict = exceptions.NotFound, exceptions.Conflict
        self.inv, self.fleet, self.workdir = inv, inv.fleet, Path(workdir)
        self.settings = cast(GcpSettings, inv.provider)  # get_provider picked this backend by these settings' kind
        self.project, self.region = self.settings.project, self.settings.region
        self.names = Names(self.fleet)
        self._clients = clients
        self._lock = threading.Lock()
        self.subnet_link: str | None = None  # the common subnetwork's, once bootstrap resolved it

    @property
    def clients(self) -> Clients:
        with self._lock:  # clones are created from parallel threads
            if self._clients is None:
                self._clients = Clients.connect()
            return self._clients

    # -- calls ------------------------------------------------------------------------------
    def classify_error(self, exc: BaseException) -> ErrorClass:
        return classify(exc)

    def api(self, what: str, fn, *args, classify=None, **kwargs):
        """Every SDK call goes through here: retried on throttling / 5xx, classified otherwise."""
        return call(fn, *args, classify=classify or self.classify_error, what=what, backoff=self.backoff, **kwargs)

    def call(self, what: str, method, *args, **kwargs):
        """One SDK call through retry.call; the SDK's own retry is off so there is one policy."""
        return self.api(what, method, *args, retry=None, **kwargs)

    def list(self, what: str, method, *args, **kwargs) -> list:
        """Every item of a paged list: later pages are fetched inside the retried call too."""
        return self.api(what, lambda: list(method(*args, retry=None, **kwargs)))

    def get(self, what: str, method, **kwargs):
        try:
            return self.call(f"get {what}", method, **kwargs)
        except self.NotFound:
            return None

    def wait(self, op, what: str) -> None:
        """Until the operation is done. A failed poll (503, connection reset) polls again under
        retry.call; the operation's own error is raised as it is, for the caller to classify
        (zone fallback, rollback). Warnings (e.g. a disk larger than its image) are logged."""
        self.api(f"wait for {what}", op.result, timeout=self.op_timeout,
                 classify=lambda exc: ErrorClass.FATAL if op.error_code else classify(exc))
        if op.error_code:  # result() raises for these; kept as a guard if a future SDK does not
            raise CcrpError(f"{what}: operation {op.name} failed ({op.error_code} {op.error_message})")
        for warning in getattr(op, "warnings", None) or []:
            log.warning("%s: %s %s", what, warning.code, warning.message)

    def mutate(self, what: str, method, *args, **kwargs):
        op = self.call(what, method, *args, **kwargs)
        self.wait(op, what)
        return op

    def insert(self, what: str, method, **kwargs) -> bool:
        """Create a resource named by the caller; False when it exists already (a retried call
        that had gone through, or a parallel run)."""
        try:
            self.mutate(f"create {what}", method, **kwargs)
            return True
        except self.Conflict:
            return False

    def delete(self, what: str, method, **kwargs):
        """Start a delete; None when the resource is already gone. The caller waits."""
        try:
            return self.call(f"delete {what}", method, **kwargs)
        except self.NotFound:
            return None

    def wait_all(self, ops: builtins.list[tuple[str, object]]) -> None:  # `list` here is the method
        for what, op in ops:
            if op is not None:
                try:
                    self.wait(op, what)
                except self.NotFound:
                    pass

    def errors(self, what: str):
        """SDK failures leave the provider as one-line CcrpErrors with a hint (any exception: the
        client libraries raise many classes of their own)."""
        return translated(what, lambda w, exc: as_ccrp_error(w, exc, self.region))

    # -- the fleet's instances ---------------------------------------------------------------------
    def instances(self, role: str | None = None, robot: str | None = None) -> builtins.list[tuple[str, Any]]:  # `list` here is the method
        """(zone, instance) of every instance carrying the fleet's labels (and role / robot)."""
        request = self.compute.AggregatedListInstancesRequest(
            project=self.project, filter=self.names.label_filter(role, robot))
        found = []
        for _scope, scoped in self.list("instances", self.clients.instances.aggregated_list, request=request):
            for inst in scoped.instances:
                labels = dict(inst.labels)
                if self.names.owns_labels(labels) and (robot is None or labels.get(LABEL_ROBOT) == robot):
                    found.append((tail(inst.zone), inst))
        return found

    def find(self, robot: str, role: str | None = "clone"):
        """The robot's instance; role None finds the builder of `snapshot bake` too."""
        return next(iter(self.instances(role, robot)), None)

    def require(self, robot: str):
        found = self.find(robot, role=None)
        if found is None:
            raise CcrpError(f"robot {robot!r} has no clone in fleet {self.fleet}", hint=f"ccrp clone create --robot {robot}")
        return found

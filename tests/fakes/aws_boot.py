"""An AWS fake whose EC2 instances really boot: moto's server in this process, hooked so that an
instance is a CloudBoot container (cloudboot.py) booted with the user-data RunInstances sent.

`ccrp` runs as a separate process against it, exactly as a user types it: `AwsBoot.env()` is what
that process needs (AWS_ENDPOINT_URL, fake credentials, the region, no profile, no config files).

moto.server's ThreadedMotoServer serves every AWS service on one port of 127.0.0.1; moto's EC2
backend objects live in this process, and these methods of moto's EC2Backend are wrapped while
the fake is open (mock.patch, undone on close):

- RunInstances: the AMI must have a disk in the fake (the Debian 12 AMI, or an AMI CreateImage
  made here), else InvalidAMIID.NotFound. The instance is `pending` until its container runs,
  then `running`. The container has one interface per network interface of the instance (an
  entry gateway has two): on the Docker network of its subnet (the subnet's CIDR; its .1 is the
  host, as a VPC router's address) at its private IP; the NoCloud
  seed holds the user-data as sent (cloud-init takes gzip there too: ccrp gzips large
  user-data), instance-id = the instance id, local-hostname ip-a-b-c-d as EC2 names it, and the
  key pair's public key. A boot that fails leaves the instance `terminated` with
  Server.InternalError as its state reason (`errors` has the exception).
- Elastic IPs (AllocateAddress without an address) come from the fake's "internet": a Docker
  network it claims (a free /24 of 172.28.0.0/16 unless given; its .1 is the host). Associating
  one connects the instance's container to that network at that address; disassociating or
  releasing disconnects it. So ccrp (on the host) reaches an instance's public IP over SSH.
  Unlike EC2, the public address is on an interface of the instance (EC2 NATs it to the private IP).
  As on EC2, a region holds at most EIP_LIMIT of them: the `vpc-max-elastic-ips` moto reports (AWS's
  default) but does not enforce; one more is refused 400 AddressLimitExceeded. A test may lower the
  fake's `max_eips` (an account whose addresses others hold; moto still reports 5).
- StopInstances / StartInstances / TerminateInstances: `stopping`/`pending`/`shutting-down` while
  the container stops, starts or is removed, then `stopped`/`running`/`terminated`. An instance
  whose container exited by itself (powered off from inside) is `stopped`, as EC2 does.
- GetConsoleOutput: the container's console (docker logs: systemd and cloud-init, host-key
  fingerprints included), base64-encoded as EC2 sends it, the most recent 64 KiB as EC2 keeps.
- CreateImage: the AMI is `pending` until the container is committed (CloudBoot.capture), then
  `available`; RunInstances with it boots that image. DeregisterImage removes the Docker image.
- DeleteSubnet removes the subnet's Docker network (once nothing is attached).

Registered at start: a public "Debian 12" AMI owned by Debian's AWS account, whose disk is
cloudboot.DEBIAN_12, and the public SSM parameter /aws/service/debian/release/bookworm/latest/amd64
naming it (as AWS publishes it; moto refuses /aws/ names through the API, so it goes into moto's
SSM backend directly).

Faults, answered before a request reaches moto (a WSGI layer in front of moto's app; requests
carrying BYPASS_HEADER pass untouched, for the test's own reads): `throttle(fraction)` answers that
fraction of EC2 requests 503 RequestLimitExceeded; `refuse_robot(robot)` answers RunInstances
tagged with that robot (every RunInstances without one) 400 InstanceLimitExceeded; `no_capacity(zone)` answers RunInstances into a
subnet of that zone 500 InsufficientInstanceCapacity and CreateSubnet in that zone 400 Unsupported.
The same layer lets one request at a time into moto (its backends are not thread-safe).

Not modelled: security groups and routes (every container port is open to the host and its
networks; VPN subnets are not routed between containers by the route table; a container's way
out is Docker's, not its subnet's default route: a clone behind an entry gateway reaches the
internet without it, which on EC2 it could not), the metadata service
(the NoCloud seed stands for it), ClientToken idempotency (moto's own limit), instance types
(every container gets the host's CPUs).

Only one AwsBoot may be open in a process (moto's backends and the patches are global). Closing it
stops the server, undoes the patches, resets moto and removes every container, network and image
its CloudBoot made.
"""

from __future__ import annotations

import base64
import contextlib
import io
import ipaddress
import os
import random
import re
import socket
import sys
import tempfile
import threading
import time
import traceback
import uuid
from collections import Counter
from collections.abc import Callable
from contextlib import contextmanager
from typing import Any
from unittest import mock
from urllib.parse import parse_qs

from .cloudboot import DEBIAN_12, CloudBoot

ACCOUNT = "123456789012"          # moto's default account (what fake credentials map to)
DEBIAN_ACCOUNT = "136693071363"   # Debian's AWS account, owner of the official AMIs
DEBIAN_AMI_NAME = "debian-12-amd64-20250101-0000"
DEBIAN_SSM = "/aws/service/debian/release/bookworm/latest/amd64"
INTERNET_RANGE = "172.28.0.0/16"
BYPASS_HEADER = "X-Ccrp-Fake-Bypass"
CONSOLE_BYTES = 64 * 1024        # EC2 keeps the most recent 64 KiB of an instance's console
EIP_LIMIT = 5                    # Elastic IPs per region: AWS's default, moto's vpc-max-elastic-ips

# EC2 instance states (name, code)
PENDING, RUNNING, SHUTTING_DOWN, TERMINATED, STOPPING, STOPPED = (
    ("pending", 0), ("running", 16), ("shutting-down", 32), ("terminated", 48), ("stopping", 64), ("stopped", 80))

_active: list[AwsBoot] = []


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ec2_error(status: int, code: str, message: str) -> tuple[str, list, bytes]:
    body = (f'<?xml version="1.0" encoding="UTF-8"?>\n<Response><Errors><Error><Code>{code}</Code>'
            f"<Message>{message}</Message></Error></Errors><RequestID>{uuid.uuid4()}</RequestID></Response>")
    reason = {400: "Bad Request", 500: "Internal Server Error", 503: "Service Unavailable"}.get(status, "Error")
    return f"{status} {reason}", [("Content-Type", "text/xml"), ("Content-Length", str(len(body)))], body.encode()


def _service(environ: dict) -> str:
    """The AWS service a request is signed for (SigV4 credential scope: key/date/region/SERVICE/aws4_request)."""
    m = re.search(r"Credential=[^/]+/[^/]+/[^/]+/([^/]+)/", environ.get("HTTP_AUTHORIZATION", ""))
    return m.group(1) if m else ""


def _set_state(instance, state: tuple[str, int]) -> None:
    instance._state.name, instance._state.code = state


class AwsBoot:
    """moto's server with EC2 instances that boot as containers; see the module's docstring."""

    def __init__(self, boot: CloudBoot | None = None, region: str = "us-east-1", internet_cidr: str | None = None,
                 progress: Callable[[str], None] | None = None) -> None:
        self.region = region
        self.progress = progress or (lambda msg: print(f"aws-boot: {msg}", file=sys.stderr, flush=True))
        self.boot = boot or CloudBoot(progress=self.progress)
        self._internet_cidr_wanted = internet_cidr
        self.lock = threading.RLock()            # one request at a time in moto; the fake's bookkeeping
        self.disks: dict[str, str] = {}          # AMI id -> Docker image it boots
        self.captured: set[str] = set()          # AMI ids whose Docker image this fake committed
        self.errors: dict[str, str] = {}         # instance or AMI id -> why its boot/capture failed
        self.calls: Counter = Counter()          # "service Action" -> requests seen (faulted ones too)
        self.faulted: Counter = Counter()        # "Action Code" -> requests answered by a fault
        self._threads: dict[str, threading.Thread] = {}  # instance id -> its latest task
        self._subnet_nets: dict[str, str] = {}   # subnet id -> docker network
        self._cidr_nets: dict[str, str] = {}     # cidr -> docker network claimed up front (claim_subnet_cidr)
        self._instances: dict[str, Any] = {}     # instance id -> moto Instance, for instances with a container
        self._throttle, self._n = 0.0, 0
        self._refused_robots: dict[str, str] = {}
        self._full_zones: set[str] = set()
        self.max_eips = EIP_LIMIT                # Elastic IPs the region holds at most
        self._empty_config: str | None = None   # AWS_CONFIG_FILE of the ccrp processes (env())
        self._patches: list = []
        self._server = None
        self.url = ""
        self.debian_ami = ""

    # -- lifecycle ----------------------------------------------------------------------------------
    def start(self) -> AwsBoot:
        if _active:
            raise RuntimeError("an AwsBoot is already open in this process (moto's backends are global)")
        _active.append(self)
        try:
            self._start()
        except BaseException:
            self.close()
            raise
        return self

    def _start(self) -> None:
        from moto.moto_server.threaded_moto_server import ThreadedMotoServer

        self.boot.base_image()  # built once if missing (minutes), before any request waits on it
        if self._internet_cidr_wanted:
            self.internet_network = self.boot.ensure_network("internet", self._internet_cidr_wanted)
            self.internet_cidr = self._internet_cidr_wanted
        else:
            self.internet_network, self.internet_cidr = self.boot.claim_network("internet", INTERNET_RANGE)
        # moto's few hundred stock AMIs cost seconds of CPU per backend and are not wanted here.
        env = mock.patch.dict("os.environ", {"MOTO_EC2_LOAD_DEFAULT_AMIS": "false"})
        env.start()
        self._patches.append(env)
        self._install_hooks()
        self._reset_moto()
        fake = self

        class Server(ThreadedMotoServer):
            def _server_entry(self) -> None:  # moto's own, with the fake's WSGI layer in front
                from moto.moto_server.werkzeug_app import (
                    DomainDispatcherApplication,
                    MotoRequestHandler,
                    create_backend_app,
                )
                from werkzeug.serving import make_server

                class Quiet(MotoRequestHandler):
                    def log_request(self, *args) -> None:  # werkzeug's line per request: not wanted
                        pass

                app = DomainDispatcherApplication(create_backend_app)
                self._server = make_server(self._ip_address, self._port, fake._wsgi(app), True,
                                           request_handler=Quiet)
                self._server_ready_event.set()
                self._server.serve_forever()

        port = _free_port()
        self._server = Server("127.0.0.1", port, verbose=False)
        self._server.start()
        self.url = f"http://127.0.0.1:{port}"
        self._register_debian()
        self.progress(f"moto on {self.url}, internet {self.internet_cidr}, Debian 12 AMI {self.debian_ami}")

    def close(self) -> None:
        """Stop the server, undo the patches, reset moto, remove what CloudBoot made. Idempotent."""
        try:
            if self._server is not None:
                with contextlib.suppress(Exception):
                    self._server.stop()
                self._server = None
            for thread in list(self._threads.values()):
                thread.join(timeout=60)
            with contextlib.suppress(Exception):
                self._reset_moto()
            while self._patches:
                with contextlib.suppress(Exception):
                    self._patches.pop().stop()
            if self._empty_config is not None:
                with contextlib.suppress(OSError):
                    os.unlink(self._empty_config)
                self._empty_config = None
        finally:
            try:
                self.boot.cleanup()
            finally:
                if self in _active:
                    _active.remove(self)

    def __enter__(self) -> AwsBoot:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    @staticmethod
    def _reset_moto() -> None:
        from moto.moto_api._internal.models import moto_api_backend

        moto_api_backend.reset()

    def env(self) -> dict[str, str]:
        """The environment of a `ccrp` process using this fake (a user's shell with an endpoint set).
        No AWS_PROFILE: the inventory names no profile either. The config files are an empty file of
        the fake's own so nothing of this machine's ~/.aws leaks in (not /dev/null: on some machines it
        is a regular file that collects what processes write to it, which botocore then fails to parse)."""
        if self._empty_config is None:
            fd, self._empty_config = tempfile.mkstemp(prefix="ccrp-aws-config-")
            os.close(fd)
        return {"AWS_ENDPOINT_URL": self.url, "AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing",
                "AWS_DEFAULT_REGION": self.region, "AWS_REGION": self.region, "AWS_CONFIG_FILE": self._empty_config,
                "AWS_SHARED_CREDENTIALS_FILE": self._empty_config, "AWS_EC2_METADATA_DISABLED": "true"}

    def client(self, service: str = "ec2"):
        """A boto3 client on the fake for the test's own reads: its requests skip the faults."""
        import boto3

        client = boto3.session.Session().client(
            service, region_name=self.region, endpoint_url=self.url, aws_access_key_id="testing",
            aws_secret_access_key="testing")
        client.meta.events.register("before-sign", lambda request, **_: request.headers.__setitem__(BYPASS_HEADER, "1"))
        return client

    @property
    def ec2(self):
        """moto's EC2 backend of the fake's region."""
        from moto.ec2.models import ec2_backends

        return ec2_backends[ACCOUNT][self.region]

    # -- images -------------------------------------------------------------------------------------
    def _register_debian(self) -> None:
        """A public Debian 12 AMI (Debian's account) booting cloudboot.DEBIAN_12, and the SSM
        parameter AWS publishes for the latest one."""
        from moto.core.utils import utcnow
        from moto.ec2.models.amis import Ami
        from moto.ec2.utils import random_ami_id
        from moto.ssm.models import Parameter, ssm_backends

        with self.lock:
            backend = self.ec2
            ami = Ami(backend, random_ami_id(), name=DEBIAN_AMI_NAME, description="Debian 12 (bookworm)",
                      owner_id=DEBIAN_ACCOUNT, public=True, virtualization_type="hvm", architecture="x86_64",
                      root_device_type="ebs", root_device_name="/dev/xvda", hypervisor="xen", region_name=self.region)
            backend.amis[ami.id] = ami
            self.debian_ami = ami.id
            self.disks[ami.id] = DEBIAN_12
            ssm = ssm_backends[ACCOUNT][self.region]
            ssm._parameters[DEBIAN_SSM].append(Parameter(
                account_id=ACCOUNT, name=DEBIAN_SSM, value=ami.id, parameter_type="String", description=None,
                allowed_pattern=None, keyid=None, last_modified_date=utcnow(), version=1, data_type="aws:ec2:image"))

    # -- the WSGI layer: faults, one request at a time ------------------------------------------------
    def _wsgi(self, app):
        def serve(environ, start_response):
            length = int(environ.get("CONTENT_LENGTH") or 0)
            body = environ["wsgi.input"].read(length) if length else b""
            environ["wsgi.input"] = io.BytesIO(body)
            service = _service(environ)
            params = {k: v[0] for k, v in parse_qs(body.decode(errors="replace")).items()} if service == "ec2" else {}
            action = params.get("Action") or environ.get("HTTP_X_AMZ_TARGET", "").rpartition(".")[2] or environ.get("PATH_INFO", "")
            with self.lock:
                self.calls[f"{service} {action}"] += 1
            if service == "ec2" and not environ.get("HTTP_" + BYPASS_HEADER.upper().replace("-", "_")):
                fault = self._fault(action, params)
                if fault is not None:
                    status, headers, payload = _ec2_error(*fault)
                    with self.lock:
                        self.faulted[f"{action} {fault[1]}"] += 1
                    start_response(status, headers)
                    return [payload]
            with self.lock:  # moto's backends are not thread-safe: one request at a time
                result = app(environ, start_response)
                try:
                    return [b"".join(result)]
                finally:
                    if hasattr(result, "close"):
                        result.close()

        return serve

    def _fault(self, action: str, params: dict[str, str]) -> tuple[int, str, str] | None:
        with self.lock:
            if self._throttle:
                self._n += 1
                if int(self._n * self._throttle) > int((self._n - 1) * self._throttle):
                    return 503, "RequestLimitExceeded", "Request limit exceeded."
            if action == "RunInstances":
                tags = _tag_specs(params)
                robot = tags.get("ccrp-robot")
                code = self._refused_robots.get(robot) or self._refused_robots.get(None)
                if code:
                    return 400, code, (
                        "You have requested more instances than your current instance limit allows for the "
                        "specified instance type. Please visit http://aws.amazon.com/contact-us/ec2-request to "
                        "request an adjustment to this limit.")
                subnet = params.get("NetworkInterface.1.SubnetId") or params.get("SubnetId")
                zone = params.get("Placement.AvailabilityZone")
                if subnet and not zone:
                    with contextlib.suppress(Exception):
                        zone = self.ec2.get_subnet(subnet).availability_zone
                if zone in self._full_zones:
                    itype = params.get("InstanceType", "m1.small")
                    return 500, "InsufficientInstanceCapacity", (
                        f"We currently do not have sufficient {itype} capacity in the Availability Zone you "
                        f"requested ({zone}). Our system will be working on provisioning additional capacity.")
            if action == "CreateSubnet" and params.get("AvailabilityZone") in self._full_zones:
                zone = params["AvailabilityZone"]
                return 400, "Unsupported", (f"The requested Availability Zone ({zone}) is currently constrained "
                                            "and we are no longer accepting new customer requests.")
        return None

    @contextmanager
    def throttle(self, fraction: float = 0.3):
        """That fraction of EC2 requests (evenly spread) answered 503 RequestLimitExceeded."""
        with self.lock:
            before, self._throttle, self._n = self._throttle, fraction, 0
        try:
            yield self
        finally:
            with self.lock:
                self._throttle = before

    @contextmanager
    def refuse_robot(self, robot: str | None = None, code: str = "InstanceLimitExceeded"):
        """RunInstances tagged ccrp-robot=<robot> (any RunInstances: None) refused with an account
        quota error, as when the account is at its instance limit."""
        with self.lock:
            self._refused_robots[robot] = code
        try:
            yield self
        finally:
            with self.lock:
                self._refused_robots.pop(robot, None)

    @contextmanager
    def no_capacity(self, zone: str):
        """No instance capacity in `zone`; subnets cannot be created there either."""
        with self.lock:
            self._full_zones.add(zone)
        try:
            yield self
        finally:
            with self.lock:
                self._full_zones.discard(zone)

    # -- hooks on moto's EC2 backend ------------------------------------------------------------------
    def _install_hooks(self) -> None:
        from moto.ec2.models import EC2Backend
        from moto.ec2.models import elastic_network_interfaces as eni_models
        from moto.ec2.responses.general import General
        from moto.ec2.utils import random_private_ip

        fake = self
        orig = {name: getattr(EC2Backend, name) for name in (
            "run_instances", "start_instances", "stop_instances", "terminate_instances", "create_image",
            "deregister_image", "allocate_address", "associate_address", "disassociate_address", "delete_subnet",
            "describe_instances")}

        def run_instances(backend, image_id, count, user_data, security_group_names, **kwargs):
            from moto.ec2.exceptions import InvalidAMIIdError

            if image_id not in fake.disks:
                raise InvalidAMIIdError(image_id)
            reservation = orig["run_instances"](backend, image_id, count, user_data, security_group_names, **kwargs)
            for instance in reservation.instances:
                _set_state(instance, PENDING)
                fake._task(instance, fake._boot_instance, image_id)
            return reservation

        def describe_instances(backend, filters=None):
            # EC2 stops an instance whose OS powered off (InstanceInitiatedShutdownBehavior=stop):
            # a container that exited by itself, with no task of the fake on it, is `stopped`.
            for reservation in list(backend.reservations.values()):
                for instance in reservation.instances:
                    task = fake._threads.get(instance.id)
                    if (instance._state.name == "running" and not (task and task.is_alive())
                            and fake.boot.has(instance.id) and fake.boot.state(instance.id) != "running"):
                        _set_state(instance, STOPPED)
            return orig["describe_instances"](backend, filters)

        def start_instances(backend, instance_ids):
            done = orig["start_instances"](backend, instance_ids)
            for instance, before in done:
                if before.name != "running":
                    _set_state(instance, PENDING)
                    fake._task(instance, fake._power, True)
            return done

        def stop_instances(backend, instance_ids):
            done = orig["stop_instances"](backend, instance_ids)
            for instance, before in done:
                if before.name not in ("stopped", "terminated"):
                    _set_state(instance, STOPPING)
                    fake._task(instance, fake._power, False)
            return done

        def terminate_instances(backend, instance_ids):
            done = orig["terminate_instances"](backend, instance_ids)
            for instance, before in done:
                if before.name != "terminated":
                    _set_state(instance, SHUTTING_DOWN)
                    fake._task(instance, fake._delete)
            return done

        def create_image(backend, instance_id, name, description, tag_specifications):
            ami = orig["create_image"](backend, instance_id, name, description, tag_specifications)
            ami.state = "pending"
            fake._task(backend.get_instance(instance_id), fake._capture, ami)
            return ami

        def deregister_image(backend, ami_id):
            orig["deregister_image"](backend, ami_id)
            ref = fake.disks.pop(ami_id, None)
            if ami_id in fake.captured and ref:
                fake.captured.discard(ami_id)
                fake.boot.remove_image(ref)

        def allocate_address(backend, domain, address=None, tags=None):
            from moto.ec2.exceptions import EC2ClientError

            if len(backend.addresses) >= fake.max_eips:
                raise EC2ClientError("AddressLimitExceeded", "The maximum number of addresses has been reached.")
            return orig["allocate_address"](backend, domain, address=address or fake._free_public_ip(), tags=tags)

        def associate_address(backend, *args, **kwargs):
            eip = orig["associate_address"](backend, *args, **kwargs)
            fake._rewire()
            return eip

        def disassociate_address(backend, *args, **kwargs):
            result = orig["disassociate_address"](backend, *args, **kwargs)
            fake._rewire()
            return result

        def delete_subnet(backend, subnet_id):
            subnet = orig["delete_subnet"](backend, subnet_id)
            net = fake._subnet_nets.pop(subnet_id, None)
            if net is not None and net not in fake._cidr_nets.values():
                fake._remove_network(net)
            return subnet

        def get_console_output(response):
            from moto.core.responses import ActionResult
            from moto.core.utils import utcnow
            from moto.ec2.utils import Base64EncodedString

            instance = response.ec2_backend.get_instance(response._get_param("InstanceId"))
            result: dict = {"InstanceId": instance.id, "Timestamp": utcnow()}
            text = fake.console(instance.id)
            if text:
                result["Output"] = Base64EncodedString.from_raw_string(text)
            return ActionResult(result)

        hooks = {"run_instances": run_instances, "start_instances": start_instances, "stop_instances": stop_instances,
                 "terminate_instances": terminate_instances, "create_image": create_image,
                 "deregister_image": deregister_image, "allocate_address": allocate_address,
                 "associate_address": associate_address, "disassociate_address": disassociate_address,
                 "delete_subnet": delete_subnet, "describe_instances": describe_instances}
        def private_ip(cidr: str | None = None, ipv6: bool = False) -> str:
            """An interface's address when RunInstances names none, as EC2 gives it: never the
            subnet's first four or its last (moto draws any of the block at random, and the .1 is this
            host's, the Docker network's gateway: a container there failed "Address already in use"),
            nor one another interface holds."""
            if ipv6 or not cidr:
                return random_private_ip(cidr, ipv6)
            net = ipaddress.IPv4Network(cidr)
            taken = {e.private_ip_address for e in fake.ec2.enis.values()}
            free = [str(ip) for ip in list(net)[4:-1] if str(ip) not in taken]
            return random.choice(free) if free else random_private_ip(cidr)

        patches = [mock.patch.object(EC2Backend, name, fn) for name, fn in hooks.items()]
        patches.append(mock.patch.object(General, "get_console_output", get_console_output))
        patches.append(mock.patch.object(eni_models, "random_private_ip", private_ip))
        for patch in patches:
            patch.start()
            self._patches.append(patch)

    # -- instance work, one task at a time per instance ------------------------------------------------
    def _task(self, instance, work, *args) -> None:
        """work(instance, *args) on a thread of its own, after the instance's previous task."""
        before = self._threads.get(instance.id)

        def run() -> None:
            if before is not None:
                before.join()
            try:
                work(instance, *args)
            except Exception as exc:  # noqa: BLE001 - recorded on the instance, as a cloud would
                self.errors[instance.id] = f"{work.__name__}: {exc}\n{traceback.format_exc()}"
                self.progress(f"{instance.id}: {work.__name__.strip('_')} failed: {exc}")
                with self.lock:
                    if work == self._boot_instance:  # bound methods: equal, never identical
                        from moto.ec2.models.instances import StateReason

                        _set_state(instance, TERMINATED)
                        instance.state_reason = StateReason("Server.InternalError: Internal error on launch",
                                                            "Server.InternalError")
            finally:
                with self.lock:
                    if self._threads.get(instance.id) is threading.current_thread():
                        del self._threads[instance.id]

        thread = threading.Thread(target=run, name=f"aws-boot-{work.__name__.strip('_')}-{instance.id}", daemon=True)
        with self.lock:
            self._threads[instance.id] = thread
        thread.start()

    def _boot_instance(self, instance, image_id: str) -> None:
        with self.lock:
            if instance.state != "pending":
                return  # terminated or stopped before it could boot
            ip = instance.private_ip
            legs = self._legs(instance)
            user_data = base64.b64decode(instance.user_data.as_bytes()) if instance.user_data else b""
            key = self.ec2.key_pairs.get(instance.key_name) if instance.key_name else None
            keys = [key.material_public.decode() if isinstance(key.material_public, bytes) else key.material_public] \
                if key is not None and key.material_public else []
            image = self.disks[image_id]
        t0 = time.monotonic()
        self.boot.boot(instance.id, "ip-" + ip.replace(".", "-"), image, user_data, list(legs.items()), keys)
        with self.lock:
            self._instances[instance.id] = instance
            if instance.state == "pending":
                _set_state(instance, RUNNING)
        self._rewire()
        self.progress(f"{instance.id} booted {image} at {ip} in {time.monotonic() - t0:.1f} s")

    def _power(self, instance, on: bool) -> None:
        if not self.boot.has(instance.id):
            return
        (self.boot.start if on else self.boot.stop)(instance.id)
        with self.lock:
            if instance.state == ("pending" if on else "stopping"):
                _set_state(instance, RUNNING if on else STOPPED)

    def _delete(self, instance) -> None:
        self.boot.delete(instance.id)
        with self.lock:
            self._instances.pop(instance.id, None)
            if instance.state == "shutting-down":
                _set_state(instance, TERMINATED)

    def _capture(self, instance, ami) -> None:
        try:
            ref = self.boot.capture(instance.id, ami.name or ami.id)
        except Exception:
            ami.state = "failed"
            raise
        with self.lock:
            self.disks[ami.id] = ref
            self.captured.add(ami.id)
            ami.state = "available"
        self.progress(f"{ami.id} captured from {instance.id} as {ref}")

    def console(self, instance_id: str) -> str:
        """What GetConsoleOutput returns: the container's console, its most recent 64 KiB."""
        if not self.boot.has(instance_id):
            return ""
        text = self.boot.console(instance_id).replace("\r\n", "\n")
        data = text.encode()
        return data[-CONSOLE_BYTES:].decode(errors="ignore") if len(data) > CONSOLE_BYTES else text

    # -- networks ----------------------------------------------------------------------------------
    def claim_subnet_cidr(self, within: str, prefix: int = 24) -> str:
        """A CIDR no Docker network of this machine uses, held by a network of the fake from now on:
        a subnet created later with this CIDR (the inventory's common network) is that network."""
        name = f"cidr-{len(self._cidr_nets)}"
        net, cidr = self.boot.claim_network(name, within, prefix)
        self._cidr_nets[cidr] = net
        return cidr

    def _network_for(self, subnet_id: str, cidr: str) -> str:
        if subnet_id not in self._subnet_nets:
            self._subnet_nets[subnet_id] = self._cidr_nets.get(cidr) or self.boot.ensure_network(f"{subnet_id}", cidr)
        return self._subnet_nets[subnet_id]

    def _legs(self, instance) -> dict[str, str]:
        """Docker network -> private IP of each of the instance's network interfaces, the primary first."""
        return {self._network_for(nic.subnet.id, nic.subnet.cidr_block): nic.private_ip_address
                for _, nic in sorted(instance.nics.items())}

    def _remove_network(self, net: str) -> None:
        with contextlib.suppress(Exception):  # still in use: the run's cleanup removes it
            self.boot.networks[net].remove()
            self.boot.networks.pop(net, None)

    def _free_public_ip(self) -> str:
        """The next address of the fake's internet that no Elastic IP or interface holds."""
        from moto.ec2.exceptions import EC2ClientError

        used = {a.public_ip for a in self.ec2.addresses}
        used |= {nic.public_ip for nic in self.ec2.enis.values() if getattr(nic, "public_ip", None)}
        net = ipaddress.IPv4Network(self.internet_cidr)
        for host in list(net.hosts())[9:]:  # .1 is the host; low addresses left alone
            if str(host) not in used:
                return str(host)

        raise EC2ClientError("AddressLimitExceeded", "The maximum number of addresses has been reached.")

    def _rewire(self) -> None:
        """Each container's interfaces as EC2 has the instance: its subnet at its private IP, and
        the internet at its public IP while one is associated."""
        with self.lock:
            for iid, instance in list(self._instances.items()):
                if not self.boot.has(iid):
                    continue
                wanted = self._legs(instance)
                if instance.public_ip:
                    wanted[self.internet_network] = instance.public_ip
                have = self.boot.attachments(iid)
                for net in have.keys() - wanted.keys():
                    self.boot.detach(iid, net)
                for net, ip in wanted.items():
                    if have.get(net) != ip:
                        self.boot.attach(iid, net, ip)

    # -- what the fake holds --------------------------------------------------------------------------
    def wait_idle(self, timeout: float = 120) -> None:
        """Until no instance task (boot, stop, capture, delete) runs."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self.lock:
                threads = list(self._threads.values())
            if not threads:
                return
            threads[0].join(timeout=max(0.1, deadline - time.monotonic()))
        raise TimeoutError("instance tasks still running")


def _tag_specs(params: dict[str, str]) -> dict[str, str]:
    """Tags of a query-protocol request's TagSpecification.N.Tag.M.Key/Value parameters (all resource types)."""
    tags = {}
    for key, value in params.items():
        m = re.fullmatch(r"TagSpecification\.(\d+)\.Tag\.(\d+)\.Key", key)
        if m:
            tags[value] = params.get(f"TagSpecification.{m.group(1)}.Tag.{m.group(2)}.Value", "")
    return tags

"""`snapshot bake` orchestration over an in-memory provider: what the builder gets, when it is
captured, and that it is terminated in every case. The builder's user-data is checked by
cloud-init's own validator."""

from __future__ import annotations

import re
import shutil
import subprocess

import pytest
import yaml

from ccrp_cli.ops import snapshots
from ccrp_cli.errors import CcrpError, InputError
from ccrp_cli.fleet import Fleet
from ccrp_cli.providers import info
from ccrp_cli.providers.base import CloneRecord, CloneState, Origin, SnapshotRecord
from ccrp_cli.recipes import platform
from ccrp_cli.models.layout import LOCALE_SETUP
from ccrp_cli.render.cloudinit import PRIVATE_KEY_MARKERS
from tests.conftest import ROOT

INVENTORIES = {k: ROOT / "inventories" / f"{k}.yaml" for k in ("openstack", "gcp", "aws")}


class FakeCloud:
    """The Provider protocol's calls bake makes, kept in memory. `boot` lists the consoles the
    builder shows on successive reads (the last one repeats)."""

    def __init__(self, kind: str, boot: list[str] | None = None) -> None:
        self.kind = kind
        self.boot = boot
        # The stock Debian 12 images of each cloud (their ProviderInfo.bake_base), and AWS's public SSM
        # parameter naming Debian's current AMI.
        self.images = {"debian-12-genericcloud-amd64", "projects/debian-cloud/global/images/family/debian-12",
                       "ami-0debian12"}
        self.ssm = {"/aws/service/debian/release/bookworm/latest/amd64": "ami-0debian12"}
        self.instances: dict[str, object] = {}
        self.specs: list = []  # every spec run_instance was given
        self.calls: list[str] = []
        self.snapshots: list[SnapshotRecord] = []
        self.fail: dict[str, BaseException] = {}

    def _maybe_fail(self, what: str) -> None:
        self.calls.append(what)
        if what in self.fail:
            raise self.fail[what]

    def resolve_image(self, image: str) -> str:
        # AWS names Debian's current AMI by a public SSM parameter; other clouds by the name itself.
        return self.ssm.get(image, image) if self.kind == "aws" else image

    def has_image(self, image: str) -> bool:
        self._maybe_fail("has_image")
        return image in self.images

    def bootstrap(self) -> None:
        self._maybe_fail("bootstrap")

    def run_instance(self, spec):
        self.instances[spec.robot] = spec  # created before anything can fail, as on a cloud
        self.specs.append(spec)
        self._maybe_fail("run_instance")
        return CloneRecord(robot=spec.robot, provider_id="i-builder", state=CloneState.RUNNING, status="running",
                           origin=Origin.CREATED)

    def console_output(self, robot: str) -> str:
        self._maybe_fail("console_output")
        spec = self.instances[robot]
        token = re.search(r"ccrp-bake (\w+) finished", spec.user_data).group(1)
        text = self.boot.pop(0) if len(self.boot) > 1 else self.boot[0]
        return text.replace("TOKEN", token)

    def create_snapshot(self, robot: str, name: str) -> SnapshotRecord:
        self._maybe_fail("create_snapshot")
        assert robot in self.instances
        rec = SnapshotRecord(id=f"img-{len(self.snapshots)}", name=name, created="2025-01-01T00:00:00", source=robot)
        self.snapshots.append(rec)
        return rec

    def terminate(self, robot: str) -> bool:
        self._maybe_fail("terminate")
        return self.instances.pop(robot, None) is not None

    # -- the SSH transport a bake with software: uses (providers/cloud.py) ----------------------
    def login_keys(self) -> list[str]:
        return ["ssh-ed25519 AAAAC3NzaC1lZDI1NTE5AAAAIFakeOperatorKey ccrp-labos"]

    def connect(self, robot: str, rec) -> None:
        self._maybe_fail("connect")
        assert robot in self.instances and rec.provider_id == "i-builder"

    pushed: dict[str, object]
    build_result = (0, "== apt\n== catkin_make install\n== login removed\nccrp-software built\n")

    transport = property(lambda self: self)  # a fake clone is its own transport
    def push_files(self, robot: str, files: list, restart: list[str] = ()) -> None:
        self._maybe_fail("push_files")
        self.pushed = {f.dest: f for f in files}

    def exec(self, robot: str, argv: list[str], timeout: float = 60) -> tuple[int, str]:
        assert robot in self.instances
        if argv[0] == "env":
            self._maybe_fail("build")
            self.build_env = dict(w.split("=", 1) for w in argv[1:argv.index("sh")])
            self.build_argv = argv
            return self.build_result
        self._maybe_fail(f"exec {argv[0]}")
        return 0, ""


DONE = ("[  612.1] cloud-init[1502]: ccrp-bake TOKEN apt-ok\n"
        "[  612.9] cloud-init[1502]: ccrp-bake TOKEN locale-ok\n"
        "[  640.9] cloud-init[1502]: ccrp-bake TOKEN pip-ok\n"
        "[  641.0] cloud-init[1502]: ccrp-bake TOKEN finished after 640.95 s\n")


@pytest.fixture
def fleet(ccrp_home):
    return Fleet.open(INVENTORIES["openstack"])


def _bake(fleet, provider, **kw):
    notes: list[str] = []
    kw.setdefault("base_image", "debian-12-genericcloud-amd64")
    record = snapshots.bake(fleet, provider, notes.append, poll=0, **kw)
    return record, notes


def test_bake_captures_terminates_and_records(fleet):
    cloud = FakeCloud("openstack", ["", "booting...\n", DONE])
    record, notes = _bake(fleet, cloud)
    assert cloud.calls == ["has_image", "bootstrap", "run_instance", "console_output", "console_output",
                           "console_output", "create_snapshot", "terminate"]
    assert cloud.instances == {}  # the builder is gone
    assert record.name.startswith("ccrp-labos-noetic-")
    snap = fleet.store.load_state().snapshot
    assert snap == {"image": "img-0", "id": "img-0", "source": "snapshot-builder", "region": "mycloud",
                    "base": "debian-12-genericcloud-amd64", "name": record.name, "software": "none"}
    assert any("builder terminated" in n for n in notes)


def test_builder_spec_and_user_data(fleet, tmp_path):
    cloud = FakeCloud("openstack", [DONE])
    _bake(fleet, cloud)
    spec, = cloud.specs
    assert spec.role == "builder" and spec.image == "debian-12-genericcloud-amd64"
    ud = spec.user_data
    token = re.search(r"ccrp-bake (\w+) finished after \$UPTIME s", ud).group(1)
    # What the Docker snapshot has, from Debian's archive only: no third-party apt source.
    data = yaml.safe_load(ud)
    assert data["packages"] == platform("noetic", "debian-bookworm").packages and "apt" not in data
    assert "packages.ros.org" not in ud and "ros-core" in data["packages"] and "openvpn" in data["packages"]
    assert ["env", "PIP_BREAK_SYSTEM_PACKAGES=1", "pip3", "install", "--no-cache-dir",
            *platform("noetic", "debian-bookworm").pip] in data["runcmd"]
    assert "eclipse-zenoh==1.10.2" in platform("noetic", "debian-bookworm").pip
    assert [f["path"] for f in data["write_files"]] == ["/usr/local/lib/ccrp/relay.py", "/usr/local/lib/ccrp/api_manager.py",
                                                        "/usr/local/bin/ccrp-topic"]
    assert ["sh", "-c", LOCALE_SETUP] in data["runcmd"]
    # cloud-init's own locale module would run before the packages and fail on an image without the locale.
    assert data["locale"] == "false"
    # No image default user (admin, debian...) baked into the snapshot: only ccrp's, without key or sudo.
    assert data["users"] == [{"name": "ccrp", "shell": "/bin/bash", "lock_passwd": True}]
    # The proofs are printed with the token as an argument: the user-data itself cannot satisfy them.
    assert not any(f"ccrp-bake {token} {p}-ok" in ud for p in ("apt", "locale", "pip"))
    assert not any(m in ud for m in PRIVATE_KEY_MARKERS)
    assert "nao1" not in ud and "labos" not in ud  # nothing of the fleet's clones in the image
    assert "- /etc/machine-id" in ud  # emptied, so each clone gets its own
    # A cloud may capture the builder running (a real Nova does): the last runcmd writes back the page cache.
    assert data["runcmd"][-1] == ["sync"]
    if shutil.which("cloud-init"):
        f = tmp_path / "builder.yaml"
        f.write_text(ud)
        proc = subprocess.run(["cloud-init", "schema", "--config-file", str(f)], capture_output=True, text=True)
        assert proc.returncode == 0 and "Valid cloud-config" in proc.stdout, proc.stdout + proc.stderr


def test_missing_install_proof_fails_and_terminates(fleet):
    no_pip = DONE.replace("ccrp-bake TOKEN pip-ok\n", "pip: error: no matching distribution\n")
    cloud = FakeCloud("openstack", [no_pip])
    with pytest.raises(CcrpError, match="its pip install failed"):
        _bake(fleet, cloud)
    assert cloud.calls[-1] == "terminate" and cloud.instances == {}
    assert "create_snapshot" not in cloud.calls
    assert fleet.store.load_state().snapshot is None


def test_a_failed_install_names_its_error_not_cloud_inits_tables(fleet):
    """The error said the console's last lines: cloud-init's network table on a real OpenStack."""
    failed = DONE.replace("[  640.9] cloud-init[1502]: ccrp-bake TOKEN pip-ok\n",
                          "[  630.0] cloud-init[1502]: ERROR: Could not find a version that satisfies ros-jazzy-rclpy\n"
                          "[  630.1] cloud-init[1502]: ci-info: +------+------+\n")
    with pytest.raises(CcrpError) as err:
        _bake(fleet, FakeCloud("openstack", ["[    1.2] ACPI: no errors here\n" + failed]))
    assert "its pip install failed:" in err.value.message and "ERROR: Could not find a version" in err.value.message
    assert "ci-info" not in err.value.message and "ACPI" not in err.value.message


@pytest.mark.parametrize("where", ["run_instance", "console_output", "create_snapshot"])
def test_failure_anywhere_terminates_the_builder(fleet, where):
    cloud = FakeCloud("openstack", [DONE])
    cloud.fail[where] = CcrpError(f"{where} broke")
    with pytest.raises(CcrpError, match=f"{where} broke"):
        _bake(fleet, cloud)
    assert cloud.calls[-1] == "terminate" and cloud.instances == {}
    assert fleet.store.load_state().snapshot is None


def test_ctrl_c_while_waiting_terminates_the_builder(fleet):
    cloud = FakeCloud("openstack", ["booting...\n"])
    cloud.fail["console_output"] = KeyboardInterrupt()
    with pytest.raises(KeyboardInterrupt):
        _bake(fleet, cloud)
    assert cloud.calls[-1] == "terminate" and cloud.instances == {}


def test_timeout_terminates_the_builder(fleet):
    cloud = FakeCloud("openstack", ["still installing...\n"])
    with pytest.raises(CcrpError, match="did not finish within 0 s"):
        _bake(fleet, cloud, timeout=0)
    assert cloud.calls[-1] == "terminate" and cloud.instances == {}


def test_a_failed_terminate_keeps_the_original_error(fleet):
    cloud = FakeCloud("openstack", [DONE])
    cloud.fail["create_snapshot"] = CcrpError("quota exceeded")
    cloud.fail["terminate"] = RuntimeError("API down")
    with pytest.raises(CcrpError, match="quota exceeded"):
        _bake(fleet, cloud)
    assert cloud.calls[-1] == "terminate"


def test_a_failed_terminate_after_success_is_an_error(fleet):
    cloud = FakeCloud("openstack", [DONE])
    cloud.fail["terminate"] = RuntimeError("API down")
    with pytest.raises(CcrpError, match="could not terminate the builder") as err:
        _bake(fleet, cloud)
    assert "ccrp gc" in err.value.hint
    assert fleet.store.load_state().snapshot is None  # not recorded: the operator has to look first


def test_a_bake_starts_from_the_image_the_provider_settings_name(ccrp_home, tmp_path):
    """OpenStack's provider.image (ProviderSettings.bake_image) is the base when --base-image is not
    given; the other clouds' settings name none, so they start from their stock Debian."""
    data = yaml.safe_load(INVENTORIES["openstack"].read_text())
    data["provider"]["image"] = "my-debian-12"
    path = tmp_path / "fleet.yaml"
    path.write_text(yaml.safe_dump(data))
    cloud = FakeCloud("openstack", [DONE])
    cloud.images.add("my-debian-12")
    _bake(Fleet.open(path), cloud, base_image=None)
    assert cloud.specs[0].image == "my-debian-12"
    assert [Fleet.open(INVENTORIES[k]).inventory.provider.bake_image() for k in ("gcp", "aws")] == [None, None]


def test_aws_defaults_to_debians_ssm_parameter_resolved_to_its_ami(ccrp_home):
    aws = Fleet.open(INVENTORIES["aws"])
    cloud = FakeCloud("aws", [DONE])
    _bake(aws, cloud, base_image=None)
    assert info("aws").bake_base == "/aws/service/debian/release/bookworm/latest/amd64"
    assert cloud.specs[0].image == "ami-0debian12"  # booted from the AMI the parameter names today
    assert aws.store.load_state().snapshot["base"] == "ami-0debian12"


def test_openstack_defaults_to_debians_generic_cloud_image_and_names_it_when_missing(fleet):
    cloud = FakeCloud("openstack", [DONE])
    _bake(fleet, cloud, base_image=None)
    assert cloud.specs[0].image == info("openstack").bake_base == "debian-12-genericcloud-amd64"
    cloud = FakeCloud("openstack", [DONE])
    cloud.images.clear()  # nobody uploaded it to this cloud's Glance
    with pytest.raises(InputError, match="base image debian-12-genericcloud-amd64 not found on openstack") as err:
        _bake(fleet, cloud, base_image=None)
    assert "debian-12-genericcloud-amd64.qcow2" in err.value.hint and "provider.image" in err.value.hint
    assert cloud.calls == ["has_image"]  # nothing created


def test_gcp_defaults_to_debians_image_family_and_records_the_image_name(ccrp_home):
    gcp = Fleet.open(INVENTORIES["gcp"])
    cloud = FakeCloud("gcp", [DONE])
    record, _ = _bake(gcp, cloud, base_image=None)
    assert cloud.specs[0].image == info("gcp").bake_base == "projects/debian-cloud/global/images/family/debian-12"
    snap = gcp.store.load_state().snapshot
    assert snap["image"] == record.name and snap["region"] == "europe-west2"


@pytest.mark.skipif(shutil.which("cloud-init") is None, reason="cloud-init not installed (apt-get install cloud-init)")
@pytest.mark.parametrize("kind", sorted(INVENTORIES))
def test_every_clouds_builder_user_data_passes_cloud_init_schema(ccrp_home, tmp_path, kind):
    from ccrp_cli.render.cloudinit import builder_user_data
    from ccrp_cli.services.registry import image_agents

    inv = Fleet.open(INVENTORIES[kind]).inventory
    f = tmp_path / "builder.yaml"
    f.write_text(builder_user_data(inv, "0123456789abcdef", image_agents()))
    proc = subprocess.run(["cloud-init", "schema", "--config-file", str(f)], capture_output=True, text=True)
    assert proc.returncode == 0 and "Valid cloud-config" in proc.stdout, proc.stdout + proc.stderr


def test_docker_is_refused(ccrp_home):
    lab = Fleet.open(ROOT / "inventories" / "lab.yaml")
    with pytest.raises(InputError, match="cannot do snapshot bake") as err:
        snapshots.bake(lab, FakeCloud("docker", [DONE]), lambda m: None)
    assert "snapshot build" in err.value.hint


WORKSPACE = {
    "src/hello/package.xml": "<package format='2'><name>hello</name><version>0.0.1</version>"
                             "<description>d</description><maintainer email='a@b.c'>a</maintainer>"
                             "<license>MIT</license><buildtool_depend>catkin</buildtool_depend>"
                             "<exec_depend>rospy</exec_depend></package>",
    "src/hello/CMakeLists.txt": "cmake_minimum_required(VERSION 3.0.2)\nproject(hello)\n",
    "src/hello/scripts/hello": "#!/usr/bin/env python3\nprint('hello')\n",
    "build/junk.o": "build output stays out",
}


def _software_fleet(tmp_path):
    data = yaml.safe_load(INVENTORIES["openstack"].read_text())
    data["software"] = {"apt": ["htop"], "pip": ["numpy>=1.24"], "workspace": "ws",
                        "run": [{"name": "hello", "command": ["/opt/ccrp/workspace/lib/hello/hello"]}]}
    for rel, text in WORKSPACE.items():
        (tmp_path / "ws" / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / "ws" / rel).write_text(text)
    path = tmp_path / "inventory.yaml"
    path.write_text(yaml.safe_dump(data))
    return Fleet.open(path)


def test_bake_builds_the_software_on_the_builder_and_records_its_digest(ccrp_home, tmp_path):
    """software: on a cloud (docs/workloads.md): the builder's login gets the operator key, ccrp
    SSHes in after cloud-init, pushes the workspace, builds it with the recipe's build tools, and
    only then captures; the snapshot is recorded with the software's digest and packages as
    `snapshot build` records them."""
    import base64
    import io
    import tarfile

    from ccrp_cli.services.workloads import packages_record, snapshot_software

    fleet = _software_fleet(tmp_path)
    cloud = FakeCloud("openstack", [DONE])
    _bake(fleet, cloud)
    assert cloud.calls == ["has_image", "bootstrap", "run_instance", "console_output", "connect", "exec mkdir",
                           "push_files", "build", "create_snapshot", "terminate"]
    users = yaml.safe_load(cloud.specs[0].user_data)["users"]
    assert users == [{"name": "ccrp", "shell": "/bin/bash", "sudo": "ALL=(ALL) NOPASSWD:ALL", "lock_passwd": True,
                      "ssh_authorized_keys": cloud.login_keys()}]
    tar_file = cloud.pushed[f"{snapshots.BAKE_DIR}/workspace.tar.b64"]
    assert tar_file.mode == 0o600
    with tarfile.open(fileobj=io.BytesIO(base64.b64decode(tar_file.content))) as tar:
        assert sorted(tar.getnames()) == sorted(k for k in WORKSPACE if not k.startswith("build/"))
        assert tar.extractfile("src/hello/scripts/hello").read() == WORKSPACE["src/hello/scripts/hello"].encode()
    env = cloud.build_env
    assert env["CCRP_BUILD"] == "catkin" and env["CCRP_APT"] == "htop python3-rospy catkin"
    assert env["CCRP_BUILD_APT"] == "catkin cmake gcc g++ make" and env["CCRP_PIP"] == "numpy>=1.24"
    assert env["CCRP_LOGIN"] == "ccrp" and "pip3" in env["CCRP_PIP_CMD"]
    scripts = [(ROOT / "templates/image" / name).read_text() for name in ("interfaces-build.sh", "software-bake.sh")]
    assert cloud.build_argv[-4:-1] == ["sh", "-c", "".join(scripts)]
    software = snapshot_software(fleet.inventory, fleet.path)
    snap = fleet.store.load_state().snapshot
    assert snap["software"] == software.digest != "none" and snap["packages"] == packages_record(software)


def test_a_failed_software_build_names_its_step_and_captures_nothing(ccrp_home, tmp_path):
    fleet = _software_fleet(tmp_path)
    cloud = FakeCloud("openstack", [DONE])
    cloud.build_result = (100, "== apt\n== catkin_make install\nCMake Error at toplevel.cmake:11: boom\n"
                               "-- Configuring incomplete\n####\nInvoking \"cmake\" failed\n")
    with pytest.raises(CcrpError, match=r"could not build the software \(at catkin_make install\): "
                                        r"CMake Error at toplevel.cmake:11: boom \| .*Invoking \"cmake\" failed"):
        _bake(fleet, cloud)
    assert "create_snapshot" not in cloud.calls and cloud.calls[-1] == "terminate" and cloud.instances == {}
    assert fleet.store.load_state().snapshot is None


def test_bake_without_software_never_logs_in(fleet):
    cloud = FakeCloud("openstack", [DONE])
    _bake(fleet, cloud)
    assert "connect" not in cloud.calls and "build" not in cloud.calls
    assert fleet.store.load_state().snapshot["software"] == "none"


def test_a_baked_snapshot_goes_stale_when_the_workspace_changes(ccrp_home, tmp_path):
    """fleet up refuses (check_snapshot), and fleet plan names the clones (stale_snapshot), once the
    inventory's workspace is not the one the cloud snapshot was baked with; the hint is the cloud's."""
    from ccrp_cli.services.workloads import check_snapshot, stale_snapshot

    fleet = _software_fleet(tmp_path)
    _bake(fleet, FakeCloud("openstack", [DONE]))
    state = fleet.store.load_state()
    assert stale_snapshot(fleet, state) is None
    check_snapshot(fleet, state, "openstack")  # current: no refusal
    (tmp_path / "ws" / "src/hello/scripts/hello").write_text("print('changed')\n")
    assert "the snapshot holds software" in stale_snapshot(fleet, state)
    with pytest.raises(InputError, match="clones made from it would not have it") as err:
        check_snapshot(fleet, state, "openstack")
    assert err.value.hint == "ccrp snapshot bake -i INVENTORY first"

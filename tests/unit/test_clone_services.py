"""Clone services as plug-ins (issue 26): the registry's order, and ensure_clone running them on a
fake clone with the same pushes, restarts and commands, in the same order, as before the registry."""

from __future__ import annotations

import hashlib

import pytest
import yaml

from ccrp_cli.ops import clones
from ccrp_cli.services.registry import SERVICES
from ccrp_cli.fleet import Fleet, clone_view
from ccrp_cli.providers.base import CloneRecord, CloneState, Origin
from tests.conftest import LAB

RESULT = '{"v1": {"datasource": "DataSourceNoCloud", "errors": []}}'


def test_the_registry_runs_the_services_in_fleet_ups_order():
    assert [s.name for s in SERVICES] == ["relay", "autostop", "power", "api_manager", "knowledge", "nodes", "camera"]
    # Settings go before the keys in this order; the others are applied after the clone serves.
    assert [s.name for s in SERVICES if s.settings] == ["relay", "autostop", "knowledge"]
    assert [s.name for s in SERVICES if s.reshared] == ["relay", "knowledge"]


def test_each_services_boot_declaration_is_in_the_user_data(lab):
    """What a service says its clone gets from the user-data is what render/cloudinit.py writes:
    its units (enabled at first boot, its sockets alone and first), agents, files and users."""
    from ccrp_cli.models.layout import CCRP_LIB
    from ccrp_cli.render import cloudinit
    from ccrp_cli.services.registry import boots

    state = lab.load_allocated()
    view = clone_view(lab, state, "nao1")
    data = cloudinit.user_data_dict(view, boots())
    written = {f["path"]: f["content"] for f in data["write_files"]}
    users = {u["name"] for u in data["users"]}
    started = [c[2:] for c in data["runcmd"] if c[:2] == ["systemctl", "start"]]
    [enabled] = [c[3:] for c in data["runcmd"] if c[:3] == ["systemctl", "enable", "--no-reload"]]
    for service in SERVICES:
        boot = service.boot
        assert {f"/etc/systemd/system/{u}" for u in boot.units + boot.sockets} <= set(written), service.name
        assert {f"{CCRP_LIB}/{a}.py" for a in boot.agents} <= set(written), service.name
        assert all(written.get(f.dest) == f.content for f in boot.files(view)), service.name
        assert set(boot.users) <= users and set(boot.units) <= set(started[-1]), service.name
        assert set(boot.units + boot.sockets) <= set(enabled), service.name  # and at every later boot
    assert started[0] == ["ccrp-power.socket"]  # the power agent's port is systemd's before any service runs


@pytest.fixture(autouse=True)
def one_health_look(monkeypatch):
    """The nodes' health check looks once (its window is 3 s)."""
    from ccrp_cli.services import workloads

    monkeypatch.setattr(workloads, "HEALTH_SECONDS", 0)


class Clone:
    """A provider with one clone that keeps what is pushed to it and answers ensure_clone's
    commands as a serving clone does; `log` is every push and command, in order."""

    kind = "docker"
    max_parallel = 4

    def __init__(self) -> None:
        self.held: dict[str, str] = {}
        self.log: list[tuple] = []
        self.origin = Origin.CREATED
        self.node_state = "active"

    transport = property(lambda self: self)  # a fake clone is its own transport

    def login_keys(self) -> list[str]:
        return []

    def run_instance(self, spec) -> CloneRecord:
        self.log.append(("run_instance", self.origin.value))
        return CloneRecord(robot=spec.robot, provider_id="c1", state=CloneState.RUNNING, status="running",
                           public_ip="198.51.100.7", origin=self.origin)

    def wait_ready(self, robot, timeout=300) -> None:
        self.log.append(("wait_ready",))

    def bootstrap(self) -> None:
        pass

    def query(self) -> dict[str, CloneRecord]:
        return {"nao1": CloneRecord(robot="nao1", provider_id="c1", state=CloneState.RUNNING, status="running")}

    def terminate(self, robot) -> None:
        self.log.append(("terminate",))

    def push_files(self, robot, files, restart=()) -> None:
        self.log.append(("push", [f.name for f in files], list(restart)))
        self.held.update({f.dest: f.content for f in files})

    def exec(self, robot, argv, timeout=60) -> tuple[int, str]:
        from ccrp_cli.services import api_manager, workloads

        script = argv[2] if argv[:2] in (["bash", "-c"], ["sh", "-c"]) else None
        if script == clones.PROBE_SH:
            self.log.append(("probe",))
            lines = "".join(f"{hashlib.sha256(self.held[p].encode()).hexdigest()}  {p}\n" for p in argv[5:] if p in self.held)
            return 0, f"== result\n{RESULT}\n== digests\n{lines}== serving vpn=yes master=yes\n"
        if script == clones.WAIT_SERVING_SH:
            self.log.append(("wait_serving",))
            return 0, "vpn=yes master=yes\n"
        if script == clones.SECRETS_DIR_SH:
            self.log.append(("prepare_secrets_dir",))
            return 0, "1\n2\n"
        if argv[:2] == ["systemctl", "show"]:  # the nodes' health check: every node active
            self.log.append(("node_health", argv[4:]))
            sub = {"active": "running", "activating": "auto-restart"}.get(self.node_state, self.node_state)
            return 0, "".join(f"Id={u}\nActiveState={self.node_state}\nSubState={sub}\nNRestarts=0\n\n" for u in argv[4:])
        if argv[0] == "journalctl":
            return 0, '{"__CURSOR": "c1", "MESSAGE": "mapper: No such file or directory"}\n'
        names = {api_manager.HAS_UNIT_SH: "has_api_unit", workloads.APPLY_SH: "apply_nodes"}
        self.log.append(("exec", names[script] if script in names else " ".join(argv)))
        return 0, ""


def fleet_with_every_service(tmp_path, ccrp_home, rate: float = 1.0, idle: str | None = None) -> Fleet:
    """The lab (knowledge sync on every robot) with an API manager and a node of its own on each robot."""
    data = yaml.safe_load(LAB.read_text())
    data["services"]["api_manager"] = {"rate": rate}
    if idle:
        data["autostop"] = {"idle": idle}
    data["software"] = {"run": [{"name": "mapper", "command": ["mapper", "--fast"]}]}
    path = tmp_path / "fleet.yaml"
    path.write_text(yaml.safe_dump(data))
    return Fleet.open(path)


def up_nao1(fleet: Fleet, clone: Clone) -> list[str]:
    from ccrp_cli.ops import vpn

    state = fleet.load_allocated()
    if not fleet.pki.exists():  # as `fleet up` does before ensure_clone
        vpn.init(fleet)
        fleet.pki.issue_fleet({name: str(a.common_ip) for name, a in fleet.plan(state).items()}, 30)
    state.snapshot = {"image": "ccrp/lab-clone:1", "id": "sha256:1"}
    for rec in state.robots.values():
        rec.phase = "ready"
    said: list[str] = []
    writer = clones.StateWriter(fleet, state)
    result = clones.ensure_clone(fleet, clone, writer, "nao1", said.append)
    assert result.action == ("created" if clone.origin is Origin.CREATED else "reused")
    return [line for line in said if "started" in line]


# The secrets of a clone, in the order bundles.clone_secrets gives them, as pushed.
SECRETS = ["ca.crt", "server.crt", "server.key", "tls-crypt.key", "passwd", "relay-ca.crt", "relay.crt", "relay.key",
           "crl.pem"]


def test_a_new_clone_gets_every_service_in_the_order_it_always_had(tmp_path, ccrp_home):
    fleet = fleet_with_every_service(tmp_path, ccrp_home)
    clone = Clone()
    started = up_nao1(fleet, clone)
    pushes = [e for e in clone.log if e[0] == "push"]
    secrets = pushes[1][1]
    assert clone.log == [
        ("run_instance", "created"), ("wait_ready",), ("probe",),
        ("push", ["relay.json", "autostop.json", "knowledge.json", "knowledge.py"], []),
        ("prepare_secrets_dir",),
        ("push", secrets, ["ccrp-openvpn.service", "ccrp-relay.service"]),
        ("push", [".applied"], []),
        ("wait_serving",),
        ("exec", "has_api_unit"),
        ("push", ["api_manager.json", "api_manager.py"], ["ccrp-api-manager.service"]),
        ("exec", "systemctl restart ccrp-knowledge.service"),
        ("push", ["ccrp-run-mapper.service", "workloads.json"], []),
        ("exec", "apply_nodes"),
        ("node_health", ["ccrp-run-mapper.service"]),  # what it started stays up
        ("push", ["camera.py"], []),  # the camera agent: held, started by the first read
    ]
    assert "crl.pem" in secrets and "relay.key" in secrets
    assert started == ["[nao1] nodes started: mapper"]


def test_a_reused_clone_gets_only_the_service_file_that_changed(tmp_path, ccrp_home):
    fleet = fleet_with_every_service(tmp_path, ccrp_home)
    clone = Clone()
    up_nao1(fleet, clone)
    clone.log.clear()
    clone.origin = Origin.REUSED
    assert up_nao1(fleet, clone) == [] and clone.log == [("run_instance", "reused"), ("probe",)]  # all current

    changed = fleet_with_every_service(tmp_path, ccrp_home, rate=2.0)  # the API manager's config only
    clone.log.clear()
    assert up_nao1(changed, clone) == []
    assert clone.log == [
        ("run_instance", "reused"), ("probe",),
        ("exec", "has_api_unit"),
        ("push", ["api_manager.json", "api_manager.py"], ["ccrp-api-manager.service"]),
    ]


def test_a_reused_clone_gets_a_changed_setting_before_anything_else(tmp_path, ccrp_home):
    clone = Clone()
    up_nao1(fleet_with_every_service(tmp_path, ccrp_home), clone)
    clone.log.clear()
    clone.origin = Origin.REUSED
    assert up_nao1(fleet_with_every_service(tmp_path, ccrp_home, idle="30m"), clone) == []
    assert clone.log == [("run_instance", "reused"), ("probe",), ("push", ["autostop.json"], [])]


def test_a_node_that_does_not_stay_up_fails_fleet_up_and_clone_start(tmp_path, ccrp_home):
    """Issue 39: a node whose program is missing exits 127 and systemd restarts it every 3 s,
    `activating` in between. fleet up made it with `nodes started` and exit 0; now the nodes it
    starts get deploy's health check, and one that does not stay up fails the robot (exit 1),
    naming robot, node and its last lines. The clone is kept and recorded, to read its logs."""
    from ccrp_cli.ops import vpn
    from ccrp_cli.alerts import clone_alerts
    from ccrp_cli.cli import output
    from ccrp_cli.models.status import StatusRow
    from ccrp_cli.ops import reconcile

    fleet = fleet_with_every_service(tmp_path, ccrp_home)
    vpn.init(fleet)
    state = fleet.load_allocated()
    state.snapshot = {"image": "ccrp/lab-clone:1", "id": "sha256:1"}
    fleet.store.save_state(state)
    clone = Clone()
    clone.node_state = "activating"
    said: list[str] = []
    items = reconcile.up(fleet, clone, said.append, only=["nao1"], quotas_checked=True)
    [item] = items
    assert item.action == "failed" and output.results(items, as_json=False) == 1, item
    assert item.detail.startswith("robot 'nao1''s node mapper (ccrp-run-mapper.service) is activating/auto-restart: "
                                  "it does not stay up (ccrp logs --robot nao1 mapper); its last lines: "
                                  "mapper: No such file or directory"), item.detail
    assert not any("nodes started" in line for line in said), said
    assert ("terminate",) not in clone.log and fleet.store.load_state().robots["nao1"].phase == "ready"

    # A clone started again (`clone start`, the dashboard's Start) runs its nodes from its boot:
    # every one is checked, though fleet up restarted none.
    clone.origin, clone.node_state = Origin.RESUMED, "active"
    clone.log.clear()
    assert [i.action for i in reconcile.up(fleet, clone, said.append, only=["nao1"], quotas_checked=True)] == ["reused"]
    assert ("node_health", ["ccrp-run-mapper.service"]) in clone.log and ("exec", "apply_nodes") not in clone.log
    clone.node_state = "failed"
    assert [i.action for i in reconcile.up(fleet, clone, said.append, only=["nao1"], quotas_checked=True)] == ["failed"]
    # A clone kept as it was starts nothing: nothing checked, no seconds added.
    clone.origin = Origin.REUSED
    clone.log.clear()
    assert [i.action for i in reconcile.up(fleet, clone, said.append, only=["nao1"], quotas_checked=True)] == ["reused"]
    assert not any(e[0] == "node_health" for e in clone.log), clone.log

    # Status raises the restart-loop alert for such a node at once, not after 3 restarts.
    row = StatusRow(robot="nao1", clone="cri-nao1", phase="ready", status="running", state="running",
                    ros_distro="noetic", common_ip="10.90.0.10", vpn_subnet="10.80.1.0/24", master_reachable=True,
                    vpn_connected=True, nodes=[{"name": "mapper", "state": "activating", "sub": "auto-restart",
                                                "restarts": 0, "digest": "d1"}])
    assert [a["kind"] for a in clone_alerts(row)] == ["node-failing"]


def test_status_takes_each_services_fields(lab_up):
    from ccrp_cli.ops.status import service_fields

    fleet, state = lab_up
    nao1 = fleet.robot(state, "nao1")
    assert set(service_fields(fleet, state, nao1, None)) == {"autostop_idle_s", "api_manager", "knowledge"}
    health = {"relay": {"running": True, "peers": {"nao2": True}}, "nodes": [], "knowledge": {"running": True}}
    fields = service_fields(fleet, state, nao1, health)
    assert fields["relay_running"] and fields["relay_peers"] == {"nao2": True} and fields["nodes"] is None
    assert fields["power"] is None  # no device reported since the clone booted
    assert fields["knowledge"]["running"] and fields["api_manager"] is None and fields["autostop_idle_s"] is None


def test_the_camera_service_keeps_this_ccrps_agent_on_every_clone_and_starts_nothing(lab_up):
    """services/camera.py: its one file is the agent where robot/camera.py's unit runs it; fleet up
    pushes it when the clone's copy is missing or another, restarting nothing; no user-data, no field."""
    from ccrp_cli.resources import agent_source
    from ccrp_cli.services.base import ServiceContext
    from ccrp_cli.services.camera import AGENT, Camera

    fleet, state = lab_up
    camera = Camera()
    for robot in ("nao1", "nao2"):
        [f] = camera.files(ServiceContext(fleet, state, fleet.robot(state, robot)))
        assert (f.dest, f.mode, f.content) == (AGENT, 0o644, agent_source("camera"))
    assert camera.boot.units == camera.boot.agents == camera.boot.sockets == () and camera.boot.files(None) == []
    assert not camera.settings and not camera.reshared and camera.absent() == []
    assert camera.status(fleet, state, fleet.robot(state, "nao1"), {"relay": {}}) == {}

    clone = Clone()
    assert camera.apply(clone, "nao1", [f], {}, pushed_keys=True) == []  # missing: pushed, nothing started
    assert clone.log == [("push", ["camera.py"], [])]
    clone.log.clear()
    held = {AGENT: hashlib.sha256(f.content.encode()).hexdigest()}
    assert camera.apply(clone, "nao1", [f], held, pushed_keys=False) == [] and clone.log == []  # current: left alone
    assert camera.apply(clone, "nao1", [f], {AGENT: "0" * 64}, pushed_keys=False) == []  # another copy: replaced
    assert clone.log == [("push", ["camera.py"], [])]

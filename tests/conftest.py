"""Shared fixtures: an isolated CCRP_HOME, the lab fleet with its PKI, and a CLI runner."""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAB = ROOT / "inventories" / "lab.yaml"
INVENTORIES = sorted((ROOT / "inventories").glob("*.yaml"))


@pytest.fixture
def ccrp_home(tmp_path, monkeypatch) -> Path:
    home = tmp_path / "home"
    monkeypatch.setenv("CCRP_HOME", str(home))
    return home


def call_started() -> tuple[float, float]:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime, time.monotonic()


def record_call(args, started: tuple[float, float], code: int) -> None:
    """With CCRP_TEST_CALLS=<file>, one JSON line per `ccrp` process a test started: where the
    suite's CPU goes (docs/benchmarks.md). The children's rusage counts every child reaped
    meanwhile, so a call overlapping another is an upper bound."""
    if not os.environ.get("CCRP_TEST_CALLS"):
        return
    cpu, wall = call_started()
    line = {"test": os.environ.get("PYTEST_CURRENT_TEST", "").split(" ")[0],
            "argv": [a for a in args if not a.startswith("/")][:3], "cpu": round(cpu - started[0], 3),
            "wall": round(wall - started[1], 3), "rc": code}
    with open(os.environ["CCRP_TEST_CALLS"], "a") as fh:
        fh.write(json.dumps(line) + "\n")


def run_ccrp(*args: str, home: Path, cwd: Path = ROOT, check: bool = False) -> subprocess.CompletedProcess:
    env = {**os.environ, "CCRP_HOME": str(home)}
    env.pop("CCRP_INVENTORY", None)
    started = call_started()
    proc = subprocess.run(
        [sys.executable, "-m", "ccrp_cli", *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=120
    )
    record_call(args, started, proc.returncode)
    if check and proc.returncode != 0:
        raise AssertionError(f"ccrp {' '.join(args)} failed ({proc.returncode}): {proc.stderr}")
    return proc


@pytest.fixture
def ccrp(ccrp_home):
    def _run(*args: str, check: bool = False) -> subprocess.CompletedProcess:
        return run_ccrp(*args, home=ccrp_home, check=check)

    return _run


@pytest.fixture
def lab(ccrp_home):
    """The lab fleet with its CA and certificates for every robot."""
    from ccrp_cli.ops import vpn
    from ccrp_cli.fleet import Fleet

    fleet = Fleet.open(LAB)
    vpn.init(fleet)
    for robot in fleet.inventory.robots:
        vpn.issue(fleet, robot.name)
    return fleet


# -- end-to-end runs: shared images, grouping for parallel workers, what a failure prints -------------


@pytest.fixture(scope="session")
def clone_images():
    """distro -> the run's clone image of it (tests/e2e/fleet.py warm_snapshot), built on first use:
    every fleet's `snapshot build` after it is served from Docker's layer cache."""
    import docker

    from tests.e2e.fleet import warm_snapshot

    client = docker.from_env(timeout=900)
    built: dict[str, str] = {}

    def get(distro: str) -> str:
        if distro not in built:
            built[distro] = warm_snapshot(client, distro)
        return built[distro]

    yield get
    client.close()


# Work units of a parallel run (pytest-xdist, --dist loadgroup): the tests of a module that share a
# module-scoped fleet run on one worker, in file order; a scenario's backends are a unit each. The
# contract suite's Docker harness has one fleet name, so its tests stay on one worker too. Units start
# longest first (measured: docs/benchmarks.md "The test suite"), unit tests fill the gaps at the end.
# One cloud scenario starts first and makes the run's Noetic bake (baked_recipes); the other two
# clouds come after a Docker unit on each worker, so no worker idles waiting for that bake. Each
# worker takes a unit and one ahead (xdist's LoadScheduling), so the order is read in threes.
SLOWEST_FIRST = [
    # The third worker starts with a unit that needs no cloud bake: the AWS scenario started there
    # waited 145 s for the run's one full install of the recipe, which OpenStack's was making
    # (run 9), and found it ready when it came later (run 7).
    "tests/scenarios/test_user_path.py/openstack", "tests/e2e/test_docker_fleet.py", "tests/e2e/test_jazzy_fleet.py",
    # VM clones under TCG: long and CPU-bound, so early enough not to be the run's tail.
    "tests/e2e/test_libvirt.py",
    "tests/scenarios/test_user_path.py/aws", "tests/scenarios/test_user_path.py/docker",
    "tests/scenarios/test_user_path.py/gcp", "tests/scenarios/test_jazzy_cloud.py",
    "tests/e2e/test_gce_startup_script.py", "tests/e2e/test_evaluation.py", "tests/e2e/test_dashboard_browser.py",
]


def _group(item) -> str | None:
    """The item's work unit (no "]" in it: xdist would not see the group after one)."""
    path = item.nodeid.split("::")[0]
    if path.startswith("tests/scenarios/test_user_path.py"):
        return f"{path}/{item.callspec.params['run']}"
    if path.startswith(("tests/e2e/", "tests/scenarios/", "tests/live/")):
        return path
    if path.startswith("tests/contract/"):
        return f"{path}/{item.callspec.params['harness']}" if hasattr(item, "callspec") else path
    return None


@pytest.hookimpl(tryfirst=True)  # before xdist reads the xdist_group marks
def pytest_collection_modifyitems(config, items):
    groups = {}
    for item in items:
        group = _group(item)
        if group:
            item.add_marker(pytest.mark.xdist_group(group))
            groups[item] = group

    def rank(item) -> tuple[int, int]:
        group = groups.get(item)
        if group is None:
            return (2, 0)
        return (0, SLOWEST_FIRST.index(group)) if group in SLOWEST_FIRST else (1, 0)

    items[:] = sorted(items, key=rank)  # stable: file order within a unit


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """A failing end-to-end test prints its fleet's containers: states, failed units, journals of
    ccrp's units, consoles (tests/e2e/fleet.py diagnostics)."""
    outcome = yield
    report = outcome.get_result()
    if not report.failed or call.when not in ("setup", "call"):
        return
    labels = sorted({label for value in getattr(item, "funcargs", {}).values()
                     for label in getattr(value, "diagnostic_labels", ())})
    if not labels:
        return
    try:
        import docker

        from tests.e2e.fleet import diagnostics

        client = docker.from_env(timeout=60)
        try:
            report.sections.append(("ccrp fleet containers", "\n".join(diagnostics(client, label) for label in labels)))
        finally:
            client.close()
    except Exception as exc:  # noqa: BLE001 - never hide the test's own failure
        report.sections.append(("ccrp fleet containers", f"diagnostics failed: {exc!r}"))


def pytest_configure(config):
    """One id for the whole run, parallel workers included (xdist hands it to them): what the builder
    disks the fake clouds keep for the run carry (tests/fakes/cloudboot.py warm_bake). And ccrp_cli's
    bytecode, compiled once for the run's `ccrp` processes (compile_ccrp)."""
    if not hasattr(config, "workerinput"):
        uid = getattr(config.option, "testrunuid", None) or uuid.uuid4().hex
        if hasattr(config.option, "testrunuid"):
            config.option.testrunuid = uid
        os.environ["PYTEST_XDIST_TESTRUNUID"] = uid
        config._ccrp_pycache = compile_ccrp()


def compile_ccrp() -> list[Path]:
    """Where Python writes no bytecode (PYTHONDONTWRITEBYTECODE, as this machine's environment sets,
    or -B), every `ccrp` process a test starts compiled the 70-120 ccrp_cli modules it imports from
    source again: 0.15-0.2 s of CPU a process, in a CPU-bound run of about a thousand of them. The
    controller compiles them once before the workers start (compileall writes regardless of that
    setting; Python still checks each .pyc against its source's mtime and size); returns the
    __pycache__ directories this made, which pytest_unconfigure removes."""
    if not sys.dont_write_bytecode:
        return []  # each process writes what it compiles: the first one's work serves the rest
    import compileall

    package = ROOT / "ccrp_cli"
    before = set(package.rglob("__pycache__"))
    compileall.compile_dir(str(package), quiet=2)  # a tree it cannot write to: nothing gained, nothing said
    return sorted(set(package.rglob("__pycache__")) - before)


def pytest_unconfigure(config):
    import shutil

    for cache in getattr(config, "_ccrp_pycache", []):
        shutil.rmtree(cache, ignore_errors=True)


def pytest_sessionfinish(session):
    """After the last worker: remove the builder disks the run kept."""
    if hasattr(session.config, "workerinput"):
        return
    try:
        import docker

        from tests.fakes.cloudboot import remove_baked

        client = docker.from_env(timeout=120)
        try:
            remove_baked(client)
        finally:
            client.close()
    except Exception:  # noqa: BLE001 - no engine here: nothing was kept
        pass


@pytest.fixture(scope="session")
def baked_recipes():
    """distro -> the run's one full install of its recipe on the fake clouds' stock image
    (tests/fakes/cloudboot.py warm_bake), which later `snapshot bake` builders start from."""
    import yaml

    from ccrp_cli.loader import load_inventory
    from ccrp_cli.render.cloudinit import builder_user_data
    from ccrp_cli.services.registry import image_agents
    from tests.fakes.cloudboot import warm_bake

    done: dict[str, str] = {}

    def get(distro: str, tmp: Path) -> str:
        if distro not in done:
            data = yaml.safe_load((ROOT / "inventories" / "openstack.yaml").read_text())
            data["ros"]["distro"] = distro
            path = tmp / f"bake-{distro}.yaml"
            path.write_text(yaml.safe_dump(data))
            token = uuid.uuid4().hex[:16]
            done[distro] = warm_bake(builder_user_data(load_inventory(path), token, image_agents()).encode(), progress=lambda m: None)
        return done[distro]

    return get

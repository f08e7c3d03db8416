"""A new backend is its own package and one registry line (docs/architecture.md, "A new backend"):
the memory backend (tests/memory_backend, tests only) is registered with its line, and the
inventory, `fleet validate` and `fleet plan` take it with no other change; and no module of the
core names a backend's kind (what differs by backend is declared in its package: ProviderInfo,
abilities)."""

from __future__ import annotations

import ast
import json
import re
import sys
from pathlib import Path

import pytest

from ccrp_cli.errors import CcrpError

from ccrp_cli.providers import REGISTRY, register, unregister

ROOT = Path(__file__).resolve().parents[2]
INVENTORY = """\
fleet: mem
provider:
  kind: memory
robots:
  - name: r1
  - name: r2
"""
# Where the core may write a backend's kind inside a string (a message, a help text, a path), and
# how many strings do, each with its reason: each is a place a new backend would have to be added by
# hand. Not scanned: the backends' own packages (providers/<kind>/), providers/registry.py (where a
# backend is declared: its one line) and docstrings (documentation, which names backends to explain
# them). A message that lists the kinds takes them from the registry (registry.kinds).
NAMES_A_KIND: dict[str, int] = {
    # `ccrp init --provider` and `--cloud`'s help texts describe each backend (left for the cli/ move).
    "ccrp_cli/cli/init.py": 2,
    # `robot sim --network`'s help: which fleets have their own network (Docker's, libvirt's).
    "ccrp_cli/cli/robot.py": 1,
    # A comment in deploy's install script citing templates/docker/software.j2, a file's path.
    "ccrp_cli/ops/install_space.py": 1,
    # What runs on this host's Docker engine whatever the fleet's backend (robot_host, build_workspace,
    # and whether it answers: local_engine_answers, where ccrp deploy builds), and the wheel cache
    # its image builds fill (fetch_wheels: a bake's build tools).
    "ccrp_cli/providers/__init__.py": 4,
    # The Docker SDK's import names (the robot host and build use it whatever the fleet's backend).
    "ccrp_cli/providers/sdk.py": 2,
    # `robot sim`'s hint for robots outside the host: a libvirt fleet's vpn_forward.
    "ccrp_cli/robot/simulated.py": 1,
}

def ccrp(monkeypatch, capsys, *args: str) -> tuple[int, str, str]:
    """The `ccrp` entry point in this process, where the test registered the backend."""
    from ccrp_cli.cli.main import run

    monkeypatch.setattr(sys, "argv", ["ccrp", *args])
    with pytest.raises(SystemExit) as done:
        run()
    out = capsys.readouterr()
    return done.value.code, out.out, out.err


@pytest.fixture
def memory():
    from tests.memory_backend import INFO, cloud

    register(INFO)  # the backend's one line
    try:
        yield cloud.fresh()
    finally:
        unregister(INFO.kind)


def test_a_backend_in_its_own_package_takes_the_inventory_and_fleet_plan(memory, ccrp_home, tmp_path, monkeypatch,
                                                                         capsys):
    from ccrp_cli.fleet import Fleet
    from ccrp_cli.providers import get_provider

    inv = tmp_path / "ccrp.yaml"
    inv.write_text(INVENTORY)
    code, out, err = ccrp(monkeypatch, capsys, "fleet", "validate", "-i", str(inv))
    assert code == 0, err
    assert "2 robots" in err and "cri-r2" in out
    # A clone made by the backend's provider (as `fleet up` would) is in the plan; the other is to create.
    fleet = Fleet.open(inv)
    provider = get_provider(fleet.inventory)
    provider.bootstrap()
    memory.add("image", "base", {})
    spec = {"hostname": "cri-r1", "image": "base", "user_data": "#cloud-config\n", "instance_id": "mem-r1-1",
            "common_ip": "10.90.0.10"}
    from ccrp_cli.providers.base import CloneSpec

    made = provider.run_instance(CloneSpec(robot="r1", **spec))
    code, out, err = ccrp(monkeypatch, capsys, "fleet", "plan", "-i", str(inv), "--json")
    assert code == 0, err
    rows = {r["robot"]: r for r in json.loads(out)}
    assert rows["r1"]["action"] == "configure" and rows["r1"]["provider_id"] == made.provider_id
    assert rows["r2"]["action"] == "create"
    code, out, err = ccrp(monkeypatch, capsys, "fleet", "plan", "-i", str(inv))
    assert code == 0, err
    assert "instances" in out and "memory cloud" in out  # the backend's quota, read through Housekeeping


def test_a_command_closes_the_providers_it_opened_whichever_way_it_ends(memory, ccrp_home, tmp_path, monkeypatch,
                                                                       capsys):
    from tests.memory_backend.provider import MemoryProvider

    closed: list[MemoryProvider] = []
    monkeypatch.setattr(MemoryProvider, "close", lambda self: closed.append(self))
    inv = tmp_path / "ccrp.yaml"
    inv.write_text(INVENTORY)
    code, _, err = ccrp(monkeypatch, capsys, "fleet", "plan", "-i", str(inv))
    assert code == 0, err
    assert len(closed) == 1
    # A command that fails after it opened its provider closes it too.
    monkeypatch.setattr(MemoryProvider, "query", lambda self: (_ for _ in ()).throw(CcrpError("the cloud is down")))
    code, _, err = ccrp(monkeypatch, capsys, "fleet", "plan", "-i", str(inv))
    assert code == 1 and "the cloud is down" in err
    assert len(closed) == 2


def test_without_its_line_the_backend_is_refused(ccrp_home, tmp_path, monkeypatch, capsys):
    assert "memory" not in REGISTRY
    inv = tmp_path / "ccrp.yaml"
    inv.write_text(INVENTORY)
    code, _, err = ccrp(monkeypatch, capsys, "fleet", "validate", "-i", str(inv))
    assert code == 2 and "memory" in err and len(err.strip().splitlines()) == 1


def _docstrings(tree: ast.AST) -> set[int]:
    return {id(node.body[0].value) for node in ast.walk(tree)
            if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body
            and isinstance(node.body[0], ast.Expr) and isinstance(node.body[0].value, ast.Constant)}


def test_the_core_names_no_backend_kind_but_the_listed_ones():
    """No string of the core (a message, a default, an f-string's text) names a backend's kind as a
    word, but those NAMES_A_KIND lists."""
    kinds = set(REGISTRY)
    word = re.compile(r"\b(?:" + "|".join(sorted(kinds)) + r")\b")
    found: dict[str, int] = {}
    for path in sorted((ROOT / "ccrp_cli").rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        parts = rel.split("/")
        if rel == "ccrp_cli/providers/registry.py" or (parts[1] == "providers" and parts[2] in kinds):
            continue
        tree = ast.parse(path.read_text())
        docs = _docstrings(tree)
        n = sum(isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docs
                and bool(word.search(node.value)) for node in ast.walk(tree))
        if n:
            found[rel] = n
    assert found == NAMES_A_KIND, ("a string of the core names a backend's kind: declare it in ProviderInfo "
                                   "or take it from the registry instead, or list it above with its reason")


def test_every_backend_is_protected_and_in_the_contract_suite():
    """The other places docs/architecture.md says a new backend touches."""
    import tomllib

    from tests.contract.conftest import KINDS, VARIANTS

    contracts = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    backends = next(c for c in contracts if c["id"] == "backends")
    assert set(backends["protected_modules"]) == {f"ccrp_cli.providers.{kind}" for kind in REGISTRY}
    # memory registers itself (a test-only backend).
    assert set(KINDS) == set(REGISTRY) | {"memory"}
    assert all((ROOT / "tests" / "contract" / f"harness_{kind}.py").exists() for kind in KINDS)
    assert set(VARIANTS.values()) <= set(KINDS)  # a variant runs an existing backend's provider

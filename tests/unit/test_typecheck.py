"""The type check of the provider seam ([tool.mypy] in pyproject.toml, docs/architecture.md "The
type check"): mypy over the protocols (providers/base.py), each backend's provider.py, ops/ and
services/, and tests/typecheck/backends.py, where each backend is asserted to satisfy its protocols."""

from __future__ import annotations

import ast
import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

from ccrp_cli.providers import REGISTRY
from ccrp_cli.providers.base import Ability

ROOT = Path(__file__).resolve().parents[2]
BACKENDS = ROOT / "tests" / "typecheck" / "backends.py"
# The protocol of providers/base.py each ability adds to Provider.
ABILITY_PROTOCOLS = {Ability.LOCAL_BUILD: "LocalBuild", Ability.BAKE: "Bake", Ability.ROBOT_ATTACH: "RobotAttach",
                     Ability.HOST_IMAGES: "HostImages", Ability.ENTRY_GATEWAY: "Gateways"}

# The mypy runs share its cache (.mypy_cache): on one worker, one after the other.
pytestmark = pytest.mark.xdist_group("mypy")
needs_mypy = pytest.mark.skipif(importlib.util.find_spec("mypy") is None,
                                reason="mypy is not installed (the dev extra: pip install -e '.[dev]')")


def mypy(*args: str) -> tuple[int, str]:
    """mypy with the project's configuration (pyproject.toml), from the tree's root: its exit code
    and what it printed. Its cache (.mypy_cache, ignored by git) makes a run after the first quick."""
    proc = subprocess.run([sys.executable, "-m", "mypy", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=600)
    return proc.returncode, proc.stdout + proc.stderr


@needs_mypy
def test_the_seam_type_checks():
    rc, out = mypy()
    assert rc == 0, f"mypy (pyproject.toml [tool.mypy]) found errors:\n{out}"


@needs_mypy
def test_a_backend_that_drifts_from_its_protocol_fails_the_check(tmp_path):
    """What the check reports when a backend's method no longer matches the protocol: the
    backend, the protocol and the member."""
    drifted = tmp_path / "drifted.py"
    drifted.write_text("from ccrp_cli.providers.base import Images, SnapshotRecord\n"
                       "class Drifted:\n"
                       "    def create_snapshot(self, robot: str) -> SnapshotRecord: ...\n"  # its name dropped
                       "    def list_snapshots(self) -> list[SnapshotRecord]: ...\n"
                       "    def delete_snapshot(self, snapshot_id: str) -> None: ...\n"
                       "    def has_image(self, image: str) -> bool: ...\n"
                       "    def resolve_image(self, image: str) -> str: ...\n"
                       "def drifted(backend: Drifted) -> None:\n"
                       "    images: Images = backend\n")
    rc, out = mypy(str(drifted))
    assert rc == 1, out
    assert 'expression has type "Drifted", variable has type "Images"' in out, out
    assert "def create_snapshot(self, robot: str, name: str) -> SnapshotRecord" in out, out


def test_every_backend_is_asserted_to_satisfy_its_protocols():
    """tests/typecheck/backends.py has one function per registered backend, taking its provider class
    and assigning it to Provider and to the protocol of each ability it declares: a new backend or
    a new ability cannot be left out of the type check."""
    asserted: dict[str, tuple[str, set[str]]] = {}
    for fn in ast.parse(BACKENDS.read_text()).body:
        if isinstance(fn, ast.FunctionDef) and fn.name in REGISTRY:
            cls = ast.unparse(fn.args.args[0].annotation)
            protocols = {ast.unparse(s.annotation) for s in fn.body if isinstance(s, ast.AnnAssign)}
            asserted[fn.name] = (cls, protocols)
    for kind, info in REGISTRY.items():
        assert kind in asserted, f"{BACKENDS.name}: no function for backend {kind}"
        cls, protocols = asserted[kind]
        assert cls == info.factory.rsplit(":", 1)[1], f"{BACKENDS.name}: {kind}() takes {cls}, not {info.factory}"
        want = {"Provider"} | {ABILITY_PROTOCOLS[a] for a in info.abilities}
        assert protocols == want, f"{BACKENDS.name}: {kind}() asserts {sorted(protocols)}, its protocols are {sorted(want)}"

"""The import contract ([tool.importlinter] in pyproject.toml, docs/architecture.md "Who imports
whom"): import-linter checks it over ccrp_cli's import graph, function-local imports included."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

from ccrp_cli.models import layout
from ccrp_cli.agent import autostop, health

ROOT = Path(__file__).resolve().parents[2]
# The venv's own lint-imports, beside its python.
LINT_IMPORTS = Path(sys.executable).parent / "lint-imports"


def lint(config: Path) -> tuple[int, list[str], str]:
    """lint-imports on `config` over this tree's ccrp_cli: its exit code, the names of the broken
    contracts, and what it printed."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
           "COLUMNS": "500"}  # one line per contract, whatever the terminal
    proc = subprocess.run([str(LINT_IMPORTS), "--no-cache", str(config)], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=120)
    out = proc.stdout + proc.stderr
    return proc.returncode, re.findall(r"^(.+) BROKEN$", out, re.MULTILINE), out


def test_the_import_contract_holds():
    contracts = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    rc, broken, out = lint(ROOT / "pyproject.toml")
    assert not broken, f"broken import contracts: {'; '.join(broken)}\n{out}"
    assert rc == 0, out
    # Every contract was checked (a config import-linter reads differently would check none).
    kept = re.findall(r"^(.+) KEPT", out, re.MULTILINE)
    assert sorted(kept) == sorted(c["name"] for c in contracts), out
    assert {c["id"] for c in contracts} >= {"agents", "providers", "backends", "layers", "acyclic"}


def test_a_broken_contract_fails_naming_it(tmp_path):
    """What the test above reports when the code breaks a contract: here the CLI imports
    errors.py, which a contract forbids."""
    config = tmp_path / "contract.toml"
    config.write_text('[tool.importlinter]\nroot_package = "ccrp_cli"\n\n[[tool.importlinter.contracts]]\n'
                      'name = "the cli imports no errors"\ntype = "forbidden"\n'
                      'source_modules = ["ccrp_cli.cli"]\nforbidden_modules = ["ccrp_cli.errors"]\n')
    rc, broken, out = lint(config)
    assert rc != 0 and broken == ["the cli imports no errors"], out
    assert "ccrp_cli.cli.main -> ccrp_cli.errors" in out


def test_a_known_violation_that_went_away_fails_too(tmp_path):
    """An ignore_imports line that matches no import is an error, so the list of known violations
    shrinks as they are fixed instead of hiding new ones."""
    config = tmp_path / "contract.toml"
    config.write_text('[tool.importlinter]\nroot_package = "ccrp_cli"\n\n[[tool.importlinter.contracts]]\n'
                      'name = "agents alone"\ntype = "forbidden"\n'
                      'source_modules = ["ccrp_cli.agent"]\nforbidden_modules = ["ccrp_cli.*"]\n'
                      'ignore_imports = ["ccrp_cli.agent.relay -> ccrp_cli.errors"]\n')
    rc, _, out = lint(config)
    assert rc != 0 and "ccrp_cli.agent.relay -> ccrp_cli.errors" in out, out


def test_the_agents_copies_of_the_layout_match_it():
    """Agents are standalone files on the clone: they keep their own copies of what layout.py says."""
    assert autostop.NOTE == layout.AUTOSTOP_NOTE
    assert autostop.BOOT_LINE == layout.AUTOSTOP_BOOT_LINE
    assert health.MGMT == layout.MGMT_SOCKET
    assert autostop.STATUS.startswith(layout.VPN_DIR + "/")

"""Is a node's program on its clone? (docs/workloads.md, ROS habits)

A `run` command that names a program the clone image lacks crash-loops at boot (`rosrun: not
found`). Its first word is judged here, before anything is built or changed, against what the
snapshot holds: the recipe platform's packages, what they bring (`implied`), the fleet's apt
packages and those the workspace's package.xml files resolve to, and the workspace's own console
scripts. What is known comes from the recipe (snapshots/<distro>.yaml `programs:`, `refused:`).

Only what cannot work is refused: a program the recipe knows whose package the image lacks, or one
the platform has not at all (`ros2` on the wheels). A path (`/opt/ccrp/workspace/lib/...`) is left
to run, and a bare name known nowhere is a warning: ccrp cannot list every program of the Debian
packages and wheels the fleet adds, and `fleet up` would show such a node failing within 3 s.
"""

from __future__ import annotations

import ast
import configparser
import re
from collections.abc import Iterator

from ..errors import InputError, shown
from ..models.inventory import Inventory
from ..models.software import RunNode
from ..recipes import platform

# An entry point as setup.py/setup.cfg write it: "name = package.module:function".
_ENTRY = re.compile(r"^\s*([A-Za-z0-9_.+-]+)\s*=\s*[A-Za-z_][\w.]*(\s*:\s*[\w.]+)?\s*$")


def console_scripts(files: list[tuple[str, bytes]]) -> set[str]:
    """The console scripts the workspace's Python packages install (on a node's PATH): every string
    of setup.py that reads as an entry point, and setup.cfg's [options.entry_points]. Read, never run;
    too many names only spare a warning, too few would not refuse anything (a warning too)."""
    names: set[str] = set()
    for rel, data in files:
        base = rel.rsplit("/", 1)[-1]
        if base == "setup.py":
            try:
                tree = ast.parse(data.decode("utf-8", "replace"))
            except SyntaxError:
                continue
            texts = [n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)]
        elif base == "setup.cfg":
            cfg = configparser.ConfigParser(interpolation=None)
            try:
                cfg.read_string(data.decode("utf-8", "replace"))
            except configparser.Error:
                continue
            texts = cfg.get("options.entry_points", "console_scripts", fallback="").splitlines()
        else:
            continue
        names.update(m.group(1) for m in map(_ENTRY.match, texts) if m)
    return names


def _nodes(inv: Inventory) -> Iterator[tuple[str, RunNode]]:
    """Every `run` entry of every level, with where the inventory gives it."""
    levels = [("software", inv.software),
              *((f"types.{name}.software", t.software) for name, t in inv.types.items()),
              *((f"robots[{r.name}].software", r.software) for r in inv.robots),
              ("template.software", inv.template.software if inv.template else None)]
    for where, software in levels:
        for node in software.run if software else []:
            yield f"{where}.run {node.name}", node


def check(inv: Inventory, apt: list[str], workspace: list[tuple[str, bytes]]) -> list[str]:
    """Refuse (InputError, one line) a node whose program the clone cannot have; return a warning
    per bare name known nowhere. `apt`: the snapshot's Debian packages (software.apt and what the
    workspace resolves to); `workspace`: its source files."""
    plat = platform(inv.ros.distro, inv.clone_platform)
    has = {*plat.packages, *plat.implied, *apt}
    scripts: set[str] | None = None
    warnings = []
    for where, node in _nodes(inv):
        program = node.command[0]
        package = plat.programs.get(program)
        if "/" in program or package in has:  # a path (left to run), or a program the image has
            continue
        scripts = console_scripts(workspace) if scripts is None else scripts
        if program in scripts:
            continue
        if program in plat.refused:
            raise InputError(f"{where}: {shown(program)}: {plat.refused[program]}")
        if package is not None:
            raise InputError(f"{where}: {shown(program)} is not on the clone: Debian's package {package} has it",
                             hint=f"add {package} to software.apt, then ccrp snapshot build")
        if program not in has:  # a package named as its program (htop) is taken for it
            warnings.append(f"{where}: {shown(program)} is no program ccrp knows on the clone (ROS {inv.ros.distro}, "
                            f"{inv.clone_platform}): unless a package of software.apt or pip installs it, the node "
                            "will not start; add its Debian package to software.apt, or give its path")
    return warnings

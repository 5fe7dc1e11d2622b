"""Read a scenario's YAML text into plain data, refusing what could hang or exhaust memory.

``yaml.SafeLoader`` builds only plain data (no code), but it still accepts three shapes that
cost far more than the file's size: a huge file; nested aliases (the "billion laughs" file, where
a 1.6 KB text expands to ~10^9 nodes as soon as anything walks it); and an anchor whose alias sits
inside its own node (an infinite, self-referencing value). ``load_yaml`` refuses all three before
anything walks the data, and a key repeated in one mapping (PyYAML silently keeps the last).
Every refusal is one ``ScenarioError`` naming the file, the place and the limit.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml

from pipeline.io.errors import ScenarioError
from pipeline.io.files import FileRefused, FileTooLarge, read_bytes

MAX_BYTES = 1_000_000  # a scenario file is a few KB; demos live in their own CSV files
# (read as a regular file only: a FIFO or device is refused, pipeline.io.files.read_bytes)
MAX_ALIASES = 100  # '*name' references in one file
MAX_NODES = 100_000  # YAML nodes after expanding every alias (the shipped files: < 500)


class _UniqueKeys:
    """Refuses a key repeated in one mapping (a constructor mixin for both loaders)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        first_line: dict[object, int] = {}
        for key_node, _ in node.value:
            if not isinstance(key_node, yaml.ScalarNode) or key_node.tag.endswith(":merge"):
                continue
            key = self.construct_object(key_node)  # type: ignore[attr-defined]
            if key in first_line:
                raise yaml.constructor.ConstructorError(
                    problem=f"duplicate key '{key}' (first at line {first_line[key]})",
                    problem_mark=key_node.start_mark,
                )
            first_line[key] = key_node.start_mark.line + 1
        return super().construct_mapping(node, deep=deep)  # type: ignore[misc]


class _ScenarioLoader(_UniqueKeys, yaml.SafeLoader):
    """``yaml.SafeLoader`` that counts aliases while composing and refuses a key repeated in one
    mapping: the reference, whose errors are the ones reported."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self.aliases = 0

    def compose_node(self, parent: yaml.Node | None, index: object) -> yaml.Node:  # type: ignore[override]
        if self.check_event(yaml.AliasEvent):
            self.aliases += 1
            if self.aliases > MAX_ALIASES:
                raise yaml.composer.ComposerError(
                    problem=f"more than {MAX_ALIASES} aliases ('*name' references)",
                    problem_mark=self.peek_event().start_mark,
                )
        return super().compose_node(parent, index)  # type: ignore[arg-type]


_LIBYAML = getattr(yaml, "CSafeLoader", None)  # PyYAML built with libyaml (the wheels are)
# libyaml's parser, the same constructor with the duplicate-key check
_FAST_LOADER: Any = None if _LIBYAML is None else type("_FastLoader", (_UniqueKeys, _LIBYAML), {})

# A number in exponent form without a dot (1e6, 5E-3) is a float, as in YAML 1.2; YAML 1.1, which
# PyYAML reads, makes it text, which the schema refuses where a number belongs.
EXPONENT = re.compile(r"^[-+]?[0-9][0-9_]*(?:\.[0-9_]*)?[eE][-+]?[0-9]+$")
for _loader in (_ScenarioLoader, _FAST_LOADER):
    if _loader is not None:  # a copy of the resolvers per class: yaml.SafeLoader is left alone
        _loader.add_implicit_resolver("tag:yaml.org,2002:float", EXPONENT, list("-+0123456789"))


def _compose_with_libyaml(text: str) -> tuple[yaml.Node | None, Any] | None:
    """``(node, loader)`` composed by libyaml (~10x faster than the pure-Python composer), or
    None where the reference loader must decide: no libyaml, a tab anywhere (libyaml accepts
    tabs where PyYAML refuses them), a document libyaml refuses, or more than ``MAX_ALIASES``
    aliases (counted as the extra references to anchored nodes)."""
    if _FAST_LOADER is None or "\t" in text:
        return None
    loader = _FAST_LOADER(text)
    try:
        node = loader.get_single_node()
    except (yaml.YAMLError, RecursionError):
        return None
    if node is not None and _aliases(node) > MAX_ALIASES:
        return None
    return node, loader


def _aliases(root: yaml.Node) -> int:
    """How many alias references the composed ``root`` holds: references to nodes beyond the
    first one of each (an alias is a second reference to its anchor's node)."""
    seen = {id(root)}
    references, pending = 0, [root]
    while pending:
        for child in _children(pending.pop()):
            references += 1
            if id(child) not in seen:
                seen.add(id(child))
                pending.append(child)
    return references - (len(seen) - 1)


def expanded_size(root: yaml.Node, limit: int = MAX_NODES) -> int:
    """Number of nodes of ``root`` with every alias expanded, counting up to just above
    ``limit``; raises ``ValueError`` if a node contains itself (a self-referencing anchor).

    Iterative and memoised per node, so the cost is the number of distinct nodes, not the
    expanded size.
    """
    size: dict[int, int] = {}
    open_nodes: set[int] = set()
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]
    while stack:
        node, children_done = stack.pop()
        key = id(node)
        if children_done:
            open_nodes.discard(key)
            total = 1 + sum(size[id(child)] for child in _children(node))
            size[key] = min(total, limit + 1)
            continue
        if key in size:
            continue
        if key in open_nodes:
            raise ValueError(f"the node at line {node.start_mark.line + 1} contains itself")
        open_nodes.add(key)
        stack.append((node, True))
        for child in _children(node):
            if id(child) in open_nodes:
                raise ValueError(f"the node at line {child.start_mark.line + 1} contains itself")
            if id(child) not in size:
                stack.append((child, False))
    return size[id(root)]


def _children(node: yaml.Node) -> list[yaml.Node]:
    if isinstance(node, yaml.SequenceNode):
        return list(node.value)
    if isinstance(node, yaml.MappingNode):
        return [part for pair in node.value for part in pair]
    return []


def load_yaml(path: Path) -> object:
    """The data of the YAML file ``path`` (plain dicts, lists, strings and numbers), or a
    ``ScenarioError`` for an unreadable, oversized, malformed or alias-bomb file."""
    try:
        raw = read_bytes(path, MAX_BYTES)
    except FileTooLarge:
        raise ScenarioError(
            f"file is larger than {MAX_BYTES:,} bytes",
            file=path,
            expected="a scenario file of a few KB (demonstrations belong in their CSV files)",
        ) from None
    except (OSError, FileRefused) as error:
        reason = error.strerror if isinstance(error, OSError) else error.reason
        raise ScenarioError(
            f"cannot read scenario file ({reason})",
            file=path,
            expected="a readable YAML file",
        ) from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise ScenarioError(
            "cannot read scenario file (not UTF-8 text)",
            file=path,
            expected="a readable YAML file",
        ) from None
    fast = _compose_with_libyaml(text)
    loader: Any = _ScenarioLoader(text) if fast is None else fast[1]
    try:
        node = loader.get_single_node() if fast is None else fast[0]
        if node is None:
            return None
        try:
            nodes = expanded_size(node)
        except ValueError as error:
            raise ScenarioError(
                f"self-referencing alias: {error}",
                file=path,
                expected="aliases ('*name') only to anchors defined before, outside the value",
            ) from None
        if nodes > MAX_NODES:
            raise ScenarioError(
                f"aliases expand to more than {MAX_NODES:,} YAML nodes",
                file=path,
                expected="a scenario without nested aliases (write the values out)",
            )
        return loader.construct_document(node)
    except yaml.MarkedYAMLError as error:
        mark = error.problem_mark
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark else "unknown place"
        raise ScenarioError(f"YAML syntax error at {where}: {error.problem}", file=path) from None
    except yaml.YAMLError as error:
        raise ScenarioError(f"YAML syntax error: {error}", file=path) from None
    except RecursionError:
        raise ScenarioError(
            "YAML is nested too deeply", file=path, expected="a scenario mapping"
        ) from None
    finally:
        loader.dispose()

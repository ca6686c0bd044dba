"""YAML in: the strict loader (no aliases, no duplicate keys, bounded depth), the bounded file
reader shared with sweep files and claims files, a run config file read into flat keys, and
``a.b=value`` overrides.
"""

from __future__ import annotations

import typing
from pathlib import Path
from typing import Any

import yaml

from spot import SpotError
from spot.config.keys import check_keys


def flatten_yaml(data: Any, where: str, prefix: str = "") -> dict[str, Any]:
    """Nested mappings as flat dotted keys (``{iql: {steps: 1}}`` -> ``{"iql.steps": 1}``); also for
    sweep files (:mod:`spot.sweep.spec`), whose base/grid/zip blocks follow the same rules."""
    if not isinstance(data, dict):
        raise SpotError(f"{where}: expected a mapping of config keys, got {type(data).__name__}")
    flat: dict[str, Any] = {}
    for k, v in data.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            flat.update(flatten_yaml(v, where, key + "."))
        else:
            flat[key] = v
    return flat


MAX_YAML_BYTES = 1 << 20
"""Largest YAML file (run config, sweep file) spot reads."""


MAX_YAML_DEPTH = 16
"""Deepest nesting of mappings and lists in a YAML file or override value (a sweep file's
``smoke: {grid: {iql: {hidden: [[64, 64]]}}}`` is 6 deep, its root mapping included). PyYAML
composes nodes recursively, so a 10,000-deep ``[[[...]]]`` (20 KB) would end in a RecursionError."""


class TooDeep(yaml.composer.ComposerError):
    """A YAML document nested deeper than :data:`MAX_YAML_DEPTH`."""


class StrictLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses aliases (``*name``: an alias bomb expands a few lines into
    billions of keys), duplicate mapping keys (PyYAML silently keeps the last one) and nesting
    deeper than :data:`MAX_YAML_DEPTH`."""

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.composer.ComposerError(
                None,
                None,
                f"alias '*{event.anchor}' found: spot's YAML files take no aliases; write the value out",
                event.start_mark,
            )
        if not self.check_event(yaml.MappingStartEvent, yaml.SequenceStartEvent):
            return super().compose_node(parent, index)  # a scalar: no deeper
        depth = getattr(self, "_depth", 0)
        if depth >= MAX_YAML_DEPTH:
            raise TooDeep(
                None,
                None,
                f"nested deeper than {MAX_YAML_DEPTH} levels; expected at most {MAX_YAML_DEPTH}",
                self.peek_event().start_mark,
            )
        self._depth = depth + 1
        try:
            return super().compose_node(parent, index)
        finally:
            self._depth = depth

    def construct_mapping(self, node: Any, deep: bool = False) -> Any:
        if isinstance(node, yaml.MappingNode):
            seen: set[Any] = set()
            for key_node, _ in node.value:
                key = self.construct_object(key_node, deep=True)
                if isinstance(key, typing.Hashable):
                    if key in seen:
                        raise yaml.constructor.ConstructorError(
                            None, None, f"duplicate key {key!r}", key_node.start_mark
                        )
                    seen.add(key)
        return super().construct_mapping(node, deep=deep)


def read_yaml(path: str | Path, where: str) -> Any:
    """Parse a YAML file with :class:`StrictLoader`: at most :data:`MAX_YAML_BYTES`, UTF-8, no
    aliases, no duplicate keys. Raises SpotError starting with ``where`` (e.g. ``config file 'x'``)."""
    path = Path(path)
    if not path.is_file():
        raise SpotError(f"{where} does not exist")
    size = path.stat().st_size
    if size > MAX_YAML_BYTES:
        raise SpotError(f"{where}: {size} bytes; expected a YAML file of at most {MAX_YAML_BYTES} bytes")
    try:
        with path.open("rb") as fh:
            raw = fh.read(MAX_YAML_BYTES + 1)  # bounded: the file may grow after the stat
        if len(raw) > MAX_YAML_BYTES:
            raise SpotError(f"{where}: grew past {MAX_YAML_BYTES} bytes while read; expected a YAML file at most that")
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise SpotError(f"{where}: not UTF-8 text (byte {e.start}); save it as UTF-8") from None
    except OSError as e:
        raise SpotError(f"{where}: cannot be read ({e.strerror})") from None
    try:
        return yaml.load(text, Loader=StrictLoader)  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as e:
        raise SpotError(f"{where}: not valid YAML: {yaml_problem(e)}") from None
    except ValueError as e:  # PyYAML's int(): an integer of more than 4300 digits
        raise SpotError(f"{where}: not valid YAML: {str(e).split(';')[0]}") from None


def yaml_problem(error: yaml.YAMLError) -> str:
    """A PyYAML error on one line: the problem and where (PyYAML's own text quotes the source)."""
    problem = getattr(error, "problem", None) or str(error).splitlines()[0]
    context = getattr(error, "context", None)
    mark = getattr(error, "problem_mark", None)
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    return f"{context + ': ' if context else ''}{problem}{where}"


def load_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML run config into a flat dict (keys checked, values not yet coerced)."""
    path = Path(path)
    data = read_yaml(path, f"config file '{path}'") or {}
    return check_keys(flatten_yaml(data, f"config file '{path}'"), f"config file '{path}'")


def parse_overrides(items: list[str] | tuple[str, ...]) -> dict[str, Any]:
    """``["iql.steps=1000", "method=pt"]`` -> flat dict (values parsed as YAML scalars)."""
    flat: dict[str, Any] = {}
    for item in items:
        if "=" not in item:
            raise SpotError(f"override '{item}': expected KEY=VALUE, e.g. iql.steps=1000")
        key, text = item.split("=", 1)
        try:
            value = yaml.load(text, Loader=StrictLoader) if text.strip() else ""  # noqa: S506
        except TooDeep as e:
            raise SpotError(f"override '{key.strip()}': value {yaml_problem(e)}") from None
        except (yaml.YAMLError, ValueError):  # ValueError: an integer of more than 4300 digits
            value = text
        flat[key.strip()] = value if value is not None else ""
    return check_keys(flat, "override")

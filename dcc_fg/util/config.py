"""Options dataclasses <-> YAML: one configuration mechanism for every command.

A command's configuration is a dataclass whose fields are *sections*, each itself a dataclass of
plain options (numbers, strings, booleans, tuples of numbers, ``None``). The same object is

* written as YAML by ``dcc-fg config --print COMMAND`` (the defaults) and recorded in every
  ``summary.json`` (the effective options of a run);
* read from a YAML file by ``--config FILE`` (any subset of sections and keys; the rest keep their
  defaults) and then overridden by the command-line flags the user gave.

Unknown sections or keys and values of the wrong type are refused with the file and key named,
before any work starts. Units are those of the field names and docstrings of each options class.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import yaml

T = TypeVar("T")


class ConfigError(ValueError):
    """A configuration file or value is invalid (the message names the file and key)."""


def to_plain(obj: Any, nonfinite_as_none: bool = False) -> Any:
    """Dataclasses, numpy values, tuples and paths as plain YAML/JSON values (dicts, lists, floats).

    ``nonfinite_as_none`` turns NaN and infinities into None (JSON has no NaN).
    """
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_plain(getattr(obj, f.name), nonfinite_as_none) for f in dataclasses.fields(obj)}
    if isinstance(obj, Mapping):
        return {str(k): to_plain(v, nonfinite_as_none) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_plain(v, nonfinite_as_none) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_plain(obj.tolist(), nonfinite_as_none)
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, Path):
        return str(obj)
    if nonfinite_as_none and isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def _allows_none(tp: Any) -> bool:
    return typing.get_origin(tp) in (typing.Union, types.UnionType) and type(None) in typing.get_args(tp)


def _non_none(tp: Any) -> Any:
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return args[0] if len(args) == 1 else tp
    return tp


def _convert(value: Any, tp: Any, where: str) -> Any:
    """``value`` (from YAML or a flag) converted to the annotated type ``tp`` or a ConfigError."""
    if value is None:
        if _allows_none(tp) or tp is Any:
            return None
        raise ConfigError(f"{where}: must not be empty (null)")
    tp = _non_none(tp)
    origin = typing.get_origin(tp)
    if tp is Any:
        return value
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{where}: expected true or false, got {value!r}")
    if tp in (int, float):
        if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        if not np.isfinite(float(value)):
            raise ConfigError(f"{where}: expected a finite number, got {value!r}")
        if tp is int:
            if float(value) != int(value):
                raise ConfigError(f"{where}: expected an integer, got {value!r}")
            return int(value)
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        args = typing.get_args(tp)
        item = args[0] if args else Any
        return tuple(_convert(v, item, f"{where}[{i}]") for i, v in enumerate(value))
    if origin is dict:
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}: expected a mapping, got {value!r}")
        return dict(value)
    if origin is typing.Literal:
        if value not in typing.get_args(tp):
            raise ConfigError(f"{where}: expected one of {list(typing.get_args(tp))}, got {value!r}")
        return value
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}: expected a mapping of options, got {value!r}")
        return from_dict(tp, value, where)
    return value


def from_dict(cls: type[T], data: Mapping[str, Any], where: str = "<config>", base: T | None = None) -> T:
    """Build the dataclass ``cls`` from ``data``; keys not given keep ``base``'s (or the defaults).

    ``where`` prefixes every error message (e.g. the file name). Nested dataclass fields take
    nested mappings. The dataclass's own ``__post_init__`` checks (ranges, choices) apply.
    """
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where}: expected a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]  # type: ignore[arg-type]
    unknown = sorted(set(data) - set(names))
    if unknown:
        raise ConfigError(f"{where}: unknown option(s) {', '.join(map(str, unknown))}; known: {', '.join(names)}")
    start = base if base is not None else cls()
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        current = getattr(start, name)
        if dataclasses.is_dataclass(current) and isinstance(value, Mapping):
            kwargs[name] = from_dict(type(current), value, f"{where}.{name}", current)
        else:
            kwargs[name] = _convert(value, hints[name], f"{where}.{name}")
    try:
        return dataclasses.replace(start, **kwargs)  # type: ignore[type-var]
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"{where}: {exc}") from exc


def load_yaml_config(path: str | Path, cls: type[T], command: str) -> T:
    """Read a ``--config`` YAML file for ``command`` into ``cls`` (defaults for what it leaves out).

    The file may carry ``command: NAME`` (as ``dcc-fg config --print`` writes it); a file for another
    command is refused. It may also be a ``summary.json`` of an earlier run, whose ``options`` are used.
    """
    p = Path(path)
    if p.is_dir():
        raise ConfigError(f"{p}: is a folder; expected a configuration YAML file (dcc-fg config --print {command})")
    if not p.is_file():
        raise FileNotFoundError(f"{p}: configuration file not found")
    try:
        data = yaml.safe_load(p.read_bytes().decode("utf-8")) or {}
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"{p}: not a text file (byte offset {exc.start} is not UTF-8); expected a YAML file"
        ) from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{p}: malformed YAML: {' '.join(str(exc).split())}") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"{p}: expected a mapping of sections")
    if "dcc_fg_version" in data:  # a summary.json of an earlier run
        if not isinstance(data.get("options"), dict):
            raise ConfigError(f"{p}: a summary.json without 'options' (written by a dcc-fg older than 0.1.0?)")
        data = {"command": data.get("command", command), **data["options"]}
    named = data.pop("command", command)
    if named != command:
        raise ConfigError(f"{p}: is a configuration for 'dcc-fg {named}', not 'dcc-fg {command}'")
    return from_dict(cls, data, str(p))


def apply_overrides(config: T, overrides: Mapping[str, Any], where: str = "command line") -> T:
    """``config`` with ``{"section.key": value}`` overrides (the flags the user gave) applied."""
    nested: dict[str, dict[str, Any]] = {}
    for dotted, value in overrides.items():
        section, key = dotted.split(".", 1)
        nested.setdefault(section, {})[key] = to_plain(value)
    return from_dict(type(config), nested, where, config)


class _ConfigDumper(yaml.SafeDumper):
    """Block style for sections, flow style (``[a, b]``) for lists of numbers."""


_ConfigDumper.add_representer(
    list, lambda dumper, data: dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=True)
)


def dump_yaml(config: Any, command: str, header: str = "") -> str:
    """YAML text of ``config`` with ``command:`` first, loadable by :func:`load_yaml_config`."""
    body = yaml.dump(
        {"command": command, **to_plain(config)}, Dumper=_ConfigDumper, sort_keys=False, default_flow_style=False
    )
    lines = [f"# {line}" if line else "#" for line in header.splitlines()]
    return "\n".join(lines + [body]) if lines else body

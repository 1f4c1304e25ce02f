"""Reading YAML into the config dataclasses: a file's content, and a (nested) frozen dataclass built
from a mapping, every key and value checked and named when wrong."""

from __future__ import annotations

import dataclasses
import enum
import math
from pathlib import Path
from typing import Any

import yaml

from .errors import ConfigError


def read_yaml_file(path, what: str = "config file") -> Any:
    """A YAML (or JSON) file's content, or a ConfigError naming the file when it is missing, not text
    (binary junk) or not YAML."""
    path = Path(path)
    try:
        return yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such {what}") from None
    except (UnicodeDecodeError, IsADirectoryError):
        raise ConfigError(f"{path}: not a text file (a YAML {what} was expected)") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from None


# an optional field: a value other than null converts as this default would
_OPTIONAL_KINDS = {"float | None": 0.0, "int | None": 0, "str | None": ""}


def convert_value(cls, name: str, value: Any, source: str) -> Any:
    """``value`` read from YAML as field ``name`` of dataclass ``cls`` (an enum member, a whole number, a
    tuple, ...), or a ConfigError naming ``source``, the key and the value."""
    ftype = {f.name: f.type for f in dataclasses.fields(cls)}[name]
    default = {f.name: f.default for f in dataclasses.fields(cls)}[name]
    if isinstance(value, float) and not math.isfinite(value):
        raise ConfigError(f"{source}: {name} = {value!r} must be a finite number")
    if str(ftype) in _OPTIONAL_KINDS:
        if value is None:
            return None
        default = _OPTIONAL_KINDS[str(ftype)]
    try:
        if isinstance(default, enum.Enum):
            return type(default)(value)
        if isinstance(default, bool):
            if not isinstance(value, bool):
                raise TypeError
            return value
        if isinstance(default, int):
            if isinstance(value, bool) or int(value) != value:
                raise TypeError
            return int(value)
        if isinstance(default, float):
            if isinstance(value, bool):
                raise TypeError
            return float(value)
        if isinstance(default, tuple):
            items = tuple(value) if isinstance(value, (list, tuple)) else (value,)
            if any(isinstance(item, (dict, list, tuple)) for item in items):
                raise TypeError
            if str(ftype) == "tuple[str, ...]" and not all(isinstance(item, str) for item in items):  # paths, logs, names
                raise TypeError
            return items
        if isinstance(default, str):
            if not isinstance(value, str):
                raise TypeError
            return value
        return value
    except (TypeError, ValueError):
        allowed = f" (one of {', '.join(m.value for m in type(default))})" if isinstance(default, enum.Enum) else ""
        raise ConfigError(f"{source}: {name} = {value!r} is not a valid {ftype}{allowed}") from None


def dataclass_from_dict(cls, data: Any, source: str):
    """Build a (possibly nested) frozen dataclass from a YAML mapping: unknown keys and wrongly typed
    values raise a ConfigError naming ``source`` and the dotted key; missing keys keep the defaults."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    not_names = [k for k in data if not isinstance(k, str)]
    if not_names:
        raise ConfigError(f"{source}: key {not_names[0]!r} is not a name (a {type(not_names[0]).__name__})")
    unknown = set(data) - set(fields)
    if unknown:
        raise ConfigError(f"{source}: unknown key(s) {sorted(unknown)}; known: {sorted(fields)}")
    values = {}
    for name, value in data.items():
        default = fields[name].default
        if default is dataclasses.MISSING and fields[name].default_factory is not dataclasses.MISSING:
            default = fields[name].default_factory()
        if dataclasses.is_dataclass(default):
            values[name] = dataclass_from_dict(type(default), value, f"{source}.{name}")
        elif isinstance(default, dict):  # already-parsed sub-mappings (e.g. named entries)
            if not isinstance(value, dict):
                raise ConfigError(f"{source}: {name} must be a mapping, got {type(value).__name__}")
            values[name] = dict(value)
        else:
            values[name] = convert_value(cls, name, value, source)
    try:
        return cls(**values)
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None

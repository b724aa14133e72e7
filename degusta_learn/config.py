"""Typed configs from YAML: dataclasses, `--set key=value` overrides and errors that name the key.

Only this module (and the CLI) reads YAML. A config class is a dataclass whose fields carry a one-line
docstring-like comment; nested sections are nested dataclasses. `load_config` checks every key and
type and raises `DegustaError` with messages such as
``configs/x.yaml: backend.n: expected int, got 'five'`` or ``configs/x.yaml: unknown key 'lr'``.

Example:
    cfg = load_config(MyConfig, "configs/learned_cpu.yaml", overrides=["trainer.max_epochs=3"])
"""

from __future__ import annotations

import dataclasses
import types
import typing
from pathlib import Path
from typing import Any, Literal, TypeVar, Union, get_args, get_origin

import yaml

from degusta_learn.errors import DegustaError

T = TypeVar("T")


def read_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping; a missing file, a syntax error or a non-mapping raises DegustaError."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise DegustaError(f"{path}: config file not found") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f":{mark.line + 1}" if mark is not None else ""
        raise DegustaError(f"{path}{where}: invalid YAML ({getattr(e, 'problem', e)})") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise DegustaError(f"{path}: expected a mapping of keys at the top level, got {type(data).__name__}")
    return data


def apply_overrides(data: dict[str, Any], overrides: list[str] | None) -> dict[str, Any]:
    """Apply `a.b=value` overrides (value parsed as YAML, so `n=5` is an int) to a nested dict copy."""
    out = _deepcopy(data)
    for item in overrides or []:
        if "=" not in item:
            raise DegustaError(f"--set {item!r}: expected key=value")
        key, raw = item.split("=", 1)
        try:
            value = yaml.safe_load(raw) if raw != "" else ""
        except yaml.YAMLError:
            value = raw
        node = out
        parts = key.strip().split(".")
        for part in parts[:-1]:
            child = node.get(part)
            if child is None:
                child = node[part] = {}
            if not isinstance(child, dict):
                raise DegustaError(f"--set {key}: '{part}' is not a section")
            node = child
        node[parts[-1]] = value
    return out


def from_dict(cls: type[T], data: dict[str, Any], where: str = "config", prefix: str = "") -> T:
    """Build dataclass `cls` from `data`, checking unknown keys, missing keys and types."""
    if not isinstance(data, dict):
        raise DegustaError(f"{where}: {prefix.rstrip('.') or 'config'}: expected a mapping, got {data!r}")
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise DegustaError(
            f"{where}: unknown key '{prefix}{unknown[0]}' (known keys: {', '.join(sorted(fields))})"
        )
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for name, field in fields.items():
        key = prefix + name
        if name in data:
            kwargs[name] = _convert(hints[name], data[name], where, key)
        elif field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING:
            raise DegustaError(f"{where}: missing required key '{key}'")
    try:
        return cls(**kwargs)
    except DegustaError as e:
        raise DegustaError(f"{where}: {e}") from None


def load_config(cls: type[T], path: str | Path | None = None, overrides: list[str] | None = None,
                data: dict[str, Any] | None = None) -> T:
    """Read YAML at `path` (or take `data`), apply `--set` overrides and build a validated `cls`."""
    raw = read_yaml(path) if path is not None else dict(data or {})
    return from_dict(cls, apply_overrides(raw, overrides), where=str(path) if path else "config")


def to_dict(cfg: Any) -> dict[str, Any]:
    """A plain dict of a config dataclass (for writing the resolved config beside outputs)."""
    return dataclasses.asdict(cfg)


def _convert(tp: Any, value: Any, where: str, key: str) -> Any:
    origin = get_origin(tp)
    if tp is Any:
        return value
    if origin in (Union, types.UnionType):
        args = get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _convert(arg, value, where, key)
            except DegustaError as e:
                errors.append(str(e))
        raise DegustaError(errors[0] if len(errors) == 1 else f"{where}: {key}: expected {_name(tp)}, got {value!r}")
    if origin is Literal:
        choices = get_args(tp)
        if value not in choices:
            raise DegustaError(f"{where}: {key}: expected one of {list(choices)}, got {value!r}")
        return value
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise DegustaError(f"{where}: {key}: expected a list, got {value!r}")
        args = get_args(tp)
        item_tp = args[0] if args else Any
        items = [_convert(item_tp, v, where, f"{key}[{i}]") for i, v in enumerate(value)]
        return items if origin is list else tuple(items)
    if origin is dict:
        if not isinstance(value, dict):
            raise DegustaError(f"{where}: {key}: expected a mapping, got {value!r}")
        _, vt = get_args(tp) or (Any, Any)
        return {k: _convert(vt, v, where, f"{key}.{k}") for k, v in value.items()}
    if dataclasses.is_dataclass(tp):
        return from_dict(tp, value, where, prefix=key + ".")
    if tp is bool:
        if isinstance(value, bool):
            return value
    elif tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
    elif tp is str:
        if isinstance(value, str):
            return value
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return str(value)
    else:
        return value
    raise DegustaError(f"{where}: {key}: expected {_name(tp)}, got {value!r}")


def _name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def _deepcopy(d: Any) -> Any:
    if isinstance(d, dict):
        return {k: _deepcopy(v) for k, v in d.items()}
    if isinstance(d, list):
        return [_deepcopy(v) for v in d]
    return d

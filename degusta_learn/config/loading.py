"""Typed configs from plain data: `from_dict` checks every key and type, naming the key; `load_config` reads a file.

A config class is a dataclass whose fields carry a one-line docstring; nested sections are nested dataclasses.
Unknown keys, missing keys, wrong types, numbers outside a `bounded` field's range and bad path keys are one
`DegustaError` such as ``configs/x.yaml: backend.n: expected int, got 'five'``.

Usage:
    cfg = load_config(MyConfig, "configs/learned_cpu.yaml", overrides=["trainer.max_epochs=3"])
"""

from __future__ import annotations

import contextvars
import copy
import dataclasses
import math
import re
import types
import typing
from pathlib import Path
from typing import Any, Literal, TypeVar, Union, get_args, get_origin

from degusta_learn.config.fields import check_bounds, show_value
from degusta_learn.config.yaml_io import apply_overrides, read_yaml
from degusta_learn.errors import DegustaError
from degusta_learn.files.paths import NOT_UTF8, check_path, not_utf8, shown_path

T = TypeVar("T")

_EXPONENT = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+")
"""A number in exponent notation given as text to a float key (a quoted '6e-3', or a dict built in Python from
YAML 1.1 output, which reads 6e-3 as text): taken as the number. The YAML 1.2 loader reads 6e-3 as a float."""


def from_dict(cls: type[T], data: dict[str, Any], where: str = "config", prefix: str = "", *,
              probe_paths: bool | None = None) -> T:
    """Build dataclass `cls` from `data`, checking unknown keys, missing keys and types.

    Path keys (`PATH_KEYS`) have `~` expanded and are checked (`files.paths.check_path`). `probe_paths=False`: their text
    only, not what is on disk now: for a record of paths as they were (a fine-tuning record's dataset may have moved).
    """
    if probe_paths is not None:
        token = _PROBE_PATHS.set(probe_paths)
        try:
            return from_dict(cls, data, where, prefix)
        finally:
            _PROBE_PATHS.reset(token)
    if not isinstance(data, dict):
        raise DegustaError(f"{where}: {prefix.rstrip('.') or 'config'}: expected a mapping, got {show_value(data)}")
    if hasattr(cls, "section_class"):  # a section whose class one of its keys picks (backend: {name: hf} -> HFConfig)
        try:
            cls = cls.section_class(data, prefix)
        except DegustaError as e:
            raise DegustaError(f"{where}: {e}") from None
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields), key=str)
    renamed = [k for k in unknown if isinstance(k, str) and k in getattr(cls, "RENAMED", {})]
    if renamed:  # an old spelling: say the one key every config kind now uses for the concept
        raise DegustaError(f"{where}: '{prefix}{renamed[0]}' is now '{cls.RENAMED[renamed[0]]}' "
                           "(one spelling per concept across config kinds: docs/configs.md)")
    removed = [k for k in unknown if isinstance(k, str) and k in getattr(cls, "REMOVED", {})]
    if removed:  # an option taken out: say what it was and why, not merely "unknown key"
        raise DegustaError(f"{where}: {prefix}{removed[0]}: removed ({cls.REMOVED[removed[0]]})")
    if unknown:
        name = unknown[0] if isinstance(unknown[0], str) and len(unknown[0]) <= 60 else show_value(unknown[0])
        raise DegustaError(
            f"{where}: unknown key '{prefix}{name}' (known keys: {', '.join(sorted(fields))})"
        )
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for name, field in fields.items():
        key = prefix + name
        if name in data:
            kwargs[name] = _convert(hints[name], _onto_default(field, data[name]), where, key)
            if "bounds" in field.metadata:
                check_bounds(kwargs[name], field.metadata["bounds"], where, key)
        elif field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING:
            raise DegustaError(f"{where}: missing required key '{key}'")
    try:
        return cls(**kwargs)
    except DegustaError as e:
        raise DegustaError(f"{where}: {e}") from None


def _onto_default(field: dataclasses.Field, value: Any) -> Any:
    """A partial section given for a field whose default is a configured instance (`default_factory=lambda:
    OptimConfig(lr=1.5e-3)`) fills its missing keys from that instance, not from the section class's own
    defaults: `--set optim.weight_decay=0.1` must not reset the kind's `optim.lr`."""
    if not isinstance(value, dict) or field.default_factory is dataclasses.MISSING:
        return value
    default = field.default_factory()
    if not dataclasses.is_dataclass(default) or hasattr(type(default), "section_class"):
        return value  # a section whose class a key picks (backend): another class's keys would not fit
    return _merge(_init_values(default), value)


def _init_values(obj: Any) -> Any:
    """The constructor arguments of a dataclass instance, recursively (what from_dict would be given)."""
    if dataclasses.is_dataclass(obj):
        return {f.name: _init_values(getattr(obj, f.name)) for f in dataclasses.fields(obj) if f.init}
    return copy.deepcopy(obj)


def _merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def load_config(cls: type[T], path: str | Path | None = None, overrides: list[str] | None = None,
                data: dict[str, Any] | None = None) -> T:
    """Read YAML at `path` (or take `data`), apply `--set` overrides and build a validated `cls`."""
    raw = read_yaml(path) if path is not None else dict(data or {})
    return from_dict(cls, apply_overrides(raw, overrides), where=str(path) if path else "config")


def to_dict(cfg: Any) -> dict[str, Any]:
    """A plain dict of a config dataclass (for writing the resolved config beside outputs)."""
    return dataclasses.asdict(cfg)


_BOOL_HINT = (" (YAML reads an unquoted true or false as a boolean: write the word in quotes, "
              "e.g. --set \"key='true'\")")

PATH_KEYS = ("dataset", "out", "episodes", "predictions", "checkpoint", "run_dir", "export", "cache", "ledger",
             "styles", "adapter", "path", "config", "model.name")
"""The keys that hold a file or folder path in every config kind (one spelling per concept, docs/configs.md): a key
whose last part (or, dotted, whose end) is one of these has `~` / `~user` expanded and is checked by
`files.paths.check_path`, with one line naming the key and the path. `model.name` takes a hub id, a folder or an API
model id: the check refuses only what could be none of them. tests/test_hardening_paths2.py lists every string key of every
config kind, so a new path key cannot be left out silently."""


def path_key(key: str) -> bool:
    """Whether the config key `key` (dotted, e.g. `trainer.run_dir`, `methods[0].config`) holds a path."""
    return any(key == k or key.endswith("." + k) for k in PATH_KEYS)


_PROBE_PATHS = contextvars.ContextVar("degusta_probe_paths", default=True)
"""Whether path keys are probed on disk (from_dict's `probe_paths`); their text is always checked."""


def _checked_path(value: str, where: str, key: str) -> str:
    text, problem = check_path(value, probe=_PROBE_PATHS.get())
    if problem:
        raise DegustaError(f"{where}: {key}: {shown_path(value)}: {problem}")
    return text


_YAML11_NUMBER = re.compile(r"[-+]?(0b[01_]+|[0-9][0-9_]*(:[0-5]?[0-9])+(\.[0-9_]*)?|[0-9_]*_[0-9_]*(\.[0-9_]*)?"
                            r"([eE][-+]?[0-9]+)?)")


def _yaml12_hint(tp: Any, value: Any) -> str:
    """What YAML 1.1 read differently, for a number or boolean key given text (configs are read as YAML 1.2)."""
    if not isinstance(value, str):
        return ""
    if tp is bool and value.lower() in ("yes", "no", "on", "off", "y", "n"):
        return " (configs are read as YAML 1.2, where only true and false are booleans: write true or false)"
    if tp in (int, float) and _YAML11_NUMBER.fullmatch(value.strip()):
        return (" (configs are read as YAML 1.2, which reads base-60 1:30, 1_000 and 0b10 as text, not numbers: "
                "write the number in decimal digits, e.g. 90 or 1000)")
    return ""


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
        raise DegustaError(errors[0] if len(errors) == 1 else f"{where}: {key}: expected {_name(tp)}, got {show_value(value)}")
    if origin is Literal:
        choices = get_args(tp)
        # `True == 1` and `1 == 1.0` in Python: a choice matches only a value of its own type.
        if not any(type(value) is type(c) and value == c for c in choices):
            hint = _BOOL_HINT if isinstance(value, bool) and any(isinstance(c, str) for c in choices) else ""
            raise DegustaError(f"{where}: {key}: expected one of {list(choices)}, got {show_value(value)}{hint}")
        return value
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise DegustaError(f"{where}: {key}: expected a list, got {show_value(value)}")
        args = get_args(tp)
        item_tp = args[0] if args else Any
        items = [_convert(item_tp, v, where, f"{key}[{i}]") for i, v in enumerate(value)]
        return items if origin is list else tuple(items)
    if origin is dict:
        if not isinstance(value, dict):
            raise DegustaError(f"{where}: {key}: expected a mapping, got {show_value(value)}")
        kt, vt = get_args(tp) or (Any, Any)
        return {_convert(kt, k, where, f"{key} key {show_value(k)}"): _convert(vt, v, where, f"{key}.{k}")
                for k, v in value.items()}
    if dataclasses.is_dataclass(tp):
        return from_dict(tp, value, where, prefix=key + ".")
    if tp is bool:
        if isinstance(value, bool):
            return value
    elif tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif tp is float:
        if isinstance(value, str) and _EXPONENT.fullmatch(value.strip()):
            value = float(value)  # '6e-3' as text (see _EXPONENT)
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            try:
                out = float(value)
            except OverflowError:
                raise DegustaError(f"{where}: {key}: expected a finite number, got {show_value(value)}") from None
            if not math.isfinite(out):
                raise DegustaError(f"{where}: {key}: expected a finite number, got {show_value(value)}")
            return out
    elif tp is str:
        if isinstance(value, str):
            bad = not_utf8(value)
            if bad:  # a --set value from argv with undecodable bytes, or a "\udcff" escape in the YAML
                raise DegustaError(f"{where}: {key}: {shown_path(value)}: is not UTF-8 ({bad}); "
                                   + (NOT_UTF8 if path_key(key) else "give UTF-8 text"))
            return _checked_path(value, where, key) if path_key(key) else value
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            # YAML reads 1e3, 010, 0x1F, 1_000 as numbers: their text is lost, so str(value) could name
            # another file or model than the one written. Refuse and ask for quotes.
            raise DegustaError(f"{where}: {key}: expected a string, got the number {show_value(value)} "
                               "(write it in quotes if you mean the text)")
        hint = _BOOL_HINT if isinstance(value, bool) else ""
        raise DegustaError(f"{where}: {key}: expected a string, got {_kind(value)} {show_value(value)}{hint}")
    else:
        return value
    raise DegustaError(f"{where}: {key}: expected {_name(tp)}, got {show_value(value)}{_yaml12_hint(tp, value)}")


def _kind(value: Any) -> str:
    """`a list` / `a mapping` / `true/false` / `null` / `a <type>`: what a wrong-typed user value is."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "the boolean"
    if isinstance(value, (list, tuple)):
        return "a list"
    if isinstance(value, dict):
        return "a mapping"
    return f"a {type(value).__name__}"


def _name(tp: Any) -> str:
    if get_origin(tp) in (Union, types.UnionType):  # e.g. "int or 'auto'", not "Union"
        return " or ".join(_name(a) for a in get_args(tp) if a is not type(None))
    if get_origin(tp) is Literal:
        return " or ".join(repr(a) for a in get_args(tp))
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")

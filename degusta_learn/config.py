"""Typed configs from YAML: dataclasses, `--set key=value` overrides and errors that name the key.

Only this module (and the CLI) reads YAML. A config class is a dataclass whose fields carry a one-line
docstring-like comment; nested sections are nested dataclasses. `load_config` checks every key and
type and raises `DegustaError` with messages such as
``configs/x.yaml: backend.n: expected int, got 'five'`` or ``configs/x.yaml: unknown key 'lr'``.

Hostile or oversized input is refused with one line, never loaded: YAML whose aliases expand past
`MAX_YAML_NODES` values (a "billion laughs" bomb) or refer to themselves, files over `MAX_CONFIG_BYTES`,
non-UTF-8, too-deep nesting, non-finite floats, and numbers outside the range a field declares with
`bounded(default, lo, hi)` (e.g. ``x.yaml: model.image_size: expected a value from 16 to 4,096, got 60000``).

Numbers and booleans are read as YAML 1.2 (its core schema), in files and in `--set` values alike, never as
PyYAML's YAML 1.1: `010` is 10 (not octal 8), `0o10` 8, `0x10` 16, `1e3` and `6e-3` are floats; `1:30` (not 90),
`1_000`, `0b10`, `yes`, `no`, `on`, `off` and `2024-01-05` are text, so a number or boolean key given one of them
is refused with one line naming the key. Only `true` / `false` are booleans; `.inf` / `.nan` are refused by every
number key (non-finite). Path keys (`PATH_KEYS`: `dataset`, `out`, `episodes`, ...) have `~` expanded and are
checked by `fileio.check_path` (NUL bytes, names too long, non-UTF-8, a parent that is a file ...), naming the key.

Example:
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

import yaml

from degusta_learn.errors import DegustaError
from degusta_learn.fileio import NOT_UTF8, check_path, not_utf8, open_regular, shown_path

T = TypeVar("T")

_EXPONENT = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+")
"""A number in exponent notation given as text to a float key (a quoted '6e-3', or a dict built in Python from
YAML 1.1 output, which reads 6e-3 as text): taken as the number. The YAML 1.2 loader reads 6e-3 as a float."""


MAX_CONFIG_BYTES = 4 * 1024 * 1024
"""Largest config file read (configs are small text files; a bigger one is refused, not loaded)."""
MAX_YAML_NODES = 100_000
"""Most YAML nodes a config may expand to, aliases counted at their expanded size ("billion laughs")."""


MAX_SEED = 2**32 - 1
"""Largest seed a config or library entry point takes (numpy's legacy seed range: 0 .. 2**32 - 1)."""


def seed_field(default: int = 0) -> Any:
    """A config `seed` field: an integer from 0 to `MAX_SEED` (checked by `from_dict`, naming the key)."""
    return bounded(default, 0, MAX_SEED)


def check_seed(seed: Any, key: str = "seed") -> int:
    """`seed` as an int in 0..MAX_SEED, else DegustaError naming `key` (library entry points call this)."""
    try:
        import numpy as np
        ints: tuple = (int, np.integer)
    except ImportError:  # pragma: no cover - numpy is a dependency
        ints = (int,)
    if isinstance(seed, bool) or not isinstance(seed, ints) or not 0 <= int(seed) <= MAX_SEED:
        raise DegustaError(f"{key}: expected an integer from 0 to {MAX_SEED:,}, got {_show(seed)}")
    return int(seed)


class _YamlTooLarge(Exception):
    pass


class _YamlDuplicateKey(Exception):
    def __init__(self, line: int, key: Any, first: int):
        super().__init__(f"line {line}: duplicate key {key!r}")
        self.line, self.key, self.first = line, key, first


_INT12 = re.compile(r"[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+")
_FLOAT12 = re.compile(r"[-+]?(\.[0-9]+|[0-9]+(\.[0-9]*)?)([eE][-+]?[0-9]+)?|[-+]?\.(inf|Inf|INF)|\.(nan|NaN|NAN)")


class _BoundedLoader(yaml.SafeLoader):
    """The one YAML loader of configs and `--set` values: a SafeLoader that resolves plain scalars by the YAML 1.2
    core schema (not PyYAML's YAML 1.1: no octal `010`, base-60 `1:30`, `1_000`, `0b10`, yes/no/on/off booleans,
    dates or `=`; `1e3` is a float), whose documents are checked for alias expansion and cycles before they are
    built, and whose mappings refuse a key given twice (YAML would silently keep the last one)."""

    yaml_implicit_resolvers: dict = {}  # a clean slate: only the core schema's resolvers, added below

    def construct_yaml_int(self, node):
        text = self.construct_scalar(node)
        if not _INT12.fullmatch(text):
            raise yaml.constructor.ConstructorError(None, None, f"{text!r} is not a YAML 1.2 integer", node.start_mark)
        if text.startswith("0o"):
            return int(text[2:], 8)
        if text.startswith("0x"):
            return int(text[2:], 16)
        return int(text, 10)  # 010 is ten, as YAML 1.2 (and Python's int("010")) read it

    def construct_yaml_float(self, node):
        text = self.construct_scalar(node)
        if not _FLOAT12.fullmatch(text):
            raise yaml.constructor.ConstructorError(None, None, f"{text!r} is not a YAML 1.2 number", node.start_mark)
        lowered = text.lower()
        if lowered.endswith(".inf"):
            return -math.inf if lowered.startswith("-") else math.inf
        if lowered == ".nan":
            return math.nan
        return float(text)

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen: dict = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":  # `<<: *base` keys may be overridden
                    continue
                if not isinstance(key_node, yaml.ScalarNode):
                    continue  # non-scalar keys are refused later as not names
                key = self.construct_object(key_node, deep=True)
                try:
                    ident = (type(key).__name__, key)
                    hash(ident)
                except TypeError:
                    continue
                line = key_node.start_mark.line + 1
                if ident in seen:
                    raise _YamlDuplicateKey(line, key, seen[ident])
                seen[ident] = line
        return super().construct_mapping(node, deep=deep)


_BoundedLoader.add_constructor("tag:yaml.org,2002:int", _BoundedLoader.construct_yaml_int)
_BoundedLoader.add_constructor("tag:yaml.org,2002:float", _BoundedLoader.construct_yaml_float)
for _tag, _regexp, _first in (  # YAML 1.2.2, 10.3.2 (core schema), plus `<<` merge keys
        ("tag:yaml.org,2002:null", r"~|null|Null|NULL|", ["~", "n", "N", ""]),
        ("tag:yaml.org,2002:bool", r"true|True|TRUE|false|False|FALSE", list("tTfF")),
        ("tag:yaml.org,2002:int", _INT12.pattern, list("-+0123456789")),
        ("tag:yaml.org,2002:float", _FLOAT12.pattern, list("-+0123456789.")),
        ("tag:yaml.org,2002:merge", r"<<", ["<"])):
    _BoundedLoader.add_implicit_resolver(_tag, re.compile(f"^(?:{_regexp})$"), _first)


class _Dumper(yaml.SafeDumper):
    """A SafeDumper that quotes every string that YAML 1.1 *or* 1.2 would read as something else (`1e3`, `0o17`
    as well as `yes`, `010`), so what it writes reads back the same with this loader and with any other."""

    yaml_implicit_resolvers = {k: list(v) for k, v in yaml.SafeDumper.yaml_implicit_resolvers.items()}


for _tag, _regexp, _first in (("tag:yaml.org,2002:int", _INT12.pattern, list("-+0123456789")),
                              ("tag:yaml.org,2002:float", _FLOAT12.pattern, list("-+0123456789."))):
    _Dumper.add_implicit_resolver(_tag, re.compile(f"^(?:{_regexp})$"), _first)


def dump_yaml(data: Any, **kwargs) -> str:
    """YAML text of `data` (yaml.safe_dump's options) that `read_yaml` reads back as the same values."""
    return yaml.dump(data, Dumper=_Dumper, **{"sort_keys": False, "allow_unicode": True, **kwargs})


def _expanded_size(node: yaml.Node, memo: dict[int, int], active: set[int], limit: int) -> int:
    """Nodes of `node` with every alias expanded; raises _YamlTooLarge past `limit` or on a cycle."""
    key = id(node)
    if key in memo:
        return memo[key]
    if key in active:
        raise _YamlTooLarge("an alias refers to a node that contains it (a recursive structure)")
    active.add(key)
    if isinstance(node, yaml.SequenceNode):
        children = list(node.value)
    elif isinstance(node, yaml.MappingNode):
        children = [part for pair in node.value for part in pair]
    else:
        children = []
    size = 1
    for child in children:
        size += _expanded_size(child, memo, active, limit)
        if size > limit:
            raise _YamlTooLarge(f"aliases expand it to more than {limit:,} values (an alias bomb?); "
                                "write the values out instead of repeating anchors")
    active.discard(key)
    memo[key] = size
    return size


def _safe_load(text: str, limit: int = MAX_YAML_NODES) -> Any:
    """yaml.safe_load with alias expansion bounded by `limit` nodes and recursive aliases refused.

    Raises yaml.YAMLError (syntax), _YamlTooLarge, RecursionError (nesting) or ValueError (e.g. an integer
    of more digits than Python converts)."""
    loader = _BoundedLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        _expanded_size(node, {}, set(), limit)
        return loader.construct_document(node)
    finally:
        loader.dispose()


def read_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping; a missing/unreadable/oversized file, a syntax error, an alias bomb or a
    non-mapping raises DegustaError with a one-line message naming the file."""
    path = Path(path)
    with open_regular(path, MAX_CONFIG_BYTES, "a YAML config file") as f:
        data = f.read()
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise DegustaError(f"{path}: not UTF-8 text (byte {e.start}); expected a YAML config file") from None
    try:
        data = _safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f":{mark.line + 1}" if mark is not None else ""
        problem = " ".join(str(getattr(e, "problem", None) or e).split())
        raise DegustaError(f"{path}{where}: invalid YAML ({problem})") from None
    except _YamlTooLarge as e:
        raise DegustaError(f"{path}: refused: {e}") from None
    except _YamlDuplicateKey as e:
        raise DegustaError(f"{path}:{e.line}: duplicate key {_show(e.key)} (first given on line {e.first}); "
                           "YAML would silently keep the last value: give each key once") from None
    except RecursionError:
        raise DegustaError(f"{path}: refused: the YAML is nested too deeply") from None
    except (ValueError, OverflowError) as e:  # e.g. an integer of more than 4300 digits
        raise DegustaError(f"{path}: invalid YAML value ({' '.join(str(e).split())[:120]})") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise DegustaError(f"{path}: expected a mapping of keys at the top level, got {type(data).__name__}")
    bad = [k for k in data if not isinstance(k, str)]
    if bad:
        raise DegustaError(f"{path}: keys must be names, got {_show(bad[0])}")
    return data


def apply_overrides(data: dict[str, Any], overrides: list[str] | None) -> dict[str, Any]:
    """Apply `a.b=value` overrides (value parsed as YAML, so `n=5` is an int) to a nested dict copy."""
    out = _deepcopy(data)
    for item in overrides or []:
        if "=" not in item:
            raise DegustaError(f"--set {_show(item)}: expected key=value")
        key, raw = item.split("=", 1)
        try:
            value = _safe_load(raw) if raw != "" else ""
        except yaml.YAMLError:
            value = raw
        except _YamlDuplicateKey as e:
            raise DegustaError(f"--set {key}: duplicate key {_show(e.key)} in the value; give each key once") from None
        except RecursionError:
            raise DegustaError(f"--set {key}: refused value (nested too deeply)") from None
        except (ValueError, OverflowError) as e:
            why = "a number with too many digits" if "digits" in str(e) else " ".join(str(e).split())[:120]
            raise DegustaError(f"--set {key}: refused value ({why})") from None
        except _YamlTooLarge as e:
            raise DegustaError(f"--set {key}: refused value ({' '.join(str(e).split())[:120] or 'too large'})") from None
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


def bounded(default: Any = dataclasses.MISSING, lo: float | None = None, hi: float | None = None, *,
            special: tuple = (), factory: Any = None) -> Any:
    """A dataclass field whose number (or each number of its list) must lie in [lo, hi] or be in `special`.

    `from_dict` checks it and names the key, so a config cannot ask for a 60000-px image or a billion-row
    batch. Example: `image_size: int = bounded(448, 16, 4096)`; `max_steps: int = bounded(-1, 1, 10**9, special=(-1,))`;
    lists: `channels: list[int] = bounded(lo=1, hi=4096, factory=lambda: [32, 64])`.
    """
    meta = {"bounds": (lo, hi, tuple(special))}
    if factory is not None:
        return dataclasses.field(default_factory=factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def _check_bounds(value: Any, bounds: tuple, where: str, key: str) -> None:
    lo, hi, special = bounds
    items = value if isinstance(value, (list, tuple)) else [value]
    for v in items:
        if v is None or isinstance(v, bool) or not isinstance(v, (int, float)) or v in special:
            continue
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            if lo is not None and hi is not None:
                want = f"a value from {lo:,} to {hi:,}"
            else:
                want = f"at least {lo:,}" if lo is not None else f"at most {hi:,}"
            if special:
                want += " (or " + " / ".join(repr(x) for x in special) + ")"
            raise DegustaError(f"{where}: {key}: expected {want}, got {_show(v)}")


def check_choices(obj: Any, section: str) -> None:
    """Check every `Literal` field of dataclass `obj` against its choices, naming `section.field`: the loader
    does this for YAML and `--set`; a dataclass built in Python calls this from its `__post_init__`."""
    for name, tp in typing.get_type_hints(type(obj)).items():
        args = get_args(tp) if get_origin(tp) in (Union, types.UnionType) else (tp,)
        if not hasattr(obj, name) or not all(get_origin(a) is Literal or a is type(None) for a in args):
            continue  # only Literal[...] and Literal[...] | None fields
        value = getattr(obj, name)
        choices = [c for a in args if a is not type(None) for c in get_args(a)]
        if not (value is None and type(None) in args) and not any(type(value) is type(c) and value == c
                                                                    for c in choices):
            where = f"{section}.{name}" if section else name
            raise DegustaError(f"{where}: expected one of {choices}, got {_show(value)}")


def from_dict(cls: type[T], data: dict[str, Any], where: str = "config", prefix: str = "", *,
              probe_paths: bool | None = None) -> T:
    """Build dataclass `cls` from `data`, checking unknown keys, missing keys and types.

    Path keys (`PATH_KEYS`) have `~` expanded and are checked (`fileio.check_path`). `probe_paths=False`: their text
    only, not what is on disk now: for a record of paths as they were (a fine-tuning record's dataset may have moved).
    """
    if probe_paths is not None:
        token = _PROBE_PATHS.set(probe_paths)
        try:
            return from_dict(cls, data, where, prefix)
        finally:
            _PROBE_PATHS.reset(token)
    if not isinstance(data, dict):
        raise DegustaError(f"{where}: {prefix.rstrip('.') or 'config'}: expected a mapping, got {_show(data)}")
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
    if unknown:
        name = unknown[0] if isinstance(unknown[0], str) and len(unknown[0]) <= 60 else _show(unknown[0])
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
                _check_bounds(kwargs[name], field.metadata["bounds"], where, key)
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
             "styles", "adapter", "path", "config", "model.name", "backend.model")
"""The keys that hold a file or folder path in every config kind (one spelling per concept, docs/configs.md): a key
whose last part (or, dotted, whose end) is one of these has `~` / `~user` expanded and is checked by
`fileio.check_path`, with one line naming the key and the path. `model.name` and `backend.model` take a hub id or a
folder: the check refuses only what could be neither. tests/test_hardening_paths2.py lists every string key of every
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
        raise DegustaError(errors[0] if len(errors) == 1 else f"{where}: {key}: expected {_name(tp)}, got {_show(value)}")
    if origin is Literal:
        choices = get_args(tp)
        # `True == 1` and `1 == 1.0` in Python: a choice matches only a value of its own type.
        if not any(type(value) is type(c) and value == c for c in choices):
            hint = _BOOL_HINT if isinstance(value, bool) and any(isinstance(c, str) for c in choices) else ""
            raise DegustaError(f"{where}: {key}: expected one of {list(choices)}, got {_show(value)}{hint}")
        return value
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise DegustaError(f"{where}: {key}: expected a list, got {_show(value)}")
        args = get_args(tp)
        item_tp = args[0] if args else Any
        items = [_convert(item_tp, v, where, f"{key}[{i}]") for i, v in enumerate(value)]
        return items if origin is list else tuple(items)
    if origin is dict:
        if not isinstance(value, dict):
            raise DegustaError(f"{where}: {key}: expected a mapping, got {_show(value)}")
        kt, vt = get_args(tp) or (Any, Any)
        return {_convert(kt, k, where, f"{key} key {_show(k)}"): _convert(vt, v, where, f"{key}.{k}")
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
                raise DegustaError(f"{where}: {key}: expected a finite number, got {_show(value)}") from None
            if not math.isfinite(out):
                raise DegustaError(f"{where}: {key}: expected a finite number, got {_show(value)}")
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
            raise DegustaError(f"{where}: {key}: expected a string, got the number {_show(value)} "
                               "(write it in quotes if you mean the text)")
        hint = _BOOL_HINT if isinstance(value, bool) else ""
        raise DegustaError(f"{where}: {key}: expected a string, got {_kind(value)} {_show(value)}{hint}")
    else:
        return value
    raise DegustaError(f"{where}: {key}: expected {_name(tp)}, got {_show(value)}{_yaml12_hint(tp, value)}")


def _show(value: Any, n: int = 60) -> str:
    """A short one-line repr of a user value (huge integers and long strings are summarised)."""
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 64:
        return f"an integer of about {int(value.bit_length() * 0.30103) + 1} digits"
    try:
        text = repr(value)
    except (ValueError, RecursionError):
        return f"a {type(value).__name__}"
    text = " ".join(text.split())
    return text if len(text) <= n else text[:n] + "..."


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


def _deepcopy(d: Any) -> Any:
    if isinstance(d, dict):
        return {k: _deepcopy(v) for k, v in d.items()}
    if isinstance(d, list):
        return [_deepcopy(v) for v in d]
    return d

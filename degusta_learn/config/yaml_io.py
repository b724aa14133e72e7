"""YAML in and out: the one loader of configs and `--set` values (YAML 1.2, bounded), and a dumper it reads back.

Hostile or oversized input is refused with one line, never loaded: aliases that expand past `MAX_YAML_NODES` values
(a "billion laughs" bomb) or refer to themselves, files over `MAX_CONFIG_BYTES`, non-UTF-8, too-deep nesting, a key
given twice. Numbers and booleans are read as YAML 1.2 (see the package docstring).

Usage:
    raw = apply_overrides(read_yaml("configs/learned_cpu.yaml"), ["trainer.max_epochs=3"])
    text = dump_yaml(raw)
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import yaml

from degusta_learn.config.fields import show_value
from degusta_learn.errors import DegustaError
from degusta_learn.files.jsonio import open_regular

MAX_CONFIG_BYTES = 4 * 1024 * 1024
"""Largest config file read (configs are small text files; a bigger one is refused, not loaded)."""

MAX_YAML_NODES = 100_000
"""Most YAML nodes a config may expand to, aliases counted at their expanded size ("billion laughs")."""


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
        raise DegustaError(f"{path}:{e.line}: duplicate key {show_value(e.key)} (first given on line {e.first}); "
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
        raise DegustaError(f"{path}: keys must be names, got {show_value(bad[0])}")
    return data


def apply_overrides(data: dict[str, Any], overrides: list[str] | None) -> dict[str, Any]:
    """Apply `a.b=value` overrides (value parsed as YAML, so `n=5` is an int) to a nested dict copy."""
    out = _deepcopy(data)
    for item in overrides or []:
        if "=" not in item:
            raise DegustaError(f"--set {show_value(item)}: expected key=value")
        key, raw = item.split("=", 1)
        try:
            value = _safe_load(raw) if raw != "" else ""
        except yaml.YAMLError:
            value = raw
        except _YamlDuplicateKey as e:
            raise DegustaError(f"--set {key}: duplicate key {show_value(e.key)} in the value; give each key once") from None
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


def _deepcopy(d: Any) -> Any:
    if isinstance(d, dict):
        return {k: _deepcopy(v) for k, v in d.items()}
    if isinstance(d, list):
        return [_deepcopy(v) for v in d]
    return d

"""Config field helpers: bounded numbers, seeds, `Literal` choices and one-line renderings of user values.

Usage:
    @dataclass
    class Section:
        image_size: int = bounded(448, 16, 4096)     # from_dict refuses 60000, naming the key
        seed: int = seed_field()                      # 0 .. MAX_SEED
"""

from __future__ import annotations

import dataclasses
import types
import typing
from typing import Any, Literal, Union, get_args, get_origin

from degusta_learn.errors import DegustaError

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
        raise DegustaError(f"{key}: expected an integer from 0 to {MAX_SEED:,}, got {show_value(seed)}")
    return int(seed)


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


def check_bounds(value: Any, bounds: tuple, where: str, key: str) -> None:
    """Refuse (DegustaError "WHERE: KEY: expected a value from LO to HI, got V") a number, or any number of a list,
    outside `bounds` (the (lo, hi, special) of a `bounded` field's metadata; `special` values always pass)."""
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
            raise DegustaError(f"{where}: {key}: expected {want}, got {show_value(v)}")


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
            raise DegustaError(f"{where}: expected one of {choices}, got {show_value(value)}")


def show_value(value: Any, n: int = 60) -> str:
    """A short one-line repr of a user value (huge integers and long strings are summarised)."""
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 64:
        return f"an integer of about {int(value.bit_length() * 0.30103) + 1} digits"
    try:
        text = repr(value)
    except (ValueError, RecursionError):
        return f"a {type(value).__name__}"
    text = " ".join(text.split())
    return text if len(text) <= n else text[:n] + "..."

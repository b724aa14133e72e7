"""Field checks shared by the dataset, episode and prediction readers.

Each check raises `DegustaError` whose message starts with ``file:line: field 'name'`` so a user knows
exactly which entry to fix.
"""

from __future__ import annotations

import math
from typing import Any

from degusta_learn.errors import DegustaError


class Where:
    """Location of the entry under validation: file, optional line (1-based) or list index."""

    def __init__(self, path: Any, line: int | None = None, index: int | None = None):
        self.path, self.line, self.index = path, line, index

    def __str__(self) -> str:
        if self.line is not None:
            return f"{self.path}:{self.line}"
        if self.index is not None:
            return f"{self.path}: entry {self.index}"
        return str(self.path)

    def fail(self, field: str | None, message: str) -> DegustaError:
        return DegustaError(f"{self}: field '{field}': {message}" if field else f"{self}: {message}")


def require_mapping(obj: Any, where: Where) -> dict:
    if not isinstance(obj, dict):
        raise where.fail(None, f"expected a JSON object, got {type(obj).__name__}")
    return obj


def get(obj: dict, key: str, kind: str, where: Where, optional: bool = False, default: Any = None) -> Any:
    """Fetch obj[key] checked as `kind` in {'int', 'number', 'str', 'list', 'id'}; NaN/inf rejected."""
    if key not in obj or obj[key] is None:
        if optional:
            return default
        raise where.fail(key, "missing")
    value = obj[key]
    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise where.fail(key, f"expected an integer, got {value!r}")
    elif kind == "number":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise where.fail(key, f"expected a number, got {value!r}")
        if not math.isfinite(value):
            raise where.fail(key, f"expected a finite number, got {value!r}")
        value = float(value)
    elif kind == "str":
        if not isinstance(value, str) or not value:
            raise where.fail(key, f"expected a non-empty string, got {value!r}")
    elif kind == "id":  # participant ids: strings, or integers taken as their decimal string
        if isinstance(value, bool) or not isinstance(value, (str, int)) or value == "":
            raise where.fail(key, f"expected a string id, got {value!r}")
        value = str(value)
    elif kind == "list":
        if not isinstance(value, list):
            raise where.fail(key, f"expected a list, got {type(value).__name__}")
    else:  # pragma: no cover - programming error
        raise ValueError(kind)
    return value


def unit_interval(value: float, key: str, where: Where) -> float:
    if not 0.0 <= value <= 1.0:
        raise where.fail(key, f"{value} is outside [0, 1] (normalized image coordinates)")
    return value

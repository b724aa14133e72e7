"""What the toolkit's two web servers (`degusta serve`, `degusta collect`) share: a strict JSON reader for request
bodies and a body read that stops at a size limit.

- `strict_json(data, what)`: UTF-8, finite numbers only (no NaN / Infinity), integers of at most MAX_INT_DIGITS
  digits, no key given twice in one object, bounded nesting; any other body is one `DegustaError` line starting
  with `what`.
- `read_body(request, limit)`: the body of a Starlette request, refused from its Content-Length before it is read
  (or as soon as a chunked body passes the limit): `BodyTooLarge` (413) or `DegustaError` (400).
"""

from __future__ import annotations

import json
import math
from typing import Any

from degusta_learn.errors import DegustaError

MAX_INT_DIGITS = 20
"""Digits of an integer in a request body (a longer one is refused, not parsed)."""


class BodyTooLarge(DegustaError):
    """A request body over its limit (413)."""


def shown(value: Any, n: int = 60) -> str:
    """repr of a value for a message, cut short."""
    text = repr(value)
    return text if len(text) <= n else f"{text[:n - 10]}... ({len(text)} characters)"


class _BadJSON(ValueError):
    pass


def _no_constant(name: str):
    raise _BadJSON(f"{name} is not a number JSON allows (expected a finite number)")


def _int(text: str) -> int:
    if len(text.lstrip("-")) > MAX_INT_DIGITS:
        raise _BadJSON(f"an integer of {len(text.lstrip('-'))} digits is out of range")
    return int(text)


def _float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise _BadJSON(f"{shown(text, 30)} overflows to infinity (expected a finite number)")
    return value


def _pairs(pairs: list) -> dict:
    obj = dict(pairs)
    if len(obj) != len(pairs):
        seen: set = set()
        dup = next(k for k, _ in pairs if k in seen or seen.add(k))
        raise _BadJSON(f"the key {shown(dup, 40)} is given twice in one object")
    return obj


_DECODER = json.JSONDecoder(parse_constant=_no_constant, parse_int=_int, parse_float=_float, object_pairs_hook=_pairs)


def strict_json(data: bytes, what: str = "request") -> Any:
    """Parse a request body strictly (module docstring); errors are one line starting with `what`."""
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise DegustaError(f"{what}: not UTF-8 text (byte {data[e.start]:#04x} at offset {e.start})") from None
    try:
        return _DECODER.decode(text)
    except json.JSONDecodeError as e:
        raise DegustaError(f"{what}: invalid JSON at line {e.lineno} column {e.colno} ({e.msg})") from None
    except _BadJSON as e:
        raise DegustaError(f"{what}: invalid JSON ({e})") from None
    except RecursionError:
        raise DegustaError(f"{what}: invalid JSON (nested too deeply)") from None


async def read_body(request, limit: int, too_large) -> bytes:
    """The body of `request`, at most `limit` bytes; `too_large(size, read)` words the refusal (BodyTooLarge)."""
    declared = request.headers.get("content-length")
    if declared is not None:
        if not declared.strip().isdigit():
            raise DegustaError(f"request: Content-Length {declared[:40]!r} is not a number of bytes")
        if int(declared) > limit:
            raise BodyTooLarge(too_large(int(declared), False))
    data = bytearray()
    async for chunk in request.stream():
        data += chunk
        if len(data) > limit:
            raise BodyTooLarge(too_large(len(data), True))
    return bytes(data)


def check_bindable(host: str, port: int) -> None:
    """Refuse, before a server says it is serving, an address it cannot listen on (a port another server holds, an
    address this machine does not have), in one line naming it and the remedy."""
    import errno
    import socket

    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as e:
        raise DegustaError(f"--host {host}: not an address of this machine ({e.strerror})") from None
    family, kind, proto, _, address = infos[0]
    with socket.socket(family, kind, proto) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn binds
        try:
            s.bind(address)
        except OSError as e:
            hint = "another server is using it: choose another with --port" if e.errno == errno.EADDRINUSE else "choose another --host"
            raise DegustaError(f"cannot serve on {host}:{port}: {e.strerror} ({hint})") from None


__all__ = ["MAX_INT_DIGITS", "BodyTooLarge", "check_bindable", "read_body", "shown", "strict_json"]

"""The HTTP client every remote backend hands its official client (openai, anthropic, gemini): one deadline for
the whole request and a bound on the size of the reply.

The official clients bound each socket read by their timeout, not the request: a server that sends a byte just
before each read would time out (a trickled status line or body, an endless chunked body) holds a request
forever. And httpx inflates a gzip / deflate reply whole, so a reply of a megabyte on the wire can grow to
gigabytes in memory. `guarded_client(seconds, library)` is an `httpx.Client` (or an `httpx2.Client`, the fork
newer openai / anthropic clients build on: `flavour_of(library)`) that closes both holes for every backend at
once, below the client libraries (so their own error types and messages stay what they are):

- **Deadline.** A request -- connecting, TLS, sending the body, the status line, the headers and the whole
  reply, redirects included -- ends `seconds` after `send` starts (`backend.timeout`). Every blocking socket
  operation of the request waits at most until that moment: the network backend under httpcore clips the
  timeout of each connect, TLS handshake, write (in 16 KiB pieces) and read to the time left, and raises the
  clients' own timeout error (`httpx.ReadTimeout`, `httpx.ConnectTimeout`, `httpx.WriteTimeout`) once it is
  spent. No watchdog thread, nothing to cancel from outside, no socket left half-read: the thread making the
  request gives up by itself, on time, and the connection is closed. (A DNS look-up is the one step no
  timeout of Python's socket layer bounds.)
- **Size.** A reply body may be at most `MAX_REPLY_BYTES`, as sent and as decoded: a Content-Length over it is
  refused before a byte of the body is read, the body is counted as it arrives, and gzip / deflate (the only
  encodings asked for) are inflated here, in steps of at most 64 KiB (zlib's `max_length`), so the bound is
  checked before anything past it is allocated; any other Content-Encoding is refused. A refused reply raises
  `ReplyRefused` (an `httpx.ReadError`: a transport fault, which the runner retries as a server fault).

`fault_reason(exc)` finds the reason (deadline or size) in the chain of whatever exception a client library
made of it, for the backends' one-line messages.

Example:
    client = openai.OpenAI(..., max_retries=0, http_client=guarded_client(cfg.timeout, openai))
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import ipaddress
import socket
import threading
import time
import zlib
from collections.abc import Iterator
from types import SimpleNamespace

MAX_REPLY_BYTES = 32 * 2**20
"""The most bytes of one reply body, on the wire and decoded (32 MiB: 1,000 times the answers of n = 5 samples at
max_tokens 1024; well under the 64 MiB a predictions line may hold, files.jsonio.MAX_LINE_BYTES)."""
_STEP = 1 << 16  # the most bytes one inflate step produces
_WRITE_PIECE = 1 << 14  # a write is sent in pieces this big, each waiting at most until the deadline
_ENCODINGS = {"gzip": 16 + zlib.MAX_WBITS, "x-gzip": 16 + zlib.MAX_WBITS, "deflate": zlib.MAX_WBITS}
_ACCEPT = "gzip, deflate"


class _Request(threading.local):
    deadline: float | None = None  # time.monotonic() by which the request in this thread must end
    seconds: float = 0.0


_current = _Request()


class GuardFault(Exception):
    """A request cut off by this module (deadline or size); its message is the reason."""


def _deadline_message() -> str:
    return f"no complete reply within the {_current.seconds:g} s deadline of the request (backend.timeout)"


def fault_reason(exc: BaseException | None) -> str | None:
    """The message of the GuardFault in `exc`'s chain of causes (a client library wraps it), or None."""
    seen = 0
    while exc is not None and seen < 20:
        if isinstance(exc, GuardFault):
            return str(exc)
        exc = exc.__cause__ or exc.__context__
        seen += 1
    return None


def _expired() -> bool:
    return _current.deadline is not None and time.monotonic() >= _current.deadline


def _left(timeout: float | None, fault: type[Exception]) -> float | None:
    """`timeout` clipped to the time left before this thread's deadline; `fault` once none is left."""
    if _current.deadline is None:
        return timeout
    left = _current.deadline - time.monotonic()
    if left <= 0:
        raise fault(_deadline_message())
    return left if timeout is None else min(timeout, left)


@contextlib.contextmanager
def _deadline(deadline: float | None, seconds: float) -> Iterator[None]:
    """Make `deadline` this thread's for the block (the one already set, if any, stays: redirects share it)."""
    if _current.deadline is not None or deadline is None:
        yield
        return
    _current.deadline, _current.seconds = deadline, seconds
    try:
        yield
    finally:
        _current.deadline = None


class _Inflater:
    """One Content-Encoding undone in bounded steps (never more than _STEP bytes at once, MAX_REPLY_BYTES in all)."""

    def __init__(self, encoding: str, refused: type[Exception]):
        self.encoding, self.total, self._first, self._refused = encoding, 0, True, refused
        self._d = zlib.decompressobj(_ENCODINGS[encoding])

    def feed(self, data: bytes) -> Iterator[bytes]:
        while data and not self._d.eof:
            try:
                piece = self._d.decompress(data, _STEP)
            except zlib.error:
                if self._first and self.encoding == "deflate":  # raw deflate, without the zlib header (as httpx)
                    self._first = False
                    self._d = zlib.decompressobj(-zlib.MAX_WBITS)
                    continue
                raise self._refused(f"the reply's {self.encoding} body is corrupt") from None
            self._first = False
            data = self._d.unconsumed_tail
            yield from self._count(piece)
            while len(piece) == _STEP and not data and not self._d.eof:  # output still pending inside zlib
                piece = self._d.decompress(b"", _STEP)
                yield from self._count(piece)

    def finish(self) -> Iterator[bytes]:
        try:
            tail = self._d.flush()  # at most the few bytes of a match in progress: every step above was bounded
        except zlib.error:
            raise self._refused(f"the reply's {self.encoding} body is corrupt") from None
        yield from self._count(tail)

    def _count(self, piece: bytes) -> Iterator[bytes]:
        self.total += len(piece)
        if self.total > MAX_REPLY_BYTES:
            raise self._refused(f"the reply inflates ({self.encoding}) to more than {MAX_REPLY_BYTES} bytes, the "
                                "most a reply may hold; refused")
        if piece:
            yield piece


def _through(decoders: list[_Inflater], data: bytes) -> Iterator[bytes]:
    if not decoders:
        yield data
        return
    for piece in decoders[0].feed(data):
        yield from _through(decoders[1:], piece)


_FLAVOURS: dict[str, SimpleNamespace] = {}
_LOCK = threading.Lock()


def flavour_of(library=None) -> str:
    """Which httpx a client library builds on: "httpx", or its fork "httpx2" (newer openai and anthropic clients),
    read from the MRO of its default client class (`library.DefaultHttpxClient`). Without one (google-genai, which
    takes either; an old client): "httpx" if it is installed, else "httpx2"."""
    for c in getattr(getattr(library, "DefaultHttpxClient", None), "__mro__", ()):
        root = str(getattr(c, "__module__", "")).partition(".")[0]
        if root in ("httpx", "httpx2"):
            return root
    return "httpx" if importlib.util.find_spec("httpx") is not None else "httpx2"


def _flavour(name: str) -> SimpleNamespace:
    """The guard's classes built on `name` ("httpx" with httpcore, or "httpx2" with httpcore2), once."""
    with _LOCK:
        if name not in _FLAVOURS:
            _FLAVOURS[name] = _build(importlib.import_module(name),
                                     importlib.import_module("httpcore" if name == "httpx" else "httpcore2"))
        return _FLAVOURS[name]


def _build(httpx, httpcore) -> SimpleNamespace:
    """The guard's classes on one httpx flavour (the modules `httpx` + `httpcore`, or `httpx2` + `httpcore2`)."""

    class _ConnectDeadline(GuardFault, httpcore.ConnectTimeout):
        pass

    class _ReadDeadline(GuardFault, httpcore.ReadTimeout):
        pass

    class _WriteDeadline(GuardFault, httpcore.WriteTimeout):
        pass

    class DeadlineExceeded(GuardFault, httpx.ReadTimeout):
        """The reply did not end before the request's deadline."""

    class ReplyRefused(GuardFault, httpx.ReadError):
        """A reply over MAX_REPLY_BYTES (sent or decoded), or in an encoding that was not asked for, or corrupt."""

    class _Stream(httpcore.NetworkStream):
        """A connection whose every blocking operation waits at most until the deadline of the request using it."""

        def __init__(self, inner: httpcore.NetworkStream):
            self._inner = inner

        def read(self, max_bytes: int, timeout: float | None = None) -> bytes:
            wait = _left(timeout, _ReadDeadline)
            try:
                return self._inner.read(max_bytes, wait)
            except httpcore.ReadTimeout:
                if _expired():
                    raise _ReadDeadline(_deadline_message()) from None
                raise

        def write(self, buffer: bytes, timeout: float | None = None) -> None:
            view = memoryview(buffer)
            for start in range(0, len(view), _WRITE_PIECE):
                wait = _left(timeout, _WriteDeadline)
                try:
                    self._inner.write(bytes(view[start:start + _WRITE_PIECE]), wait)
                except httpcore.WriteTimeout:
                    if _expired():
                        raise _WriteDeadline(_deadline_message()) from None
                    raise

        def close(self) -> None:
            self._inner.close()

        def start_tls(self, ssl_context, server_hostname: str | None = None,
                      timeout: float | None = None) -> httpcore.NetworkStream:
            wait = _left(timeout, _ConnectDeadline)
            try:
                return _Stream(self._inner.start_tls(ssl_context, server_hostname, wait))
            except httpcore.ConnectTimeout:
                if _expired():
                    raise _ConnectDeadline(_deadline_message()) from None
                raise

        def get_extra_info(self, info: str):
            return self._inner.get_extra_info(info)

    class _NetworkBackend(httpcore.NetworkBackend):
        """httpcore's network backend whose connections keep to the request's deadline (`_Stream`)."""

        def __init__(self, inner: httpcore.NetworkBackend):
            self._inner = inner

        def _connect(self, connect, *args, timeout: float | None, **kwargs) -> httpcore.NetworkStream:
            wait = _left(timeout, _ConnectDeadline)
            try:
                return _Stream(connect(*args, timeout=wait, **kwargs))
            except httpcore.ConnectTimeout:
                if _expired():
                    raise _ConnectDeadline(_deadline_message()) from None
                raise

        def connect_tcp(self, host, port, timeout=None, local_address=None, socket_options=None):
            return self._connect(self._inner.connect_tcp, host, port, timeout=timeout, local_address=local_address,
                                 socket_options=socket_options)

        def connect_unix_socket(self, path, timeout=None, socket_options=None):
            return self._connect(self._inner.connect_unix_socket, path, timeout=timeout, socket_options=socket_options)

        def sleep(self, seconds: float) -> None:
            self._inner.sleep(seconds)

    class _Body(httpx.SyncByteStream):
        """A reply body read within the request's deadline, counted, and decoded in bounded steps."""

        def __init__(self, raw: httpx.SyncByteStream, encodings: list[str], deadline: float | None, seconds: float):
            self._raw, self._deadline, self._seconds = raw, deadline, seconds
            # the last encoding applied is undone first
            self._decoders = [_Inflater(e, ReplyRefused) for e in reversed(encodings)]

        def __iter__(self) -> Iterator[bytes]:
            size = 0
            chunks = iter(self._raw)
            while True:
                with _deadline(self._deadline, self._seconds):
                    chunk = next(chunks, None)
                    if chunk is not None and _expired():
                        raise DeadlineExceeded(_deadline_message())
                if chunk is None:
                    break
                size += len(chunk)
                if size > MAX_REPLY_BYTES:
                    raise ReplyRefused(f"the reply is longer than {MAX_REPLY_BYTES} bytes, the most a reply may hold; "
                                       "refused")
                yield from _through(self._decoders, chunk)
            for i, decoder in enumerate(self._decoders):
                for piece in decoder.finish():
                    yield from _through(self._decoders[i + 1:], piece)

        def close(self) -> None:
            self._raw.close()

    class GuardedTransport(httpx.HTTPTransport):
        """httpx's transport on a network backend that keeps to each request's deadline, whose replies are bounded
        and decoded in bounded steps (`_Body`)."""

        def __init__(self, seconds: float, **kwargs):
            super().__init__(**kwargs)
            self.seconds = seconds
            pool = getattr(self, "_pool", None)  # httpcore's connection pool: its connections come from this backend
            inner = getattr(pool, "_network_backend", None)
            if inner is not None:
                pool._network_backend = _NetworkBackend(inner)
            # (were httpcore's pool ever built otherwise, the body would still keep to the deadline, chunk by chunk)

        def handle_request(self, request: httpx.Request) -> httpx.Response:
            request.headers["Accept-Encoding"] = _ACCEPT  # never br / zstd, which would be inflated whole
            deadline = _current.deadline if _current.deadline is not None else time.monotonic() + self.seconds
            seconds = _current.seconds if _current.deadline is not None else self.seconds
            with _deadline(deadline, seconds):
                response = super().handle_request(request)
            try:
                encodings = [e.strip().lower() for e in response.headers.get("content-encoding", "").split(",")]
                encodings = [e for e in encodings if e and e != "identity"]
                unknown = [e for e in encodings if e not in _ENCODINGS]
                if unknown or len(encodings) > 2:
                    raise ReplyRefused(f"the reply is encoded {', '.join(encodings)!r}, which was not asked for "
                                       f"({_ACCEPT}); refused")
                length = response.headers.get("content-length", "").strip()
                if length.isdigit() and int(length) > MAX_REPLY_BYTES:
                    raise ReplyRefused(f"the reply announces {int(length)} bytes (Content-Length), more than the "
                                       f"{MAX_REPLY_BYTES} a reply may hold; refused")
            except BaseException:
                response.close()
                raise
            headers = response.headers
            if encodings:  # decoded here: httpx must not decode again, and the length is the encoded one
                headers = [(k, v) for k, v in response.headers.raw
                           if k.lower() not in (b"content-encoding", b"content-length")]
            return httpx.Response(response.status_code, headers=headers,
                                  stream=_Body(response.stream, encodings, deadline, seconds),
                                  extensions=response.extensions)

    class GuardedClient(httpx.Client):
        """A client whose requests each end within `seconds` (redirects and the whole body included) and whose
        replies are bounded (module docstring); proxies from the environment are honoured as httpx does."""

        def __init__(self, seconds: float, **kwargs):
            self.seconds = float(seconds)
            mounts = {pattern: None if proxy is None else proxy_transport(self.seconds, proxy)
                      for pattern, proxy in environment_proxies().items()}
            super().__init__(timeout=self.seconds, transport=GuardedTransport(self.seconds, **options()),
                             mounts=mounts, follow_redirects=True, **kwargs)

        def send(self, request: httpx.Request, **kwargs) -> httpx.Response:
            with _deadline(time.monotonic() + self.seconds, self.seconds):
                return super().send(request, **kwargs)

    def proxy_transport(seconds: float, proxy: str) -> GuardedTransport:
        try:
            return GuardedTransport(seconds, proxy=proxy, **options())
        except ImportError as e:  # a socks5:// proxy without the socksio package
            from degusta_learn.errors import DegustaError

            raise DegustaError(f"backend: the proxy in the environment ({proxy}) cannot be used: {e}") from None

    def options() -> dict:
        """The official clients' own: their connection limits, and TCP keep-alive (anthropic's) so that a
        connection dropped by a NAT on the way is noticed."""
        return {"limits": httpx.Limits(max_connections=1000, max_keepalive_connections=100),
                "socket_options": _keepalive()}

    return SimpleNamespace(Client=GuardedClient, Transport=GuardedTransport, DeadlineExceeded=DeadlineExceeded,
                           ReplyRefused=ReplyRefused, options=options)


def _keepalive() -> list[tuple[int, int, int]]:
    options = [(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)]
    for name, value in (("TCP_KEEPIDLE", 60), ("TCP_KEEPINTVL", 60), ("TCP_KEEPCNT", 5)):
        if hasattr(socket, name):
            options.append((socket.IPPROTO_TCP, getattr(socket, name), value))
    return options


def environment_proxies() -> dict[str, str | None]:
    """{URL pattern: proxy URL, or None for no proxy} from HTTP_PROXY / HTTPS_PROXY / ALL_PROXY / NO_PROXY, read as
    httpx reads them for a client it builds itself (a client given its own transport reads none)."""
    from urllib.request import getproxies

    info = getproxies()
    mounts: dict[str, str | None] = {}
    for scheme in ("http", "https", "all"):
        if info.get(scheme):
            url = info[scheme]
            mounts[f"{scheme}://"] = url if "://" in url else f"http://{url}"
    for host in (h.strip() for h in info.get("no", "").split(",")):
        if host == "*":
            return {}
        if not host:
            continue
        if "://" in host:
            mounts[host] = None
            continue
        try:
            ip = ipaddress.ip_address(host)
        except ValueError:
            ip = None
        if ip is not None:
            mounts[f"all://[{host}]" if ip.version == 6 else f"all://{host}"] = None
        else:
            mounts[f"all://{host}" if host.lower() == "localhost" else f"all://*{host}"] = None
    return mounts


def guarded_client(seconds: float, library=None):
    """The client a remote backend builds its official client on (module docstring), of the httpx flavour the
    client library `library` (a module: openai, anthropic) takes."""
    return _flavour(flavour_of(library)).Client(seconds)


def guarded_transport(seconds: float, library=None):
    """The transport alone, for a client library that builds its own client (each hop keeps the deadline)."""
    ns = _flavour(flavour_of(library))
    return ns.Transport(seconds, **ns.options())

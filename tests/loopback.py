"""A real HTTP server on 127.0.0.1 for the tests that talk to a model API over the wire.

`Loopback(reply)` serves GET and POST in a thread. Every request is recorded in `requests` as
{"method", "path", "headers" (a dict, names lowercased), "body" (the parsed JSON, or None)}, then answered
by the first entry of `script` if there is one, else by `reply(request)`. A reply is
`(status, content_type, data)` or `(status, content_type, data, headers)`, where `data` is bytes or a
callable(request) -> bytes, or `raw(write)`: `write(handler)` then writes the whole response itself on the
socket (`handler.wfile`), for servers that misbehave below JSON: a trickled status line or body, an endless
chunked body, a compressed bomb, a request that is never answered (`trickle_status`, `trickle_headers`,
`trickle_body`, `endless_chunks`, `stall`, `compressed`, `gzip_bomb`). Every misbehaving writer is bounded: it stops when the
client hangs up, when `close()` is called, or after `MAX_MISBEHAVE_S`, so a test never leaves a thread behind.
"""

from __future__ import annotations

import json
import threading
import time
import zlib
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

MAX_MISBEHAVE_S = 30.0
"""The longest any misbehaving writer keeps a connection (a client without a deadline is cut off then)."""


class _Raw:
    def __init__(self, write):
        self.write = write


def raw(write) -> _Raw:
    """A reply written by `write(handler)` byte by byte on the socket (status line, headers and body)."""
    return _Raw(write)


class _Server(ThreadingHTTPServer):
    daemon_threads = True

    def handle_error(self, request, client_address):  # a client that hung up on a misbehaving reply: expected
        pass


class Loopback:
    """HTTP on 127.0.0.1 (`root`; `url` is `root + "/v1"`, the OpenAI-style base URL); `close()` when done."""

    def __init__(self, reply):
        self.respond, self.script, self.requests, self.lock = reply, [], [], threading.Lock()
        self.closing = threading.Event()
        server = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self):
                size = int(self.headers.get("Content-Length") or 0)
                data = self.rfile.read(size) if size else b""
                try:
                    body = json.loads(data) if data else None
                except ValueError:
                    body = None
                headers = {k.lower(): v for k, v in self.headers.items()}
                req = {"method": self.command, "path": self.path, "headers": headers, "body": body}
                with server.lock:
                    server.requests.append(req)
                    answer = server.script.pop(0) if server.script else server.respond(req)
                self.closing = server.closing
                if isinstance(answer, _Raw):
                    self.close_connection = True
                    answer.write(self)
                    return
                status, ctype, data, *extra = answer
                data = data(req) if callable(data) else data
                if isinstance(data, _Raw):
                    self.close_connection = True
                    data.write(self)
                    return
                self.send_response(status)
                self.send_header("Content-Type", ctype)
                for k, v in (extra[0] if extra else {}).items():
                    self.send_header(k, v)
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)

            do_GET = do_POST

            def log_message(self, *args):
                pass

        self.httpd = _Server(("127.0.0.1", 0), Handler)
        self.root = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        self.url = self.root + "/v1"
        threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.02}, daemon=True).start()

    def close(self):
        self.closing.set()
        self.httpd.shutdown()
        self.httpd.server_close()


def json_reply(status: int, payload, headers: dict | None = None) -> tuple:
    """A reply carrying `payload` as JSON."""
    return status, "application/json", json.dumps(payload).encode(), headers or {}


def chat_completion(model: str, contents: list[str], prompt_tokens: int = 100,
                    completion_tokens: int | None = None) -> dict:
    """An OpenAI chat-completions response, one choice per text; 10 completion tokens a choice by default."""
    completion_tokens = 10 * len(contents) if completion_tokens is None else completion_tokens
    choices = [{"index": i, "message": {"role": "assistant", "content": text}, "finish_reason": "stop"}
               for i, text in enumerate(contents)]
    return {"id": "chatcmpl-x", "object": "chat.completion", "created": 0, "model": model, "choices": choices,
            "usage": {"prompt_tokens": prompt_tokens, "completion_tokens": completion_tokens,
                      "total_tokens": prompt_tokens + completion_tokens}}


# ----------------------------------------------------------------------------- misbehaving replies

def _drip(handler, data: bytes, delay: float, started: float | None = None) -> bool:
    """Write `data` one byte every `delay` seconds; False once the client hung up or the test is over."""
    started = time.monotonic() if started is None else started
    for i in range(len(data)):
        if handler.closing.is_set() or time.monotonic() - started > MAX_MISBEHAVE_S:
            return False
        try:
            handler.wfile.write(data[i:i + 1])
            handler.wfile.flush()
        except OSError:
            return False
        handler.closing.wait(delay)
    return True


def _head(status: int = 200, headers: dict | None = None) -> bytes:
    lines = [f"HTTP/1.1 {status} OK", *(f"{k}: {v}" for k, v in (headers or {}).items()), "", ""]
    return "\r\n".join(lines).encode()


def trickle_status(delay: float = 0.05) -> _Raw:
    """A status line sent one byte every `delay` s, and never finished (each read sees a byte: a per-read
    timeout never fires)."""
    def write(handler):
        started = time.monotonic()
        while _drip(handler, b"HTTP/1.1 200 OK", delay, started):
            pass
    return raw(write)


def trickle_headers(delay: float = 0.05) -> _Raw:
    """A complete status line, then one header that never ends, a byte every `delay` s."""
    def write(handler):
        started = time.monotonic()
        if _drip(handler, b"HTTP/1.1 200 OK\r\nContent-Type: application/json\r\nX-Slow: ", 0.0, started):
            while _drip(handler, b"abcdefgh", delay, started):
                pass
    return raw(write)


def trickle_body(payload: bytes, delay: float = 0.05, headers: dict | None = None) -> _Raw:
    """Correct headers, then the body (`payload`) one byte every `delay` s."""
    def write(handler):
        head = _head(200, {"Content-Type": "application/json", "Content-Length": len(payload), **(headers or {})})
        try:
            handler.wfile.write(head)
        except OSError:
            return
        _drip(handler, payload, delay)
    return raw(write)


def endless_chunks(chunk: bytes = b" " * 1024, delay: float = 0.0) -> _Raw:
    """A chunked body that never ends: `chunk` after `chunk`, `delay` s apart."""
    def write(handler):
        started = time.monotonic()
        try:
            handler.wfile.write(_head(200, {"Content-Type": "application/json", "Transfer-Encoding": "chunked"}))
            opening = b'{"choices": ['
            handler.wfile.write(b"%x\r\n%s\r\n" % (len(opening), opening))
            while not handler.closing.is_set() and time.monotonic() - started < MAX_MISBEHAVE_S:
                handler.wfile.write(b"%x\r\n%s\r\n" % (len(chunk), chunk))
                if delay:
                    handler.closing.wait(delay)
        except OSError:
            return
    return raw(write)


def stall(seconds: float = MAX_MISBEHAVE_S) -> _Raw:
    """Read the request, then answer nothing (until the client hangs up or the test ends)."""
    def write(handler):
        handler.closing.wait(min(seconds, MAX_MISBEHAVE_S))
    return raw(write)


def compressed(body: bytes, encoding: str, status: int = 200, content_length: int | None = None) -> _Raw:
    """`body` (already encoded) sent with `Content-Encoding: encoding` (and a Content-Length, possibly a lie)."""
    def write(handler):
        head = _head(status, {"Content-Type": "application/json", "Content-Encoding": encoding,
                              "Content-Length": len(body) if content_length is None else content_length})
        try:
            handler.wfile.write(head)
            for i in range(0, len(body), 1 << 16):
                if handler.closing.is_set():
                    return
                handler.wfile.write(body[i:i + (1 << 16)])
        except OSError:
            return
    return raw(write)


_BOMBS: dict = {}


def gzip_bomb(inflated_mib: int = 1024, wbits: int = 31) -> bytes:
    """A gzip (wbits 31; 15: zlib 'deflate'; -15: raw deflate) stream of `inflated_mib` MiB of zeros, about
    1 KiB on the wire per MiB, built in milliseconds: one compressed MiB of zeros repeated (a full flush resets
    the compressor, so every block after the first is the same bytes). Its trailer is not valid (the
    checksum is never reached by a reader that stops early; a reader that inflates it all fails at the end)."""
    key = (inflated_mib, wbits)
    if key not in _BOMBS:
        zeros = bytes(1 << 20)
        c = zlib.compressobj(9, zlib.DEFLATED, wbits)
        first = c.compress(zeros) + c.flush(zlib.Z_FULL_FLUSH)
        block = c.compress(zeros) + c.flush(zlib.Z_FULL_FLUSH)
        _BOMBS[key] = first + block * (inflated_mib - 1) + c.flush()
    return _BOMBS[key]

"""A real HTTP server on 127.0.0.1 for the tests that talk to a model API over the wire.

`Loopback(reply)` serves GET and POST in a thread. Every request is recorded in `requests` as
{"method", "path", "headers" (a dict, names lowercased), "body" (the parsed JSON, or None)}, then answered
by the first entry of `script` if there is one, else by `reply(request)`. A reply is
`(status, content_type, data)` or `(status, content_type, data, headers)`, where `data` is bytes or a
callable(request) -> bytes.
"""

from __future__ import annotations

import json
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer


class Loopback:
    """HTTP on 127.0.0.1 (`root`; `url` is `root + "/v1"`, the OpenAI-style base URL); `close()` when done."""

    def __init__(self, reply):
        self.respond, self.script, self.requests, self.lock = reply, [], [], threading.Lock()
        server = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self):
                size = int(self.headers.get("Content-Length") or 0)
                body = json.loads(self.rfile.read(size)) if size else None
                headers = {k.lower(): v for k, v in self.headers.items()}
                req = {"method": self.command, "path": self.path, "headers": headers, "body": body}
                with server.lock:
                    server.requests.append(req)
                    answer = server.script.pop(0) if server.script else server.respond(req)
                status, ctype, data, *extra = answer
                data = data(req) if callable(data) else data
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

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.root = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        self.url = self.root + "/v1"
        threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.02}, daemon=True).start()

    def close(self):
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

"""A stand-in for the Hugging Face Hub on 127.0.0.1: the few endpoints `huggingface_hub.snapshot_download` uses.

It serves model repositories from local folders (`repos={"acme/tiny-vlm": Path(...)}`) with the headers the real
Hub sends (`X-Repo-Commit`, `ETag`, `X-Error-Code: RepoNotFound` on a 404), so that the real
huggingface_hub client downloads into a real cache (point `HF_ENDPOINT` at `hub.url` and `HF_HOME` at a temporary
folder, in a subprocess with `HF_HUB_OFFLINE=0`). Nothing leaves the machine. `hub.requests` records the paths asked.

Usage:
    with FakeHub({"acme/tiny-vlm": folder}) as hub:
        subprocess.run([...], env={**os.environ, "HF_ENDPOINT": hub.url, "HF_HUB_OFFLINE": "0", "HF_HOME": ...})
"""

from __future__ import annotations

import hashlib
import json
import re
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import unquote, urlparse


def _sha1(data: bytes) -> str:
    return hashlib.sha1(b"blob %d\0" % len(data) + data).hexdigest()  # git's blob id, as the Hub reports it


class FakeHub:
    def __init__(self, repos: dict[str, Path]):
        self.repos = {name: Path(folder) for name, folder in repos.items()}
        self.commits = {name: hashlib.sha1(name.encode()).hexdigest() for name in repos}
        self.requests: list[str] = []
        hub = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args):  # quiet
                pass

            def do_HEAD(self):
                hub._serve(self, body=False)

            def do_GET(self):
                hub._serve(self, body=True)

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"
        self._thread = threading.Thread(target=self.server.serve_forever, daemon=True)

    def __enter__(self) -> FakeHub:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.server.shutdown()
        self.server.server_close()

    def _files(self, name: str) -> dict[str, bytes]:
        root = self.repos[name]
        return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}

    def _serve(self, h: BaseHTTPRequestHandler, body: bool) -> None:
        path = unquote(urlparse(h.path).path)
        self.requests.append(f"{h.command} {path}")
        info = re.fullmatch(r"/api/models/([^/]+/[^/]+)(?:/revision/([^/]+))?", path)
        tree = re.fullmatch(r"/api/models/([^/]+/[^/]+)/tree/([^/]+)(?:/.*)?", path)
        resolve = re.fullmatch(r"/([^/]+/[^/]+)/resolve/([^/]+)/(.+)", path)
        repo = next((m.group(1) for m in (info, tree, resolve) if m), None)
        if repo not in self.repos:
            return self._send(h, 404, b'{"error": "Repository not found"}', body,
                              {"X-Error-Code": "RepoNotFound", "Content-Type": "application/json"})
        files, commit = self._files(repo), self.commits[repo]
        if info:
            data = {"id": repo, "modelId": repo, "sha": commit, "private": False, "gated": False, "disabled": False,
                    "siblings": [{"rfilename": f} for f in files], "tags": [], "downloads": 0, "likes": 0}
            return self._send(h, 200, json.dumps(data).encode(), body, {"Content-Type": "application/json"})
        if tree:
            entries = [{"type": "file", "oid": _sha1(d), "size": len(d), "path": f} for f, d in files.items()]
            return self._send(h, 200, json.dumps(entries).encode(), body, {"Content-Type": "application/json"})
        name = resolve.group(3)
        if name not in files:
            return self._send(h, 404, b'{"error": "Entry not found"}', body,
                              {"X-Error-Code": "EntryNotFound", "Content-Type": "application/json"})
        data = files[name]
        return self._send(h, 200, data, body, {"X-Repo-Commit": commit, "ETag": f'"{_sha1(data)}"',
                                               "Content-Type": "application/octet-stream"})

    @staticmethod
    def _send(h: BaseHTTPRequestHandler, status: int, data: bytes, body: bool, headers: dict) -> None:
        h.send_response(status)
        for k, v in {**headers, "Content-Length": str(len(data))}.items():
            h.send_header(k, v)
        h.end_headers()
        if body:
            h.wfile.write(data)

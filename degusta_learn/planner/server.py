"""`degusta serve`: a planner over HTTP (FastAPI on uvicorn), for a robot stack to call.

Usage:
    degusta serve --config baseline_consensus                      # http://127.0.0.1:8000
    curl -s -X POST http://127.0.0.1:8000/plan -d '{"participant": "p004", "table": 2}'
    curl -s http://127.0.0.1:8000/health ; curl -s http://127.0.0.1:8000/openapi.json

- `POST /plan`: a plan request (JSON) -> the plan (JSON). A malformed request gets 400 with `{"detail": LINE}`, LINE
  the one line `degusta plan` prints for it; a body over MAX_REQUEST_BYTES gets 413, refused from its Content-Length
  before it is read (or as soon as a chunked body passes the limit); the server goes on serving either way. A
  zero-shot method whose backend gave no answer (its API server kept failing, a budget was reached) gets 503. A fault
  of the planner itself (a bug) gets 500 with one line; its traceback goes to the server's log only.
- `GET /health`: status, method, config, its fingerprint and the request limits.
- `GET /openapi.json` (and the pages /docs, /redoc): the API, with the request and plan schemas (planner/schema.py).

One planner (one model in memory) serves every request: requests are read concurrently, planned one at a time
under the planner's lock (a worker thread each, so the server keeps answering /health meanwhile). Connections beyond
`limit_concurrency` get 503. The server has no authentication: it binds 127.0.0.1 unless told otherwise, and it
never reads a dataset folder a request names (`read_paths=False`).
"""

import logging
import traceback

from degusta_learn.errors import DegustaError
from degusta_learn.planner.planner import BackendUnavailable, Planner
from degusta_learn.planner.request import LIMITS, MAX_REQUEST_BYTES, too_large
from degusta_learn.planner.schema import ERROR_SCHEMA, PLAN_SCHEMA, REQUEST_SCHEMA
from degusta_learn.webio import BodyTooLarge, check_bindable, read_body

LIMIT_CONCURRENCY = 64
"""Open connections the server accepts at once (more get 503): bounds the bodies held in memory."""

log = logging.getLogger("degusta.serve")


def error_line(e: BaseException) -> str:
    """The one line `degusta` prints for a DegustaError (cli.main), for a 4xx body."""
    from degusta_learn.prompting.backends.base import redact
    from degusta_learn.textsafe import one_line

    return one_line(redact(str(e)), limit=None)


def create_app(planner: Planner, max_body: int = MAX_REQUEST_BYTES):
    """The FastAPI app serving `planner` (module docstring)."""
    from fastapi import FastAPI, Request
    from fastapi.responses import JSONResponse
    from fastapi.concurrency import run_in_threadpool  # starlette's, re-exported: fastapi is what we declare

    from degusta_learn import __version__

    app = FastAPI(title="degusta planner", version=__version__,
                  description="Plans for setting a table as a person likes it (docs/planner.md). Method: "
                              f"{planner.method} (config {planner.name}).")

    def error(status: int, line: str) -> JSONResponse:
        return JSONResponse({"detail": line}, status_code=status)

    @app.get("/health")
    def health() -> dict:
        return {"status": "ok", "method": planner.method, "config": planner.name,
                "config_sha256": planner.config_sha256, "limits": {**LIMITS, "request_bytes": max_body}}

    def body(description: str) -> dict:
        return {"description": description, "content": {"application/json": {"schema": ERROR_SCHEMA}}}

    @app.post("/plan", summary="Plan a table", responses={
        200: {"description": "The plan", "content": {"application/json": {"schema": PLAN_SCHEMA}}},
        400: body("A malformed request: the line `degusta plan` prints"),
        413: body("A request over the size limit"),
        503: body("A zero-shot method's backend gave no answer (a server kept failing, a budget was reached)"),
        500: body("A fault of the planner (a bug); the server's log has the traceback")},
        openapi_extra={"requestBody": {"required": True,
                                       "content": {"application/json": {"schema": REQUEST_SCHEMA}}}})
    async def plan(request: Request):
        try:
            data = await read_body(request, max_body, lambda size, read: too_large(size, max_body, read=read))
        except BodyTooLarge as e:
            return error(413, str(e))
        except DegustaError as e:
            return error(400, str(e))
        try:
            result = await run_in_threadpool(planner.plan, data)
        except BackendUnavailable as e:
            return error(503, error_line(e))
        except DegustaError as e:
            return error(400, error_line(e))
        except Exception as e:  # noqa: BLE001 - a bug: one line to the client, the traceback to the log
            log.error("POST /plan failed:\n%s", traceback.format_exc())
            return error(500, f"internal error of the planner ({type(e).__name__}); the server's log has the "
                              "traceback")
        return JSONResponse(result.to_json())

    return app


def serve(planner: Planner, host: str = "127.0.0.1", port: int = 8000, log_line=print) -> None:
    """Serve `planner` on host:port until Ctrl-C or SIGTERM (uvicorn)."""
    try:
        import fastapi  # noqa: F401
        import uvicorn
    except ImportError as e:
        raise DegustaError(f"degusta serve needs FastAPI and uvicorn ({e.name} is not installed): "
                           "pip install 'degusta_learn[serve]'") from None

    check_bindable(host, port)
    if host not in ("127.0.0.1", "localhost", "::1"):
        log_line(f"note: serving on {host}: the planner has no authentication, so anyone who reaches this address "
                 "can ask it for plans")
    log_line(f"serving {planner.method} (config {planner.name}) on http://{host}:{port}: POST /plan, GET /health, "
             "GET /openapi.json; Ctrl-C stops")
    config = uvicorn.Config(create_app(planner), host=host, port=port, log_level="warning",
                            limit_concurrency=LIMIT_CONCURRENCY, timeout_keep_alive=5)
    uvicorn.Server(config).run()


__all__ = ["LIMIT_CONCURRENCY", "create_app", "error_line", "serve"]

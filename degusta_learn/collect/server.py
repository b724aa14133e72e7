"""`degusta collect`: the study's web application (FastAPI on uvicorn), the HTTP interface of docs/collect_api.md.

Usage:
    degusta collect --dataset studies/lab1 --new          # http://127.0.0.1:8765, the researcher's key printed

- The participant page (`/`, `/static/*`) and its JSON interface (`/api/*`): a session is an HttpOnly, SameSite=Strict
  cookie holding a random token; the server keeps only its SHA-256 (store.py). Every POST and PUT must be
  `application/json` (a form on another site cannot send it) and at most MAX_BODY bytes.
- The researcher's pages (`/research`, `/research/export`) need the key printed at start (or set in
  DEGUSTA_COLLECT_KEY); it lives in memory only.
- Every answer carries a Content-Security-Policy that allows only this server's own script, style and pictures (no
  inline script), so text from a dataset or a participant cannot run as code even where a page forgot to escape it.
- A request the study refuses gets a 4xx with `{"detail": LINE}`: 400 malformed, 401 no session, 403 wrong key,
  409 a step that is not the current one, 413 too large, 415 not JSON. Nothing is written for any of them, and
  the server goes on serving. A fault of the server itself gets 500 with one line; the traceback goes to its log.
"""

import hmac
import logging
import traceback
from importlib.resources import files

from degusta_learn.collect.images import StudyImages
from degusta_learn.collect.research import export_zip, progress_page
from degusta_learn.collect.store import Conflict, NoSession, StudyStore
from degusta_learn.collect.study import Study
from degusta_learn.errors import DegustaError
from degusta_learn.webio import BodyTooLarge, read_body, strict_json

MAX_BODY = 256 * 1024
"""Bytes of a request body (64 placements are ~5 KB)."""
COOKIE = "degusta_session"
COOKIE_DAYS = 30
CSP = ("default-src 'self'; img-src 'self' data:; style-src 'self'; script-src 'self'; object-src 'none'; "
       "base-uri 'none'; frame-ancestors 'none'; form-action 'self'")
STATIC = {"app.js": "text/javascript; charset=utf-8", "app.css": "text/css; charset=utf-8"}
LIMIT_CONCURRENCY = 100

log = logging.getLogger("degusta.collect")


def _object_label(obj) -> str:
    colours = obj.color1 if obj.color2 in (None, obj.color1) else f"{obj.color1} and {obj.color2}"
    material = obj.material1 if obj.material2 in (None, obj.material1) else f"{obj.material1} and {obj.material2}"
    return f"{colours} {material} {obj.type}, {obj.shape}, {obj.pattern}"


def study_description(study: Study, images: StudyImages) -> dict:
    """GET /api/study: what the page draws (docs/collect_api.md)."""
    from degusta_learn.scene.catalog import object_size

    cfg = study.config
    types = sorted({o.type for o in study.catalog.objects})
    return {
        "title": cfg.title, "instructions": study.instructions, "min_objects": study.min_objects,
        "trials": cfg.tables_per_participant, "self_evaluation": cfg.self_evaluation,
        "participant_ids": cfg.participant_ids,
        "types": [{"type": t, "icon": f"/img/type/{t}.png", "count": sum(o.type == t for o in study.catalog.objects)}
                  for t in types],
        "objects": [{"id": o.id, "type": o.type, "label": _object_label(o), "image": f"/img/object/{o.id}.png",
                     "width": object_size(o)[0], "length": object_size(o)[1]} for o in study.catalog.objects],
        "tables": [{"id": t.id, "name": t.name, "width": images.table_size(t.id)[0],
                    "height": images.table_size(t.id)[1], "surface": [list(p) for p in t.surface],
                    "image": f"/img/table/{t.id}.png"} for t in (study.tables[i] for i in study.shown_tables)],
    }


def create_app(study: Study, researcher_key: str, store: "StudyStore | None" = None):
    """The FastAPI app of one study (module docstring). `researcher_key` opens /research."""
    from fastapi import FastAPI, Request
    from fastapi.concurrency import run_in_threadpool
    from fastapi.responses import JSONResponse, Response

    from degusta_learn import __version__

    store = store or StudyStore(study)
    images = StudyImages(study)
    description = study_description(study, images)
    page = files("degusta_learn.collect").joinpath("static", "index.html").read_bytes()
    app = FastAPI(title="degusta collect", version=__version__, docs_url=None, redoc_url=None, openapi_url=None)

    def error(status: int, line: str) -> JSONResponse:
        return JSONResponse({"detail": line}, status_code=status)

    @app.middleware("http")
    async def headers(request: Request, call_next):
        try:
            response = await call_next(request)
        except Exception as e:  # noqa: BLE001 - a bug: one line to the client, the traceback to the log
            log.error("%s %s failed:\n%s", request.method, request.url.path, traceback.format_exc())
            response = error(500, f"internal error of the study server ({type(e).__name__}); its log has the "
                                  "traceback")
        response.headers["Content-Security-Policy"] = CSP
        response.headers["X-Content-Type-Options"] = "nosniff"
        response.headers["Referrer-Policy"] = "no-referrer"
        response.headers["X-Frame-Options"] = "DENY"
        if request.url.path.startswith(("/api/", "/research")):
            response.headers["Cache-Control"] = "no-store"
        return response

    async def json_body(request: Request, what: str):
        kind = request.headers.get("content-type", "").split(";")[0].strip().lower()
        if kind != "application/json":
            raise _Refused(415, f"{what}: expected Content-Type application/json, got {kind[:60] or 'none'}")
        try:
            data = await read_body(request, MAX_BODY, lambda size, read: (
                f"{what}: {'more than ' if read else ''}{size:,} bytes, over the limit of {MAX_BODY:,}"))
        except BodyTooLarge as e:
            raise _Refused(413, str(e)) from None
        return strict_json(data, what)

    def refusals(handler):
        async def wrapped(request: Request):
            try:
                return await handler(request)
            except _Refused as e:
                return error(e.status, e.line)
            except NoSession as e:
                return error(401, str(e))
            except Conflict as e:
                return error(409, str(e))
            except DegustaError as e:
                return error(400, str(e))
        wrapped.__name__ = handler.__name__
        return wrapped

    def session_of(request: Request):
        return store.session(request.cookies.get(COOKIE))

    def state_response(st, replayed: bool = False, token: str | None = None) -> JSONResponse:
        response = JSONResponse(st.public(study.min_objects, replayed))
        if token is not None:
            response.set_cookie(COOKIE, token, max_age=COOKIE_DAYS * 86400, httponly=True, samesite="strict",
                                path="/")
        return response

    @app.get("/")
    def index() -> Response:
        return Response(page, media_type="text/html; charset=utf-8")

    @app.get("/static/{name}")
    def static(name: str) -> Response:
        if name not in STATIC:
            return error(404, f"no static file {name[:60]!r}")
        return Response(files("degusta_learn.collect").joinpath("static", name).read_bytes(), media_type=STATIC[name])

    @app.get("/api/study")
    def api_study() -> dict:
        return description

    def picture(data: bytes | None, what: str) -> Response:
        if data is None:
            return error(404, f"no {what}")
        return Response(data, media_type="image/png", headers={"Cache-Control": "public, max-age=86400"})

    @app.get("/img/object/{object_id}.png")
    async def object_image(object_id: int) -> Response:
        return picture(await run_in_threadpool(images.object_png, object_id), f"object {object_id}")

    @app.get("/img/table/{table_id}.png")
    async def table_image(table_id: int) -> Response:
        return picture(await run_in_threadpool(images.table_png, table_id), f"table {table_id}")

    @app.get("/img/type/{type_}.png")
    async def type_image(type_: str) -> Response:
        return picture(await run_in_threadpool(images.type_png, type_), f"object type {type_[:40]!r}")

    @app.post("/api/session")
    @refusals
    async def api_session(request: Request):
        body = await json_body(request, "session")
        try:
            return state_response(session_of(request))  # already in a session: resume it
        except NoSession:
            pass
        if not isinstance(body, dict):
            raise DegustaError("session: expected a JSON object such as {} or {\"participant\": \"p01\"}")
        unknown = sorted(set(body) - {"participant"})
        if unknown:
            raise DegustaError(f"session: unknown key {unknown[0][:40]!r} (expected only participant)")
        token, st = await run_in_threadpool(store.start, body.get("participant"))
        return state_response(st, token=token)

    @app.get("/api/state")
    @refusals
    async def api_state(request: Request):
        return state_response(session_of(request))

    @app.put("/api/draft")
    @refusals
    async def api_draft(request: Request):
        st = session_of(request)
        body = await json_body(request, "draft")
        await run_in_threadpool(store.save_draft, st, body)
        return JSONResponse({"saved": True})

    @app.post("/api/submit")
    @refusals
    async def api_submit(request: Request):
        st = session_of(request)
        body = await json_body(request, "submission")
        st, replayed = await run_in_threadpool(store.submit, st, body)
        return state_response(st, replayed)

    def researcher(request: Request) -> None:
        given = request.query_params.get("key") or request.headers.get("authorization", "").removeprefix("Bearer ")
        if not given or not hmac.compare_digest(given.encode(), researcher_key.encode()):
            raise _Refused(403, "research: the researcher's key is missing or wrong (it is printed when "
                                "degusta collect starts)")

    @app.get("/research")
    @refusals
    async def research(request: Request):
        researcher(request)
        return Response(progress_page(study, store.progress(), researcher_key), media_type="text/html; charset=utf-8")

    @app.get("/research/export")
    @refusals
    async def research_export(request: Request):
        researcher(request)
        complete = request.query_params.get("complete") in ("1", "true", "yes")
        data = await run_in_threadpool(export_zip, study, store, complete)
        name = f"{study.root.name}{'-complete' if complete else ''}.zip"
        return Response(data, media_type="application/zip",
                        headers={"Content-Disposition": f'attachment; filename="{name}"'})

    app.state.store = store
    return app


class _Refused(Exception):
    def __init__(self, status: int, line: str):
        super().__init__(line)
        self.status, self.line = status, line


LOCAL_HOSTS = ("127.0.0.1", "localhost", "::1")


def serve(study: Study, researcher_key: str, host: str = "127.0.0.1", port: int = 8765, log_line=print) -> None:
    """Serve the study on host:port until Ctrl-C or SIGTERM (uvicorn)."""
    try:
        import fastapi  # noqa: F401
        import uvicorn
    except ImportError as e:
        raise DegustaError(f"degusta collect needs FastAPI and uvicorn ({e.name} is not installed): "
                           "pip install 'degusta_learn[serve]'") from None
    app = create_app(study, researcher_key)
    store = app.state.store
    shown = f"[{host}]" if ":" in host else host
    if host in LOCAL_HOSTS:
        log_line(f"serving the study on http://{shown}:{port}/ (this machine only: --host 0.0.0.0 lets other "
                 "machines of the lab reach it)")
    else:
        log_line(f"serving the study on http://{shown}:{port}/ to every machine that can reach this address; "
                 "participants' sessions are cookies, the researcher's pages need the key")
    done = sum(p["finished"] for p in store.progress())
    log_line(f"study folder {study.root}: {len(study.arrangements)} arrangements, {done} participants finished; "
             f"{study.config.tables_per_participant} tables each, at least {study.min_objects} objects")
    log_line(f"researcher's progress page: http://{shown}:{port}/research?key={researcher_key}  (export: "
             f"/research/export?key=...); Ctrl-C stops")
    config = uvicorn.Config(app, host=host, port=port, log_level="warning", limit_concurrency=LIMIT_CONCURRENCY,
                            timeout_keep_alive=5)
    uvicorn.Server(config).run()


__all__ = ["COOKIE", "CSP", "LOCAL_HOSTS", "MAX_BODY", "create_app", "serve", "study_description"]

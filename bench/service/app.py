"""The HTTP + websocket API (FastAPI: OpenAPI at /openapi.json built from the pydantic models, websockets and
Starlette's test client included; served by uvicorn).

Every request but GET /api/health and the login page carries a token (`Authorization: Bearer`, or the UI's
cookie); AuthMiddleware answers 401 before any route runs, so a new endpoint cannot forget it. Roles are checked
per endpoint (403).
"""

from __future__ import annotations

import asyncio
import gc
import errno
import threading
from contextlib import asynccontextmanager
from dataclasses import asdict
from http.cookies import SimpleCookie
from typing import Any, Callable

import anyio
from fastapi import Body, Depends, FastAPI, Request, WebSocket, WebSocketDisconnect
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, Response
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException

from bench.service.auth import COOKIE, ROLES, Principal, bearer, create_token
from bench.service.core import MEDIA, Service, ServiceSettings
from bench.service.errors import ApiError, bad_input
from bench.service.guard import BodyLimitMiddleware, ReadCache, api_answers, rate_limited_accept_errors
from bench.service.limits import MAX_SCENARIO_CHARS
from bench.service.params import MAX_ID, Id
from bench.service.leases import extend, lease_dict, release, reserve, active_leases
from bench.service.queue import Submission, submit

PUBLIC = {("GET", "/api/health"), ("GET", "/login"), ("POST", "/login"), ("GET", "/openapi.json"), ("GET", "/docs"),
          ("GET", "/docs/swagger-ui-bundle.js"), ("GET", "/docs/swagger-ui.css")}
READ_METHODS = ("GET", "HEAD", "OPTIONS")


class AuthMiddleware:
    """Resolves the token of every HTTP and websocket request to a Principal in scope["state"]["principal"]."""

    def __init__(self, app, service_getter):
        self.app = app
        self.service_getter = service_getter

    async def __call__(self, scope, receive, send):
        if scope["type"] not in ("http", "websocket"):
            return await self.app(scope, receive, send)
        method = scope.get("method", "GET")
        if (method, scope["path"]) in PUBLIC or (method == "HEAD" and ("GET", scope["path"]) in PUBLIC):
            return await self.app(scope, receive, send)
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
        token = bearer(headers.get("authorization"))
        if token is None and "cookie" in headers:
            jar = SimpleCookie()
            try:
                jar.load(headers["cookie"])
            except Exception:
                jar = SimpleCookie()
            token = jar[COOKIE].value if COOKIE in jar else None
        service: Service = self.service_getter()
        principal = await service.tokens.resolve(token) if token else None
        if principal is None:
            return await self._deny(scope, receive, send, "a valid token is needed (Authorization: Bearer TOKEN)"
                                    if token is None else "unknown or revoked token")
        scope.setdefault("state", {})["principal"] = principal
        if (scope["type"] == "http" and method not in READ_METHODS and scope["path"].startswith("/api/")
                and not principal.at_least("operator")):
            # a viewer only reads: refused before its body is read (a 100 MB body cost the service 300 MB)
            response = JSONResponse({"detail": f"{principal.role} token {principal.name!r}: this needs the "
                                               f"operator role"}, status_code=403)
            return await response(scope, receive, send)
        return await self.app(scope, receive, send)

    async def _deny(self, scope, receive, send, message: str):
        if scope["type"] == "websocket":
            await receive()          # websocket.connect
            if "websocket.http.response" in scope.get("extensions", {}):
                response = JSONResponse({"detail": message}, status_code=401)
                await send({"type": "websocket.http.response.start", "status": 401,
                            "headers": response.raw_headers})
                await send({"type": "websocket.http.response.body", "body": response.body})
            else:
                await send({"type": "websocket.close", "code": 4401, "reason": "unauthorized"})
            return
        if scope["path"].startswith(("/api/", "/live/")) or scope["path"] in ("/openapi.json", "/metrics"):
            response = JSONResponse({"detail": message}, status_code=401, headers={"WWW-Authenticate": "Bearer"})
        else:
            from fastapi.responses import RedirectResponse
            response = RedirectResponse("/login", status_code=303)
        await response(scope, receive, send)


def principal(request: Request) -> Principal:
    return request.scope["state"]["principal"]


def role(needed: str):
    def check(request: Request) -> Principal:
        who = principal(request)
        if not who.at_least(needed):
            raise ApiError(403, f"{who.role} token {who.name!r}: this needs the {needed} role")
        return who
    check.__name__ = f"role_{needed}"
    return check


viewer, operator, admin = role("viewer"), role("operator"), role("admin")


# --- request bodies ----------------------------------------------------------------------------------------

class RunSubmit(BaseModel):
    scenario: str | None = Field(None, description="a scenario path under the service's scenario root")
    scenario_toml: str | None = Field(None, max_length=MAX_SCENARIO_CHARS, description="the scenario file's text")
    filename: str | None = Field(None, description="how error lines name scenario_toml")
    rig: str | None = None
    tag: str | None = None
    seed: int | None = Field(None, ge=0, le=MAX_ID)


class LeaseRequest(BaseModel):
    ttl_s: float = Field(..., description="seconds until the lease expires unless extended")
    reason: str | None = ""


class ExtendRequest(BaseModel):
    ttl_s: float | None = None


class RigPatch(BaseModel):
    enabled: bool


class TokenRequest(BaseModel):
    name: str = Field(..., min_length=1, max_length=200)
    role: str


def _validation_lines(exc: RequestValidationError) -> list[str]:
    lines = []
    for err in exc.errors():
        loc = [str(x) for x in err.get("loc", ())]
        where = ".".join(loc[1:]) if loc and loc[0] in ("body", "query", "path") else ".".join(loc)
        lines.append(f"request: {where or '(body)'}: {err.get('msg', 'invalid')}")
    return lines


EXPORTS = threading.BoundedSemaphore(2)
EXPORT_MEDIA = {"mf4": "application/octet-stream", "csv": "text/csv"}


def create_app(settings: ServiceSettings | None = None, service: Service | None = None) -> FastAPI:
    holder: dict[str, Service] = {}

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        svc = service or Service(settings)
        holder["service"] = svc
        app.state.service = svc
        svc.events.bind(asyncio.get_running_loop())
        svc.events.on_shown = answers.show
        svc.events.on_changed = answers.changed
        rate_limited_accept_errors(asyncio.get_running_loop())
        svc.start()
        # what start-up left alive (the web stack, the ORM, the migrations) out of the collector's generations: a full
        # collection walked all of it, 166-372 ms with the event loop stopped (benchmarks/service.py, measured)
        gc.collect()
        gc.freeze()
        try:
            yield
        finally:
            await anyio.to_thread.run_sync(svc.stop)

    # FastAPI's native OpenTelemetry off: the service exports its own /metrics, and the per-request check of
    # whether a provider is configured was about 3 % of its CPU per cached answer (py-spy, benchmarks/service_abuse.py)
    app = FastAPI(title="drivebench bench service", version="1", lifespan=lifespan, docs_url=None,
                  redoc_url=None, openapi_url="/openapi.json",
                  telemetry={"tracing": False, "metrics": False, "logs": False, "operation_spans": False})
    answers = api_answers()
    app.add_middleware(ReadCache, generation=lambda: holder["service"].events.generation,
                       changed=lambda: holder["service"].events.changed(), answers=answers)
    app.add_middleware(BodyLimitMiddleware)          # inner: runs only for a request the token let through
    app.add_middleware(AuthMiddleware, service_getter=lambda: holder["service"])

    def svc() -> Service:
        return holder["service"]

    ui_error: Callable[[Request, ApiError], Response] | None = None    # set by add_ui below

    @app.exception_handler(ApiError)
    async def api_error(request: Request, exc: ApiError):
        if request.url.path.startswith("/api/") or ui_error is None:
            return JSONResponse({"detail": exc.detail}, status_code=exc.status)
        return ui_error(request, exc)   # a web page's error is a page

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, exc: RequestValidationError):
        return JSONResponse({"detail": _validation_lines(exc)}, status_code=422)

    @app.exception_handler(OSError)
    async def os_error(request: Request, exc: OSError):
        if exc.errno == errno.ENAMETOOLONG:   # a path component over the file system's 255 bytes
            return JSONResponse({"detail": ["request: (path): a name in it is too long"]}, status_code=422)
        raise exc

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException):
        return JSONResponse({"detail": exc.detail}, status_code=exc.status_code, headers=exc.headers)

    # -- health, rigs, leases ------------------------------------------------------------------------------

    @app.get("/api/health")
    async def health() -> dict:                     # on the event loop: answers while worker threads are busy
        runner = svc().runner
        return {"status": "ok", "database": "sqlite" if svc().db.is_sqlite else "postgresql",
                "run_processes": runner.run_processes(),
                "fork_server": runner.forks.health() if runner.settings.run_start == "forkserver" else None}

    @app.get("/api/rigs")
    def rigs(who: Principal = Depends(viewer)) -> list[dict]:
        return svc().rigs()

    @app.get("/api/rigs/{name}")
    def rig(name: str, who: Principal = Depends(viewer)) -> dict:
        return svc().rig(name)

    @app.patch("/api/rigs/{name}")
    def patch_rig(name: str, body: RigPatch, who: Principal = Depends(admin)) -> dict:
        return svc().set_rig_enabled(name, body.enabled)

    @app.post("/api/rigs/{name}/lease", status_code=201)
    def lease(name: str, body: LeaseRequest, who: Principal = Depends(operator)) -> dict:
        held = reserve(svc().db, name, who, body.ttl_s, body.reason)
        return {"id": held.id, "expires_utc": lease_dict(held)["expires_utc"], "rig": name, "holder": who.name}

    @app.post("/api/rigs/{name}/probe", status_code=201)
    def probe(name: str, who: Principal = Depends(operator)) -> dict:
        """`drivebench probe` of the rig now (reads only; under a manual lease named probe): identity, checklist."""
        from bench.service.probes import probe_rig
        return asdict(probe_rig(svc().db, name, who))

    @app.get("/api/rigs/{name}/probe")
    def last_probe(name: str, who: Principal = Depends(viewer)) -> dict:
        from bench.service.probes import last_probe as newest
        svc().rig(name)                                     # 404 for an unknown rig
        found = newest(svc().db, name)
        if found is None:
            raise ApiError(404, f"rig {name}: never probed from this service (POST /api/rigs/{name}/probe)")
        return asdict(found)

    @app.get("/api/leases")
    def leases(who: Principal = Depends(viewer)) -> list[dict]:
        with svc().db.session() as s:
            return [lease_dict(l) for l in active_leases(s)]

    @app.post("/api/leases/{lease_id}/extend")
    def extend_lease(lease_id: Id, body: ExtendRequest | None = Body(None),
                     who: Principal = Depends(operator)) -> dict:
        held = extend(svc().db, lease_id, who, body.ttl_s if body else None)
        return {"id": held.id, "expires_utc": lease_dict(held)["expires_utc"]}

    @app.delete("/api/leases/{lease_id}")
    def delete_lease(lease_id: Id, who: Principal = Depends(operator)) -> dict:
        held = release(svc().db, lease_id, who)
        return {"id": held.id, "released": True, "released_by": held.released_by}

    # -- runs ------------------------------------------------------------------------------------------------

    @app.post("/api/runs", status_code=201)
    def submit_run(body: RunSubmit, who: Principal = Depends(operator)) -> dict:
        s = svc()
        run = submit(s.db, who, Submission(**body.model_dump()), s.settings.scenario_root, s.settings.data_dir)
        s.runner.wake()
        return {"id": run.id, "state": run.state, "url": f"/runs/{run.id}"}

    @app.get("/api/runs")
    def list_runs(rig: str | None = None, state: str | None = None, scenario: str | None = None,
                  verdict: str | None = None, revision: str | None = None, owner: str | None = None,
                  limit: int = 100, who: Principal = Depends(viewer)) -> list[dict]:
        s = svc()
        return s.run_dicts(s.list_runs(rig, state, scenario, verdict, revision, owner, limit))

    @app.get("/api/runs/{run_id}")
    def get_run(run_id: Id, who: Principal = Depends(viewer)) -> dict:
        return svc().run_dict(svc().get_run(run_id))

    @app.post("/api/runs/{run_id}/abort")
    def abort_run(run_id: Id, who: Principal = Depends(operator)) -> dict:
        run = svc().abort(run_id, who)
        return {"id": run.id, "state": run.state, "abort_requested_by": run.abort_requested_by}

    @app.get("/api/runs/{run_id}/files/{name}")
    def run_file(run_id: Id, name: str, who: Principal = Depends(viewer)):
        path = svc().run_file(run_id, name)
        return FileResponse(path, media_type=MEDIA.get(path.suffix, "application/octet-stream"), filename=name)

    @app.get("/metrics", include_in_schema=False)
    def metrics(who: Principal = Depends(viewer)):
        from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

        from bench.service.metrics import registry_for

        return Response(generate_latest(registry_for(svc().db)), media_type=CONTENT_TYPE_LATEST)

    @app.get("/docs", include_in_schema=False)
    def docs():
        from fastapi.openapi.docs import get_swagger_ui_html

        return get_swagger_ui_html(openapi_url="/openapi.json", title="drivebench API",
                                   swagger_js_url="/docs/swagger-ui-bundle.js", swagger_css_url="/docs/swagger-ui.css",
                                   swagger_favicon_url="data:,")

    @app.get("/docs/{asset}", include_in_schema=False)
    def docs_asset(asset: str):
        from importlib.resources import files      # served from the package: a lab may have no internet

        if asset not in ("swagger-ui-bundle.js", "swagger-ui.css"):
            return Response(f"/docs/{asset}: not found", status_code=404, media_type="text/plain")
        media = "text/javascript" if asset.endswith(".js") else "text/css"
        return FileResponse(str(files("fastapi_swagger.resources") / asset), media_type=media)

    @app.get("/api/runs/{run_id}/export/{fmt}")
    def export_run_file(run_id: Id, fmt: str, who: Principal = Depends(viewer)):
        from bench.outputs.export import FORMATS, export_run

        if fmt not in FORMATS:
            raise ApiError(404, f"run {run_id}: export {fmt!r}: one of {', '.join(FORMATS)}")
        record = svc().run_file(run_id, "record.json")
        target = record.parent / f"telemetry.{fmt}"
        if not target.is_file() or target.stat().st_mtime_ns < record.stat().st_mtime_ns:
            if not EXPORTS.acquire(timeout=10.0):      # a long run's export is seconds of CPU: two at once
                raise ApiError(503, "exports are being written; retry shortly")
            try:
                export_run(record.parent, fmt, target)
            finally:
                EXPORTS.release()
        return FileResponse(target, media_type=EXPORT_MEDIA[fmt], filename=f"run-{run_id}.{fmt}")

    @app.get("/api/failing")
    def failing(scenario: str | None = None, who: Principal = Depends(viewer)) -> list[dict]:
        """Criteria whose latest judged run fails, with the run and revision their failing streak began at."""
        return svc().failing_since(scenario)

    @app.get("/api/trend")
    def trend(criterion: str, scenario: str | None = None, limit: int = 500,
              who: Principal = Depends(viewer)) -> list[dict]:
        if not 1 <= limit <= 5000:
            raise bad_input([f"request: limit: must be in [1, 5000], got {limit}"])
        return svc().trend(criterion, scenario, limit)

    # -- tokens ----------------------------------------------------------------------------------------------

    @app.post("/api/tokens", status_code=201)
    def new_token(body: TokenRequest, who: Principal = Depends(admin)) -> dict:
        if body.role not in ROLES:
            raise bad_input([f"request: role: must be one of {', '.join(ROLES)}, got {body.role!r}"])
        token_id, token = create_token(svc().db, body.name, body.role)
        return {"id": token_id, "name": body.name, "role": body.role, "token": token}

    @app.get("/api/tokens")
    def tokens(who: Principal = Depends(admin)) -> list[dict]:
        return svc().tokens_list()

    @app.delete("/api/tokens/{token_id}")
    def revoke(token_id: Id, who: Principal = Depends(admin)) -> dict:
        svc().revoke_token(token_id)
        return {"id": token_id, "revoked": True}

    # -- events ----------------------------------------------------------------------------------------------

    @app.websocket("/api/events")
    async def events(websocket: WebSocket, run: int | None = None):
        """Run events as JSON: {"type": "run", "id", "state", "verdict", ...} on every state change and
        {"type": "progress", "id", "progress_s", "duration_s"} while a run runs. ?run=ID: one run only."""
        s = svc()
        queue = s.events.subscribe(websocket.scope["state"]["principal"].token_id)
        await websocket.accept()

        async def pump():
            if run is not None:
                current = await anyio.to_thread.run_sync(lambda: s.run_dict(s.get_run(run)))
                await websocket.send_json({"type": "run", "id": current["id"], "state": current["state"],
                                           "verdict": current["verdict"], "rig": current["rig"],
                                           "progress_s": current["progress_s"], "reason": current["reason"],
                                           "duration_s": current["scenario_duration_s"]})
            while True:
                event: dict[str, Any] = await queue.get()
                if run is None or event.get("id") == run:
                    await websocket.send_json(event)

        async def watch():
            while (await websocket.receive())["type"] != "websocket.disconnect":
                pass

        tasks = {asyncio.create_task(pump()), asyncio.create_task(watch())}
        try:
            done, pending = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
            for task in pending:
                task.cancel()
            for task in done:
                if isinstance(task.exception(), ApiError):
                    await websocket.close(code=4404, reason=str(task.exception()))
        except (WebSocketDisconnect, RuntimeError):
            pass
        finally:
            s.events.unsubscribe(queue)

    from bench.service.live import add_live
    from bench.service.ui import add_ui
    add_live(app, svc)
    ui_error = add_ui(app, svc)
    return app

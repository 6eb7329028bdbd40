"""Web pages for lab engineers: server-rendered Jinja templates, a few lines of plain JavaScript for live updates
(no Node build step, nothing from the internet). The login page sets the token as an HttpOnly SameSite=Strict
cookie, so a page of another site cannot make the browser post a form with it."""

from __future__ import annotations

import asyncio
import hashlib
import io
import json
import tempfile
import urllib.parse
from collections import OrderedDict
from pathlib import Path
from typing import Callable

from fastapi import FastAPI, Form, Query, Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from fastapi.templating import Jinja2Templates

import anyio

from bench.service.auth import COOKIE, Principal
from drivers.contract.checks import find_repo_root
from bench.service.core import RUN_FILES, Service
from bench.service.db import FINAL_STATES, STATES, iso
from bench.service.errors import ApiError
from bench.service.leases import release, reserve
from bench.service.limits import MAX_RENDERS, RENDER_WAIT_S
from bench.service.live import recording_name
from bench.service.params import Id, QueryId
from bench.service.queue import Submission, submit

HERE = Path(__file__).resolve().parent
templates = Jinja2Templates(directory=str(HERE / "templates"))
templates.env.globals.update(iso=iso, FINAL_STATES=FINAL_STATES, STATES=STATES)


def _fmt(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_fmt(v) for v in value) + "]"
    return str(value)


templates.env.filters["fmt"] = _fmt


def add_ui(app: FastAPI, svc: Callable[[], Service]) -> Callable[[Request, ApiError], HTMLResponse]:
    """Adds the pages to app; returns the renderer of an ApiError as a page (app.py uses it outside /api/)."""
    def who(request: Request) -> Principal:
        return request.scope["state"]["principal"]

    def page(request: Request, name: str, **context) -> HTMLResponse:
        return templates.TemplateResponse(request, name, {"me": who(request), "waiting": svc().waiting_lookup(),
                                                          **context})

    def error(request: Request, exc: ApiError) -> HTMLResponse:
        lines = exc.detail if isinstance(exc.detail, list) else [exc.detail]
        root = f"{find_repo_root()}/"       # a page names files relative to the repository, never by a host path
        lines = [str(line).replace(root, "") for line in lines]
        response = page(request, "error.html", status=exc.status, lines=lines)
        response.status_code = exc.status
        return response

    def need_operator(request: Request, action: str) -> None:
        if not who(request).at_least("operator"):
            raise ApiError(403, f"{who(request).role} token: {action} needs the operator role")

    @app.get("/login", response_class=HTMLResponse)
    def login_page(request: Request, failed: int = 0):
        return templates.TemplateResponse(request, "login.html", {"failed": bool(failed), "me": None})

    @app.post("/login")
    def login(token: str = Form(...)):
        if svc().tokens.lookup(token.strip()) is None:
            return RedirectResponse("/login?failed=1", status_code=303)
        response = RedirectResponse("/", status_code=303)
        response.set_cookie(COOKIE, token.strip(), httponly=True, samesite="strict", max_age=30 * 24 * 3600)
        return response

    @app.get("/logout")
    def logout():
        response = RedirectResponse("/login", status_code=303)
        response.delete_cookie(COOKIE)
        return response

    @app.get("/", response_class=HTMLResponse)
    def index(request: Request):
        s = svc()
        return page(request, "index.html", rigs=s.rigs(), queue=list(reversed(s.list_runs(active=True, limit=200))),
                    recent=[r for r in s.list_runs(limit=15) if r.state in FINAL_STATES],
                    tags=_tags_in_rig_order(s))

    @app.get("/runs/{run_id}", response_class=HTMLResponse)
    def run_page(request: Request, run_id: Id):
        s = svc()
        run = s.get_run(run_id)
        files = []
        for name in RUN_FILES:
            try:
                s.run_file(run_id, name)
                files.append(name)
            except ApiError:
                pass
        return page(request, "run.html", run=run, r=s.run_dict(run), files=files, full=False,
                    recording=recording_name(run.id, run.scenario_name or run.scenario))

    @app.get("/compare", response_class=HTMLResponse)
    def compare_page(request: Request, a: QueryId, b: QueryId):
        from bench.outputs.compare import compare_runs

        s = svc()
        dirs = [s.run_file(run_id, "record.json").parent for run_id in (a, b)]
        result = compare_runs(*dirs)
        return page(request, "compare.html", a=s.get_run(a), b=s.get_run(b), result=result)

    @app.get("/compare.png")
    async def compare_png(a: QueryId, b: QueryId):
        s = svc()
        dirs = await anyio.to_thread.run_sync(lambda: [s.run_file(r, "record.json").parent for r in (a, b)])
        stamps = [(str(d), (d / "record.json").stat().st_mtime_ns) for d in dirs]
        try:
            png = await plots.get(("compare", stamps), lambda: _compare_png(*dirs))
        except TimeoutError:
            return Response("plots are being rendered; retry shortly", status_code=503, media_type="text/plain",
                            headers={"Retry-After": "2"})
        if not png:
            raise ApiError(404, f"runs {a} and {b}: no signal measured in both")
        return Response(png, media_type="image/png", headers={"Cache-Control": "private, max-age=30"})

    @app.get("/runs/{run_id}/live", response_class=HTMLResponse)
    def live_page(request: Request, run_id: Id):
        run = svc().get_run(run_id)
        return page(request, "live.html", run=run, full=True,
                    recording=recording_name(run.id, run.scenario_name or run.scenario))

    @app.post("/ui/runs")
    def ui_submit(request: Request, scenario: str = Form(...), target: str = Form(...), seed: str = Form("")):
        kind, _, value = target.partition(":")
        need_operator(request, "submitting")
        try:
            seed_value = int(seed) if seed.strip() else None
        except ValueError:
            raise ApiError(422, [f"request: seed: must be an integer, got {seed!r}"]) from None
        run = submit(svc().db, who(request), Submission(scenario=scenario, rig=value if kind == "rig" else None,
                                                         tag=value if kind == "tag" else None, seed=seed_value),
                     svc().settings.scenario_root, svc().settings.data_dir)
        svc().runner.wake()
        return RedirectResponse(f"/runs/{run.id}", status_code=303)

    @app.post("/ui/runs/{run_id}/abort")
    def ui_abort(request: Request, run_id: Id):
        need_operator(request, "aborting")
        svc().abort(run_id, who(request))
        return RedirectResponse(f"/runs/{run_id}", status_code=303)

    @app.get("/history", response_class=HTMLResponse)
    def history(request: Request, rig: str = "", state: str = "", scenario: str = "", verdict: str = "",
                revision: str = "", owner: str = "", limit: int = 200):
        s = svc()
        runs = s.list_runs(rig or None, state or None, scenario or None, verdict or None, revision or None,
                           owner or None, limit)
        return page(request, "history.html", runs=runs, failing=s.failing_since(scenario or None),
                    rigs=[r["name"] for r in s.rigs()], scenarios=s.scenario_names(),
                    filters={"rig": rig, "state": state, "scenario": scenario, "verdict": verdict,
                             "revision": revision, "owner": owner})

    @app.get("/trend", response_class=HTMLResponse)
    def trend_page(request: Request, scenario: str = "", criterion: list[str] = Query(default=[]), x: str = "run"):
        s = svc()
        chosen = [c for c in criterion if c][:MAX_TREND_CRITERIA]
        x = x if x in TREND_AXES else "run"
        series = [(c, s.trend(c, scenario or None)) for c in chosen]
        query = urllib.parse.urlencode({"scenario": scenario, "criterion": chosen, "x": x}, doseq=True)
        return page(request, "trend.html", scenarios=s.scenario_names(), scenario=scenario,
                    criteria=s.criterion_names(scenario or None), chosen=chosen, series=series, x=x,
                    axes=TREND_AXES, query=query)

    plots = app.state.plots = PlotCache()

    @app.get("/trend.png")
    async def trend_png(scenario: str = "", criterion: list[str] = Query(default=[]), x: str = "run"):
        chosen = [c for c in criterion if c][:MAX_TREND_CRITERIA]
        x = x if x in TREND_AXES else "run"
        series = await anyio.to_thread.run_sync(lambda: [(c, svc().trend(c, scenario or None)) for c in chosen])
        try:
            png = await plots.get((chosen, scenario, x, series), lambda: _trend_png(series, scenario, x))
        except TimeoutError:
            return Response("plots are being rendered; retry shortly", status_code=503, media_type="text/plain",
                            headers={"Retry-After": "2"})
        return Response(png, media_type="image/png", headers={"Cache-Control": "private, max-age=5"})

    @app.get("/rigs/{name}", response_class=HTMLResponse)
    def rig_page(request: Request, name: str):
        from bench.service.probes import last_probe
        from bench.outputs.conformance_report import latest_for_bench
        from bench.service.rig_page import current_run, drive_of_last_run, last_finished, rig_scenarios

        s = svc()
        rig = s.rig(name)
        bench = Path(rig["bench"])
        shown = bench.name if not bench.is_relative_to(s.settings.scenario_root.parent) \
            else str(bench.relative_to(s.settings.scenario_root.parent))
        runs = s.list_runs(rig=name, limit=20)
        return page(request, "rig.html", rig=rig, bench_shown=shown, runs=runs,
                    current=current_run(s, name), last=last_finished(s, name),
                    probe=last_probe(s.db, name), run_drive=drive_of_last_run(runs),
                    scenarios=rig_scenarios(s.settings.scenario_root, rig["bench"]),
                    conformance=latest_for_bench(s.settings.scenario_root.parent / "conformance", rig["bench"]))

    @app.post("/ui/rigs/{name}/reserve")
    def ui_reserve(request: Request, name: str, hours: float = Form(...), reason: str = Form("")):
        need_operator(request, "reserving")
        reserve(svc().db, name, who(request), hours * 3600.0, reason)
        return RedirectResponse(f"/rigs/{name}", status_code=303)

    @app.post("/ui/rigs/{name}/probe")
    def ui_probe(request: Request, name: str):
        from bench.service.probes import probe_rig

        need_operator(request, "probing")
        probe_rig(svc().db, name, who(request))
        svc().runner.wake()
        return RedirectResponse(f"/rigs/{name}#drive", status_code=303)

    @app.post("/ui/leases/{lease_id}/release")
    def ui_release(request: Request, lease_id: Id):
        need_operator(request, "releasing")
        lease = release(svc().db, lease_id, who(request))
        svc().runner.wake()
        return RedirectResponse(f"/rigs/{lease.rig}", status_code=303)

    @app.get("/static/app.js")
    def app_js():
        return Response((HERE / "static" / "app.js").read_text(encoding="utf-8"), media_type="text/javascript")

    return error


class PlotCache:
    """Plots rendered off the event loop, at most MAX_RENDERS at once, each once per content: the key is the plotted
    data, so a new run (a new revision, a new value) makes a new plot and a hundred viewers of one page share one
    render. A request that waits RENDER_WAIT_S for a renderer gets TimeoutError (the page says 503, retry)."""

    def __init__(self, size: int = 64):
        self.size = size
        self._done: OrderedDict[str, bytes] = OrderedDict()
        self._rendering: dict[str, asyncio.Future] = {}
        self._limiter = anyio.CapacityLimiter(MAX_RENDERS)
        self.renders = 0

    async def get(self, key_data, render) -> bytes:
        key = hashlib.sha256(json.dumps(key_data, default=str, sort_keys=True).encode()).hexdigest()
        if key in self._done:
            self._done.move_to_end(key)
            return self._done[key]
        if key in self._rendering:                   # someone is rendering this one: wait for it
            return await asyncio.wait_for(asyncio.shield(self._rendering[key]), RENDER_WAIT_S)
        future = asyncio.get_running_loop().create_future()
        self._rendering[key] = future
        try:
            with anyio.fail_after(RENDER_WAIT_S):
                await self._limiter.acquire()
            try:
                png = await anyio.to_thread.run_sync(render)
                self.renders += 1
            finally:
                self._limiter.release()
            self._done[key] = png
            while len(self._done) > self.size:
                self._done.popitem(last=False)
            future.set_result(png)
            return png
        except BaseException as exc:
            if not future.done():
                future.set_exception(TimeoutError() if isinstance(exc, TimeoutError) else exc)
                future.exception()                   # retrieved: no "never retrieved" warning
            raise
        finally:
            self._rendering.pop(key, None)


def _tags_in_rig_order(s: Service) -> list[str]:
    """The submit form's targets: the tags of the rigs file's first rig first (the default target is a tag the first
    rig has, not the alphabetically first tag, which may name a drive of another kind)."""
    order = {rig.name: i for i, rig in enumerate(s.settings.rigs)}
    rigs = sorted(s.rigs(), key=lambda r: order.get(r["name"], len(order)))
    return list(dict.fromkeys(t for r in rigs for t in r["tags"]))


def _compare_png(dir_a: Path, dir_b: Path) -> bytes:
    """bench.outputs.compare's overlay of two runs' signals on the drive clock; b"" when they share no measured signal."""
    from bench.outputs.compare import write_plot

    with tempfile.TemporaryDirectory() as scratch:
        path = write_plot(dir_a, dir_b, Path(scratch) / "compare.png")
        return path.read_bytes() if path is not None else b""


TREND_AXES = {"run": "run id", "time": "run end (UTC)", "revision": "software revision (in order of first run)"}
MAX_TREND_CRITERIA = 6


def _trend_png(series: list[tuple[str, list[dict]]], scenario: str, x: str) -> bytes:
    """Each criterion's value per run in its own panel (their units differ), on a shared x axis — run id, end time
    or revision — coloured by software revision, failures crossed, each with its limit."""
    import datetime as dt

    import matplotlib
    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 1.2 + 2.4 * max(1, len(series))), dpi=100)
    axes = fig.subplots(max(1, len(series)), 1, sharex=True, squeeze=False)[:, 0]
    every = [p for _, points in series for p in points]
    revisions = list(dict.fromkeys((p["revision"] or "unknown")[:10] for p in sorted(every, key=lambda p: p["run_id"])))
    cmap = matplotlib.colormaps["tab10"]

    def xof(p: dict):
        if x == "time":
            return dt.datetime.fromisoformat(p["ended_utc"].replace("Z", "+00:00")) if p.get("ended_utc") else None
        if x == "revision":
            return revisions.index((p["revision"] or "unknown")[:10]) + (p["run_id"] % 7) * 0.04
        return p["run_id"]

    if not series:
        axes[0].text(0.5, 0.5, "choose one or more criteria", ha="center", va="center", transform=axes[0].transAxes)
    for ax, (criterion, points) in zip(axes, series):
        points = [p for p in points if xof(p) is not None]
        if not points:
            ax.text(0.5, 0.5, "no runs with this criterion yet", ha="center", va="center", transform=ax.transAxes)
        for i, rev in enumerate(revisions):
            chosen = [p for p in points if (p["revision"] or "unknown")[:10] == rev and p["value"] is not None]
            if chosen:
                ax.plot([xof(p) for p in chosen], [p["value"] for p in chosen], "o", color=cmap(i % 10),
                        label=f"rev {rev}")
            failed = [p for p in chosen if not p["passed"]]
            ax.plot([xof(p) for p in failed], [p["value"] for p in failed], "x", color="red", ms=10)
        limits = [(xof(p), p["limit"]) for p in points if p["limit"] is not None]
        if limits:
            ax.plot([a for a, _ in limits], [b for _, b in limits], "_", color="red", ms=12, label="limit")
        ax.set_title(criterion + (f" ({scenario})" if scenario else ""), fontsize=9)
        ax.set_ylabel("value", fontsize=8)
        ax.grid(alpha=0.3)
        if points:
            ax.legend(loc="best", fontsize=7)
    if x == "revision" and revisions:
        axes[-1].set_xticks(range(len(revisions)), revisions, rotation=30, fontsize=7)
    axes[-1].set_xlabel(TREND_AXES[x])
    fig.tight_layout()
    out = io.BytesIO()
    fig.savefig(out, format="png")
    return out.getvalue()

"""The live view of a run, served by the service itself on its own address, behind its own token: no Rerun port.

Each run process writes its recording to its `run.rrd` as it goes (rerun_view's FileSink; under the service every
LIVE_INTERVAL_S of wall time with `serve --live`, else every FILE_ONLY_INTERVAL_S). The service
- serves the Rerun web viewer (its index.html, JavaScript and Wasm, taken once from the `rerun` binary of the
  rerun-sdk wheel on a loopback port that lives a few seconds, then cached under the data directory) at
  /live/viewer/, and
- streams a run's `run.rrd` at /live/runs/ID/recording.rrd, following the file while the run goes on (the viewer
  decodes an HTTP .rrd as it arrives, so it draws the run as it happens) and ending once the run has ended.
The run page embeds that viewer opened on that URL only: one run's page never loads another run's data. The
recording is named as the page names it, `run-ID · scenario` (recording_name), with recording id `run-ID`."""

from __future__ import annotations

import asyncio
import importlib.metadata
import importlib.util
import re
import shutil
import socket
import subprocess
import tempfile
import threading
import time
import urllib.request
from pathlib import Path
from typing import AsyncIterator, Callable

import anyio
from fastapi import Request
from fastapi.responses import FileResponse, Response, StreamingResponse

from bench.service.db import FINAL_STATES
from bench.service.errors import ApiError
from bench.service.params import Id

LIVE_INTERVAL_S = 0.5         # `serve --live`: a run's batches reach its run.rrd (and the viewer) at this wall cadence
FOLLOW_POLL_S = 0.25          # a followed run.rrd that has not grown is looked at again after this
STATE_POLL_S = 1.0            # ... and the run's state (has it ended?) read from the database at most this often
FOLLOW_MAX_S = 24 * 3600.0    # a follow ends after this even if the run never does (a stuck run, a lost process)
READ_CHUNK = 256 * 1024
MAX_FOLLOWS_PER_TOKEN = 8     # recordings one token may stream at once (200 followers took 64 % of a core)
EXTRACT_TIMEOUT_S = 60.0      # the wheel's viewer server must hand over its files within this
# what the viewer's index.html loads from its own origin (sw.js and the sign-in pages are never used here)
VIEWER_FILES = {"index.html": "text/html; charset=utf-8", "re_viewer.js": "text/javascript",
                "re_viewer_bg.wasm": "application/wasm", "favicon.ico": "image/x-icon",
                "apple-touch-icon.png": "image/png"}
# the viewer page links web fonts from the internet: a lab's bench PC may have none, and the viewer has its own
_INTERNET_FONTS = re.compile(r'<link[^>]*fonts\.(googleapis|gstatic)\.com[^>]*>', re.S)
# The viewer fetches an HTTP .rrd without credentials (its HTTP client's default), so the token cookie would not go
# with it: on this page, requests to the page's own origin carry it (same-origin only: nothing else gets it).
# Nothing leaves the building: rerun 0.41's web viewer sends usage analytics (PostHog, tel.rerun.io) and asks GitHub
# for its latest release at start-up, and has no option to turn either off (only its test build skips the update
# check): on this page every request to another origin is refused before it is made (fetch, XHR, beacons,
# websockets), and the page's Content-Security-Policy (VIEWER_CSP) refuses what would get past that.
_SAME_ORIGIN_ONLY = """<script>
(function () {  // drivebench: requests go to this origin only, with the service's token cookie; others are refused
  const own = (u) => new URL(u instanceof Request ? u.url : String(u), location.href).origin === location.origin;
  const refused = (u) => new TypeError("drivebench: a request outside the service refused: " + String(u));
  const plain = window.fetch;
  window.fetch = function (input, init) {
    if (!own(input)) return Promise.reject(refused(input instanceof Request ? input.url : input));
    if (input instanceof Request) input = new Request(input, {credentials: "same-origin"});
    else init = Object.assign({}, init || {}, {credentials: "same-origin"});
    return plain.call(this, input, init);
  };
  const open = XMLHttpRequest.prototype.open;
  XMLHttpRequest.prototype.open = function (method, url) {
    if (!own(url)) throw refused(url);
    return open.apply(this, arguments);
  };
  if (navigator.sendBeacon) {
    const beacon = navigator.sendBeacon.bind(navigator);
    navigator.sendBeacon = (url, data) => own(url) ? beacon(url, data) : false;
  }
  const Socket = window.WebSocket;
  window.WebSocket = function (url, protocols) {
    if (new URL(String(url), location.href).host !== location.host) throw refused(url);
    return new Socket(url, protocols);
  };
  window.WebSocket.prototype = Socket.prototype;
})();
</script>
"""
VIEWER_CSP = ("default-src 'self'; script-src 'self' 'unsafe-inline' 'wasm-unsafe-eval'; style-src 'self' "
              "'unsafe-inline'; img-src 'self' data: blob:; font-src 'self' data:; connect-src 'self'; "
              "worker-src 'self' blob:; media-src 'self' blob:; frame-ancestors 'self'")
_VIEWER_SCRIPT = '<script src="re_viewer.js"></script>'
_lock = threading.Lock()


def viewer_page(raw: bytes) -> bytes:
    """The wheel's index.html as this service serves it: no web fonts from the internet, requests to its own origin
    only (with the cookie), none to another."""
    text = _INTERNET_FONTS.sub("", raw.decode("utf-8"))
    if _VIEWER_SCRIPT not in text:
        raise RuntimeError("the rerun web viewer's index.html has changed: re_viewer.js not found")
    return text.replace(_VIEWER_SCRIPT, _SAME_ORIGIN_ONLY + _VIEWER_SCRIPT, 1).encode("utf-8")


def recording_name(run_id: int, scenario: str | None) -> str:
    """The name of a run's recording, in the viewer and on its pages."""
    return f"run-{run_id} · {scenario}" if scenario else f"run-{run_id}"


def rerun_version() -> str:
    return importlib.metadata.version("rerun-sdk")


def rerun_binary() -> str | None:
    """The `rerun` executable shipped in the rerun-sdk wheel (package rerun_cli), else one on PATH."""
    spec = importlib.util.find_spec("rerun_cli")
    if spec is not None and spec.origin:
        candidate = Path(spec.origin).parent / "rerun"
        if candidate.exists():
            return str(candidate)
    return shutil.which("rerun")


def viewer_dir(cache_root: Path) -> Path:
    """The viewer's files for the installed rerun-sdk, extracted on first use (one process at a time)."""
    dest = cache_root / f"rerun-web-viewer-{rerun_version()}"
    with _lock:
        if not all((dest / name).is_file() for name in VIEWER_FILES):
            _extract(dest)
    return dest


def _free_loopback_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _extract(dest: Path) -> None:
    """Start the wheel's viewer server on 127.0.0.1 (free ports), copy its files, stop it."""
    binary = rerun_binary()
    if binary is None:
        raise RuntimeError("the rerun-sdk wheel's `rerun` executable was not found")
    web_port, grpc_port = _free_loopback_port(), _free_loopback_port()
    proc = subprocess.Popen([binary, "--serve-web", "--bind", "127.0.0.1", "--port", str(grpc_port),
                             "--web-viewer-port", str(web_port), "--hide-welcome-screen"],
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        dest.parent.mkdir(parents=True, exist_ok=True)
        scratch = Path(tempfile.mkdtemp(prefix=dest.name + ".", dir=dest.parent))
        deadline = time.monotonic() + EXTRACT_TIMEOUT_S
        for name in VIEWER_FILES:
            while True:
                try:
                    with urllib.request.urlopen(f"http://127.0.0.1:{web_port}/{name}", timeout=10) as response:
                        data = response.read()
                    break
                except OSError:
                    if proc.poll() is not None or time.monotonic() > deadline:
                        err = proc.stderr.read().decode(errors="replace")[-500:] if proc.poll() is not None else ""
                        raise RuntimeError(f"the rerun viewer server did not hand over {name} {err}".strip())
                    time.sleep(0.2)
            (scratch / name).write_bytes(data)
        if dest.exists():
            shutil.rmtree(dest)
        scratch.rename(dest)
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)
        if proc.stderr is not None:
            proc.stderr.close()


async def follow(path_of: Callable[[], Path | None], ended: Callable[[], bool],
                 poll_s: float = FOLLOW_POLL_S, max_s: float = FOLLOW_MAX_S) -> AsyncIterator[bytes]:
    """The bytes of a growing file as they are written, until `ended()` (checked in a worker thread) says its
    writer is done and everything written has been sent. `path_of()` is None until the file exists."""
    started = time.monotonic()
    last_state_check = -float("inf")
    path: Path | None = None
    handle = None
    try:
        while True:
            if handle is None:
                path = await anyio.to_thread.run_sync(path_of)
                if path is not None:
                    handle = open(path, "rb")
            chunk = handle.read(READ_CHUNK) if handle is not None else b""
            if chunk:
                yield chunk
                continue
            if time.monotonic() - last_state_check >= STATE_POLL_S:
                last_state_check = time.monotonic()
                if await anyio.to_thread.run_sync(ended):
                    if handle is None and (path := await anyio.to_thread.run_sync(path_of)) is not None:
                        handle = open(path, "rb")
                    while handle is not None and (chunk := handle.read(READ_CHUNK)):
                        yield chunk
                    return
            if time.monotonic() - started > max_s:
                return
            await asyncio.sleep(poll_s)
    finally:
        if handle is not None:
            handle.close()


def add_live(app, svc) -> None:
    """The viewer's files and each run's followed recording, on the app's own address (behind its token)."""
    @app.get("/live/viewer/{name}")
    async def viewer_file(name: str):
        if name not in VIEWER_FILES:
            raise ApiError(404, f"live viewer: no file {name}")
        try:
            folder = await anyio.to_thread.run_sync(viewer_dir, svc().settings.data_dir)
        except (RuntimeError, OSError) as exc:
            raise ApiError(503, f"live viewer: not available: {exc}") from None
        cache = {"Cache-Control": "private, max-age=86400"}
        if name == "index.html":
            page = viewer_page(await anyio.to_thread.run_sync((folder / name).read_bytes))
            return Response(page, media_type=VIEWER_FILES[name], headers={**cache, "Content-Security-Policy": VIEWER_CSP})
        return FileResponse(folder / name, media_type=VIEWER_FILES[name], headers=cache)  # 43 MB: from disk

    following: dict[int, int] = {}     # token id -> its recordings being streamed now (the event loop's own)

    @app.get("/live/runs/{run_id}/recording.rrd")
    async def recording(run_id: Id, request: Request):
        s = svc()
        who = request.scope["state"]["principal"]
        if following.get(who.token_id, 0) >= MAX_FOLLOWS_PER_TOKEN:
            raise ApiError(429, f"live view: token {who.name!r} follows {MAX_FOLLOWS_PER_TOKEN} recordings already "
                                f"(at most {MAX_FOLLOWS_PER_TOKEN} at once per token); close one")
        run = await anyio.to_thread.run_sync(s.get_run, run_id)     # 404 for an unknown run

        def path_of() -> Path | None:
            try:
                return s.run_file(run_id, "run.rrd")
            except ApiError:
                return None

        def ended() -> bool:
            return s.get_run(run_id).state in FINAL_STATES

        if run.state in FINAL_STATES and path_of() is None:
            raise ApiError(404, f"run {run_id}: no recording (run.rrd)")
        async def counted():
            following[who.token_id] = following.get(who.token_id, 0) + 1
            try:
                async for chunk in follow(path_of, ended):
                    yield chunk
            finally:
                following[who.token_id] -= 1
                if not following[who.token_id]:
                    del following[who.token_id]

        return StreamingResponse(counted(), media_type="application/octet-stream",
                                 headers={"Cache-Control": "no-store", "X-Recording-Id": f"run-{run_id}"})


"""Helpers and fixtures of the bench-service tests: a rigs file, a Service with tokens of every role, a
`drivebench serve` subprocess, and a throwaway PostgreSQL cluster from Debian's binaries."""

from __future__ import annotations

import contextlib
import glob
import os
import pwd
import shutil
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
CHROMIUM = next((p for p in (os.environ.get("DRIVEBENCH_CHROMIUM"), shutil.which("chromium"),
                             shutil.which("chromium-browser"), shutil.which("google-chrome")) if p), None)
SCENARIOS = REPO / "tests" / "data" / "service"
SHORT = "short.toml"
LONG = "long.toml"

RIGS_TOML = f"""
[[rig]]
name = "sim-a"
bench = "{REPO}/config/benches/sim-pmsm.toml"
tags = ["pmsm"]
max_concurrent = 2

[[rig]]
name = "spim-a"
bench = "{REPO}/config/benches/sim-spim.toml"
tags = ["spim"]

[[rig]]
name = "real-a"
bench = "{REPO}/config/benches/sim-pmsm.toml"
tags = ["pmsm", "lab"]
simulated = false
"""


def write_rigs(folder: Path) -> Path:
    path = folder / "rigs.toml"
    path.write_text(RIGS_TOML)
    return path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until(predicate, timeout_s: float, period_s: float = 0.05, what: str = "condition"):
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(period_s)


@dataclass
class Tokens:
    viewer: str
    operator: str
    operator2: str
    admin: str

    @staticmethod
    def header(token: str) -> dict:
        return {"Authorization": f"Bearer {token}"}


def make_tokens(db) -> Tokens:
    from bench.service.auth import create_token

    return Tokens(*(create_token(db, name, role)[1] for name, role in
                    (("vic", "viewer"), ("olga", "operator"), ("oscar", "operator"), ("ada", "admin"))))


def make_settings(tmp_path: Path, db_url: str | None = None, **overrides):
    from bench.service.core import ServiceSettings

    return ServiceSettings(data_dir=tmp_path / "data", db_url=db_url, rigs_path=write_rigs(tmp_path),
                           scenario_root=SCENARIOS, **overrides)


@contextlib.contextmanager
def client_for(settings):
    """A Starlette TestClient around a running service (lifespan: migrations, runner)."""
    from fastapi.testclient import TestClient

    from bench.service.app import create_app
    from bench.service.core import Service

    service = Service(settings)
    tokens = make_tokens(service.db)
    with TestClient(create_app(service=service)) as client:
        client.service = service
        client.tokens = tokens
        yield client


def serve_process(tmp_path: Path, port: int, *extra: str, db_url: str | None = None) -> subprocess.Popen:
    args = [sys.executable, "-m", "bench", "serve", "--data", str(tmp_path / "data"), "--port", str(port),
            "--rigs", str(tmp_path / "rigs.toml"), "--scenarios", str(SCENARIOS), *extra]
    if db_url:
        args += ["--db", db_url]
    if not (tmp_path / "rigs.toml").exists():
        write_rigs(tmp_path)
    log = open(tmp_path / f"serve-{port}.log", "ab")
    proc = subprocess.Popen(args, cwd=REPO, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    log.close()
    import urllib.request

    def up():
        if proc.poll() is not None:
            raise AssertionError(f"drivebench serve exited {proc.returncode}: "
                                 f"{(tmp_path / f'serve-{port}.log').read_text()[-2000:]}")
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/health", timeout=1):
                return True
        except OSError:
            return False

    wait_until(up, 30, 0.1, "drivebench serve to answer /api/health")
    return proc


@contextlib.contextmanager
def chromium_page(*, timeout_ms: int, viewport: dict | None = None, cookie: tuple[str, str] | None = None,
                  webgl: bool = False):
    """A page of a fresh headless Chromium (Playwright, the system browser), closed with the block. cookie: (service
    URL, token) logs the page in through the service's cookie; webgl: software WebGL (the Rerun viewer needs it)
    instead of no GPU at all."""
    from playwright import sync_api

    args = ["--no-sandbox", "--disable-dev-shm-usage", "--enable-unsafe-swiftshader" if webgl else "--disable-gpu"]
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=args)
        try:
            context = browser.new_context(viewport=viewport) if viewport else browser.new_context()
            context.set_default_timeout(timeout_ms)
            if cookie is not None:
                from bench.service.auth import COOKIE

                context.add_cookies([{"name": COOKIE, "value": cookie[1], "url": cookie[0]}])
            yield context.new_page()
        finally:
            browser.close()


def shot(page, name: str) -> None:
    """A full-page screenshot where DRIVEBENCH_SCREENSHOTS names a directory (to look at, not to assert on)."""
    folder = os.environ.get("DRIVEBENCH_SCREENSHOTS")
    if folder:
        page.screenshot(path=os.path.join(folder, f"{name}.png"), full_page=True)


@dataclass
class Served:
    """A `drivebench serve` subprocess on a fresh database with a token of every role."""
    url: str
    port: int
    process: subprocess.Popen
    tokens: "Tokens"


@contextlib.contextmanager
def served_service(tmp_path: Path, *extra: str):
    """`drivebench serve *extra` on tmp_path's rigs and database, stopped (SIGTERM) when the block ends."""
    from bench.service.core import Service

    service = Service(make_settings(tmp_path))
    tokens = make_tokens(service.db)
    service.db.dispose()
    port = free_port()
    server = serve_process(tmp_path, port, *extra)
    try:
        yield Served(f"http://127.0.0.1:{port}", port, server, tokens)
    finally:
        stop_process(server)


def stop_process(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=40)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)


# --- PostgreSQL -------------------------------------------------------------------------------------------

def _pg_bin() -> Path | None:
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"))
    return Path(found[-1]).parent if found else None


@pytest.fixture(scope="session")
def pg_url(tmp_path_factory):
    """A throwaway PostgreSQL cluster on 127.0.0.1 (Debian's postgresql package), stopped at the end."""
    bindir = _pg_bin()
    if bindir is None:
        pytest.skip("PostgreSQL server binaries not installed (Debian: apt-get install postgresql)")
    pytest.importorskip("psycopg", reason="psycopg not installed (pip install 'drivebench[service]')")
    import tempfile

    # not under pytest's tmp dir: as root that is private to root, and the postgres user must reach it
    folder = Path(tempfile.mkdtemp(prefix="drivebench-pg-"))
    data = folder / "data"
    as_user: list[str] = []
    if os.geteuid() == 0:      # PostgreSQL refuses to run as root: use the package's postgres user
        try:
            user = pwd.getpwnam("postgres")
        except KeyError:
            pytest.skip("running as root and there is no postgres user to run PostgreSQL as")
        os.chown(folder, user.pw_uid, user.pw_gid)
        os.chmod(folder, 0o700)
        runuser = shutil.which("runuser") or shutil.which("setpriv")
        if runuser is None:
            pytest.skip("running as root and neither runuser nor setpriv is available")
        as_user = ([runuser, "-u", "postgres", "--"] if runuser.endswith("runuser")
                   else [runuser, f"--reuid={user.pw_uid}", f"--regid={user.pw_gid}", "--init-groups"])
    port = free_port()
    run = lambda *a: subprocess.run([*as_user, *a], capture_output=True, text=True, timeout=120)  # noqa: E731
    init = run(str(bindir / "initdb"), "-D", str(data), "-U", "postgres", "-A", "trust", "-E", "UTF8",
               "--no-sync")
    if init.returncode != 0:
        pytest.skip(f"initdb failed: {init.stderr.strip()[-300:]}")
    start = run(str(bindir / "pg_ctl"), "-D", str(data), "-l", str(folder / "pg.log"), "-w", "-t", "60",
                "-o", f"-p {port} -c listen_addresses=127.0.0.1 -k {folder} -c fsync=off", "start")
    if start.returncode != 0:
        pytest.skip(f"pg_ctl start failed: {start.stderr.strip()[-300:]}")
    try:
        yield f"postgresql+psycopg://postgres@127.0.0.1:{port}/postgres"
    finally:
        run(str(bindir / "pg_ctl"), "-D", str(data), "-m", "immediate", "-w", "-t", "30", "stop")
        shutil.rmtree(folder, ignore_errors=True)


def fresh_pg_database(url: str, name: str) -> str:
    """A new empty database on the cluster (one per test: migrations start from nothing)."""
    from sqlalchemy import create_engine, text

    engine = create_engine(url, isolation_level="AUTOCOMMIT")
    with engine.connect() as conn:
        conn.execute(text(f'DROP DATABASE IF EXISTS "{name}"'))
        conn.execute(text(f'CREATE DATABASE "{name}"'))
    engine.dispose()
    return url.rsplit("/", 1)[0] + "/" + name

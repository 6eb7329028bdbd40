"""`drivebench serve`, `drivebench token`, `drivebench submit` (the web stack is imported inside the commands, so
`drivebench run` does not pay for it)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import click

from drivers.contract.errors import InputError

EXIT_PASS, EXIT_FAIL, EXIT_ERROR = 0, 1, 2
DEFAULT_DATA = "runs/service"


def _data_option(fn):
    fn = click.option("--data", "data_dir", type=click.Path(file_okay=False), default=DEFAULT_DATA,
                      show_default=True, help="Service data: the embedded database, run directories.")(fn)
    return click.option("--db", "db_url", envvar="DRIVEBENCH_DB",
                        help="Database URL (default: SQLite in --data; postgresql://user@host/db to share one).")(fn)


def _bad(lines: list[str]) -> None:
    for line in lines:
        click.echo(line, err=True)
    sys.exit(EXIT_ERROR)


DB_CONNECT_TIMEOUT_S = 5     # a database server that accepts and never answers: one line after this, not a hang
MAX_ID = 2**63 - 1           # ids are 64-bit signed integers in SQLite and PostgreSQL


def bounded_db_url(db_url: str) -> str:
    """A PostgreSQL URL with libpq's connect_timeout (unless the URL sets its own)."""
    from sqlalchemy.engine import make_url

    url = make_url(db_url)
    if url.drivername.startswith("postgres") and "connect_timeout" not in url.query:
        url = url.update_query_dict({"connect_timeout": str(DB_CONNECT_TIMEOUT_S)})
    return url.render_as_string(hide_password=False)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return f"{type(exc).__name__}: {text.splitlines()[0] if text else ''}".rstrip(": ")


def _open_db(db_url: str | None, data_dir: str):
    from bench.service.db import default_url, open_database

    try:
        Path(data_dir).mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        _bad([f"{data_dir}: (--data): cannot create the directory: {exc.strerror or exc}"])
    try:
        return open_database(bounded_db_url(db_url) if db_url else default_url(Path(data_dir)))
    except Exception as exc:   # a wrong URL, an unreachable server: one line, no traceback
        _bad([f"{db_url or data_dir}: (database): cannot open: {_first_line(exc)}"])


@click.command()
@_data_option
@click.option("--host", default="127.0.0.1", show_default=True, help="Listen address (only loopback unless told).")
@click.option("--port", type=int, default=8750, show_default=True)
@click.option("--rigs", "rigs_path", type=click.Path(dir_okay=False), help="Rigs file [default: config/rigs.toml].")
@click.option("--scenarios", "scenario_root", type=click.Path(file_okay=False),
              help="Scenario root: submitted paths must lie under it [default: scenarios/].")
@click.option("--lease-ttl", "lease_ttl_s", type=float, default=10.0, show_default=True,
              help="Seconds a run's lease lives unless the service extends it.")
@click.option("--max-parallel", type=int, help="Run processes at once on this host [default: CPU count].")
@click.option("--run-start", type=click.Choice(["forkserver", "cold"]), default="forkserver", show_default=True,
              help="Run processes forked from a preloaded fork server (imports paid once), or each a new interpreter.")
@click.option("--live/--no-live", default=False, show_default=True,
              help="Runs write their run.rrd every 0.5 s, so the run page's embedded Rerun viewer follows them "
                   "closely (without: every 5 s). The viewer is served on this address behind the token either way.")
@click.option("--live-grpc-port", type=int, hidden=True, help="Ignored: no Rerun port is opened any more.")
@click.option("--live-web-port", type=int, hidden=True, help="Ignored: no Rerun port is opened any more.")
@click.option("--ssl-keyfile", type=click.Path(exists=True, dir_okay=False, readable=True),
              help="TLS key (uvicorn); with --ssl-certfile.")
@click.option("--ssl-certfile", type=click.Path(exists=True, dir_okay=False, readable=True),
              help="TLS certificate chain (uvicorn).")
@click.option("--host-id", help="Names this instance's runs when several share a database [default: host name].")
def serve(db_url, data_dir, host, port, rigs_path, scenario_root, lease_ttl_s, max_parallel, run_start, live, live_grpc_port,
          live_web_port, ssl_keyfile, ssl_certfile, host_id) -> None:
    """The bench service: HTTP API (OpenAPI at /openapi.json), run queue, leased rigs, web UI on HOST:PORT."""
    try:
        import uvicorn  # noqa: F401  (installed? bench.service.guard starts the server)

        from bench.service.app import create_app
        from bench.service.core import Service, ServiceSettings, serve_option_problems
    except ImportError as exc:
        _bad([f"drivebench serve: (install): {exc.name} is missing: pip install 'drivebench[service]'"])
    problems = serve_option_problems(port=port, lease_ttl_s=lease_ttl_s, max_parallel=max_parallel, host_id=host_id,
                                     live_grpc_port=live_grpc_port, live_web_port=live_web_port)
    if problems:
        _bad(problems)
    problems = _place_problems(host, port, scenario_root)
    if problems:
        _bad(problems)
    settings = ServiceSettings(data_dir=Path(data_dir), db_url=db_url, rigs_path=Path(rigs_path) if rigs_path else None,
                               scenario_root=Path(scenario_root) if scenario_root else None, lease_ttl_s=lease_ttl_s,
                               max_parallel=max_parallel, run_start=run_start, host_id=host_id)
    if live_grpc_port is not None or live_web_port is not None:
        click.echo("drivebench serve: --live-grpc-port/--live-web-port are ignored: the live view is served on "
                   "--host/--port behind the token (docs/service.md, Live view)", err=True)
    if live:
        from bench.service.live import LIVE_INTERVAL_S
        settings.live = True
        os.environ["DRIVEBENCH_RERUN_INTERVAL_S"] = str(LIVE_INTERVAL_S)    # inherited by the run processes
    try:
        service = Service(settings)
        service.register()        # this instance's liveness lease: refused while one with its --host-id lives
    except InputError as exc:
        _bad(exc.problems)
    except Exception as exc:
        _bad([f"{db_url or data_dir}: (database): cannot open: {type(exc).__name__}: {str(exc).splitlines()[0]}"])
    click.echo(f"drivebench serve: http{'s' if ssl_certfile else ''}://{host}:{port}/ "
               f"({'SQLite in ' + str(settings.data_dir) if service.db.is_sqlite else 'PostgreSQL'}, "
               f"{len(settings.rigs)} rigs)", err=True)
    from bench.service.guard import run_server
    run_server(create_app(service=service), host, port, ssl_keyfile, ssl_certfile)


def _place_problems(host: str, port: int, scenario_root: str | None) -> list[str]:
    """What would make the service fail after it started: a scenario root that is no directory, a port in use."""
    import socket

    if scenario_root is not None and not Path(scenario_root).is_dir():
        return [f"serve: --scenarios: {scenario_root}: not a directory"]
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except OSError as exc:
        return [f"serve: --host: {host}: {exc.strerror or exc}"]
    family, kind, proto, _, address = infos[0]
    with socket.socket(family, kind, proto) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)       # as uvicorn binds
        try:
            probe.bind(address)
        except OSError as exc:
            return [f"serve: --port: {host}:{port}: {exc.strerror or exc} (another service listens there? "
                    f"give another --port)"]
    return []


@click.group()
def token() -> None:
    """API tokens of the bench service (stored hashed; shown once)."""


@token.command("create")
@click.option("--role", type=click.Choice(["viewer", "operator", "admin"]), required=True)
@click.option("--name", required=True, help="Who or what uses it (shown as the holder of leases and runs).")
@_data_option
def token_create(role, name, db_url, data_dir) -> None:
    """Make a token and print it once on stdout (only its SHA-256 is stored)."""
    from bench.service.auth import create_token

    if not name.strip() or len(name) > 200:
        _bad([f"token create: --name: must be 1 to 200 characters, got {len(name)}"])
    db = _open_db(db_url, data_dir)
    token_id, value = create_token(db, name, role)
    db.dispose()
    click.echo(f"token {token_id} for {name} ({role}): shown once, keep it (e.g. in DRIVEBENCH_TOKEN)", err=True)
    click.echo(value)


@token.command("list")
@_data_option
def token_list(db_url, data_dir) -> None:
    """Tokens by id, name and role (never the token)."""
    from sqlalchemy import select

    from bench.service.db import Token, iso

    db = _open_db(db_url, data_dir)
    with db.session() as s:
        for t in s.execute(select(Token).order_by(Token.id)).scalars():
            click.echo(f"{t.id}\t{t.name}\t{t.role}\t{iso(t.created_ts)}\t{'revoked' if t.revoked else 'active'}")
    db.dispose()


@token.command("revoke")
@click.argument("token_id", type=click.IntRange(1, MAX_ID))
@_data_option
def token_revoke(token_id, db_url, data_dir) -> None:
    from bench.service.db import Token

    db = _open_db(db_url, data_dir)
    with db.session() as s:
        row = s.get(Token, token_id)
        if row is None:
            _bad([f"token {token_id}: not found"])
        row.revoked = True
    db.dispose()
    click.echo(f"token {token_id} revoked", err=True)


@click.command()
@click.argument("scenarios", nargs=-1, required=True)
@click.option("--server", required=True, envvar="DRIVEBENCH_SERVER", help="The service's URL.")
@click.option("--token", "token_value", envvar="DRIVEBENCH_TOKEN", help="API token [env DRIVEBENCH_TOKEN].")
@click.option("--rig", help="Run on this rig.")
@click.option("--tag", help="Run on any rig with this tag.")
@click.option("--seed", type=int, help="Override the scenarios' seed.")
@click.option("--wait", is_flag=True, help="Wait for the verdicts; exit like `drivebench run`.")
@click.option("--timeout", "timeout_s", type=float, default=3600.0, show_default=True, help="--wait at most this long.")
@click.option("--junit", "junit_path", type=click.Path(dir_okay=False), help="With --wait: write JUnit XML here.")
def submit(scenarios, server, token_value, rig, tag, seed, wait, timeout_s, junit_path) -> None:
    """Queue SCENARIOs on the bench service; with --wait, exit 0 if all passed, 1 if one failed or aborted,
    2 on bad input or an error. A local file is sent as its text; another path names a file under the service's
    scenario root."""
    from bench.faces.cli import criteria_table, make_console, verdict_exit_code
    from bench.service.client import Client, ClientError, write_junit

    if not token_value:
        _bad(["submit: --token: missing (or set DRIVEBENCH_TOKEN)"])
    if (rig is None) == (tag is None):
        _bad(["submit: --rig: give exactly one of --rig NAME or --tag TAG"])
    if junit_path and not wait:
        _bad(["submit: --junit: needs --wait (the verdicts are written when the runs end)"])
    if junit_path and not Path(junit_path).resolve().parent.is_dir():
        _bad([f"submit: --junit: {junit_path}: its directory does not exist"])
    if not 0 < timeout_s <= 7 * 24 * 3600:
        _bad([f"submit: --timeout: must be within (0, 604800] s, got {timeout_s:g}"])
    try:
        client = Client(server, token_value)
    except ClientError as exc:
        _bad(exc.lines)
    submitted: list[int] = []
    problems: list[str] = []
    for scenario in scenarios:
        try:
            answer = client.submit(scenario, rig, tag, seed)
        except ClientError as exc:
            problems.extend(exc.lines)
            continue
        submitted.append(answer["id"])
        click.echo(f"{scenario}: run {answer['id']} {answer['state']} {client.url('runs/%d' % answer['id'])}")
    if problems:
        for line in problems:
            click.echo(line, err=True)
        if submitted:
            click.echo(f"submitted {len(submitted)} of {len(scenarios)} runs", err=True)
        sys.exit(EXIT_ERROR)
    if not wait:
        sys.exit(EXIT_PASS)
    console = make_console()
    try:
        runs = client.wait(submitted, timeout_s, on_change=lambda r: click.echo(
            f"run {r['id']}: {r['state']}" + (f" on {r['rig']}" if r.get("rig") else ""), err=True))
    except ClientError as exc:
        _bad(exc.lines)
    verdicts = []
    for run_id in submitted:
        run = runs[run_id]
        state = run["state"]
        verdict = {"pass": "pass", "fail": "fail", "aborted": "aborted", "cancelled": "aborted"}.get(state, "error")
        verdicts.append(verdict)
        console.print(criteria_table(f"{run.get('scenario_name') or run['scenario']}: {run.get('verdict') or state} "
                                     f"({client.url('runs/%d' % run_id)})", run.get("criteria") or []))
        if run.get("reason"):
            console.print(f"  reason: {run['reason']}")
    if junit_path:
        write_junit(Path(junit_path), [runs[i] for i in submitted], server)
    if len(verdicts) > 1:
        console.print(f"{sum(v == 'pass' for v in verdicts)}/{len(verdicts)} passed")
    sys.exit(verdict_exit_code(verdicts))

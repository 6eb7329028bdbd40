"""The `drivebench` command line (also `python -m bench`).

Exit codes: 0 all passed, 1 a criterion failed or a run aborted, 2 bad input or an error.
Bad input is reported as one line per problem on stderr, without a traceback.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import re
import sys
import tomllib
from pathlib import Path
from typing import Any, Iterable

import click
from rich.console import Console
from rich.table import Table

from bench.faces import run_hooks
from drivers.contract.checks import find_repo_root
from drivers.contract.errors import InputError, LinkError
from drivers.contract.exits import EXIT_ERROR, EXIT_FAIL, EXIT_PASS
from drivers.contract.exits import fail as _fail, guarded as _guarded, problem_lines as _problem_lines

PROGRESS_MIN_DURATION_S = 3.0   # show a progress bar for scenarios at least this long (drive time)
URL_RE = re.compile(r"^(rerun(\+https?)?|https?)://")

def make_console(stderr: bool = False) -> Console:
    console = Console(stderr=stderr, highlight=False, soft_wrap=True)
    if not console.is_terminal:     # logs and pipes: do not squeeze tables into 80 columns
        columns = os.environ.get("COLUMNS", "")
        console.width = int(columns) if columns.isdigit() else 160   # fixed now: rich reads COLUMNS live
    return console


err_console = make_console(stderr=True)


def _out_console(as_json: bool) -> Console:
    # with --json, stdout carries JSON documents only; tables go to stderr
    return err_console if as_json else make_console()


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        if math.isnan(value):
            return "n/a"
        return f"{value:.4g}"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_fmt(v) for v in value) + "]"
    return "" if value is None else str(value)


def _as_dict(c: Any) -> dict:
    if isinstance(c, dict):
        return c
    if hasattr(c, "to_dict"):
        return c.to_dict()
    return dict(vars(c))


def criteria_table(title: str, criteria: Iterable[Any]) -> Table:
    table = Table(title=title, title_justify="left")
    table.add_column("criterion")
    table.add_column("signal", no_wrap=True)
    table.add_column("window [s]", no_wrap=True)
    table.add_column("value", justify="right", no_wrap=True)
    table.add_column("limit", justify="right", no_wrap=True)
    table.add_column("result", no_wrap=True)
    gaps = []
    for c in map(_as_dict, criteria):
        if c.get("passed"):
            result = "[green]pass[/green]"
        elif c.get("status") == "not_judged":
            gaps.append(f"{c.get('name')}: not judged: {c.get('detail')}")
            result = f"[yellow]not judged ({len(gaps)})[/yellow]"
        elif c.get("known_gap"):
            gaps.append(f"{c.get('name')}: {c['known_gap']}")
            result = f"[yellow]known gap ({len(gaps)})[/yellow]"
        else:
            result = "[red]FAIL[/red]"
        value = c.get("value")
        table.add_row(str(c.get("name")), str(c.get("signal")), _fmt(c.get("window_s")),
                      "n/a" if value is None else " ".join(filter(None, (_fmt(value), c.get("unit")))),
                      " ".join(filter(None, (_fmt(c.get("limit")), c.get("unit")))), result)
    if gaps:
        table.caption = "\n".join(f"({n}) {gap}" for n, gap in enumerate(gaps, start=1))
        table.caption_justify = "left"
    return table


VERDICT_STYLE = {"pass": "bold green", "fail": "bold red", "incomplete": "bold yellow", "aborted": "bold red",
                 "error": "bold magenta"}


def verdict_exit_code(verdicts: Iterable[str]) -> int:
    verdicts = list(verdicts)
    if any(v == "error" for v in verdicts):
        return EXIT_ERROR
    if any(v != "pass" for v in verdicts):
        return EXIT_FAIL
    return EXIT_PASS


def print_record(console: Console, record: dict, run_dir: Path | str) -> None:
    verdict = record.get("verdict", "?")
    scenario = record.get("scenario", {}) or {}
    name = scenario.get("name") or Path(str(scenario.get("path", "?"))).stem
    console.print(criteria_table(f"{name}: [{VERDICT_STYLE.get(verdict, 'bold')}]{verdict}[/] ({run_dir})",
                                 record.get("criteria", [])))
    if record.get("abort_reason"):
        console.print(f"  reason: {record['abort_reason']}")
    from bench.run.drill import UNVERIFIED, timings, unverified
    comm_loss = record.get("comm_loss") if isinstance(record.get("comm_loss"), dict) else None
    note = unverified(comm_loss)
    if note:
        console.print(f"  [bold yellow]{UNVERIFIED.upper()}[/]{note[len(UNVERIFIED):]}")
    elif timings(comm_loss):
        console.print(f"  {timings(comm_loss)}")
    warnings = [w for w in record.get("drive_warnings") or [] if isinstance(w, dict) and w.get("warning")]
    if warnings:
        emcy = next((w["emcy"] for w in warnings if w.get("emcy")), None)
        console.print(f"  [yellow]drive warning[/] (statusword bit 7) set {len(warnings)} time(s), first at "
                      f"t={warnings[0].get('t_s', float('nan')):.3f} s" + (f", EMCY {emcy} (ran on)" if emcy else ""))
    sync = record.get("sync") or {}
    if sync.get("intervals"):
        console.print(f"  SYNC {sync.get('period_ms')} ms at the bench: p50 {sync.get('p50_ms')} ms, p99 "
                      f"{sync.get('p99_ms')} ms, max {sync.get('max_ms')} ms, late {sync.get('late')} (> 1.5 periods), "
                      f"skipped {sync.get('skipped')}; time base: {sync.get('time_base')}"
                      + (f", {sync['unanswered']} SYNCs unanswered" if sync.get("unanswered") is not None else ""))
    elif sync.get("time_base"):
        console.print(f"  time base: {sync['time_base']} ({sync.get('timing')})")


# --- commands --------------------------------------------------------------------------------------------

class _WithPlugins(click.Group):
    """The bench's own commands, and those other packages register under the entry-point group `drivebench.commands`
    (the simulator's `sim`, `design-check` and `twin` come from sim_backend this way: the bench itself never imports
    the simulator). A plugin is imported when its command is named, not at every start: `twin` alone pulls in scipy
    and numba (1.0 s of a 1.7 s `drivebench --help`, measured)."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted({*super().list_commands(ctx), *_plugin_entries()})

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        found = super().get_command(ctx, name)
        entry = _plugin_entries().get(name)
        if found is not None or entry is None:
            return found
        try:
            command = entry.load()
        except Exception as exc:      # a broken plugin must not take the bench's own commands down
            err_console.print(f"warning: command {name!r} ({entry.value}) not available: {exc}")
            return None
        self.add_command(command, name)
        return command


@functools.cache
def _plugin_entries() -> dict:
    from importlib.metadata import entry_points

    return {entry.name: entry for entry in entry_points(group="drivebench.commands")}


@click.group(cls=_WithPlugins, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="drivebench")
def cli() -> None:
    """drivebench: hardware-in-the-loop test bench for sensorless motor drives."""


@cli.command()
@click.argument("scenarios", nargs=-1, required=True)
@click.option("--bench", "bench_path", type=click.Path(), help="Bench config (default: the one the scenario names).")
@click.option("--rerun", "rerun_mode", type=click.Choice(["spawn", "connect", "save", "off"]), default="save",
              show_default=True,
              help="Live view: spawn a viewer, connect URL to a running one, save run.rrd only, or off. "
                   "run.rrd is saved in every mode but off.")
@click.option("--rerun-url", help="Viewer URL for --rerun connect (also accepted right after 'connect').")
@click.option("--out", "out_root", type=click.Path(), default="runs", show_default=True, help="Run directories go here.")
@click.option("--seed", type=int, help="Override the scenario's seed.")
@click.option("--json", "as_json", is_flag=True, help="Print each record as one JSON document on stdout.")
def run(scenarios, bench_path, rerun_mode, rerun_url, out_root, seed, as_json) -> None:
    """Run SCENARIO files; exit 0 if all passed, 1 if one failed or aborted, 2 on bad input or error."""
    scenarios = list(scenarios)
    if rerun_mode == "connect" and rerun_url is None and scenarios and URL_RE.match(scenarios[0]):
        rerun_url = scenarios.pop(0)
    if not scenarios:
        raise click.UsageError("no SCENARIO given")
    sys.exit(run_many(scenarios, bench_path, out_root, seed, rerun_mode, rerun_url, as_json))


def run_many(scenarios, bench_path, out_root, seed, rerun_mode, rerun_url, as_json) -> int:
    from bench.run.orchestrator import run_scenario
    from bench.inputs.prepared import prepare_run

    problems: list[str] = []
    prepared = []
    for path in scenarios:  # validate everything before touching any hardware; each file is read once, here
        try:
            prepared.append((path, prepare_run(path, bench_path, seed=seed)))
        except (InputError, FileNotFoundError, tomllib.TOMLDecodeError, OSError) as exc:
            problems.extend(_problem_lines(exc))
    if problems:
        for line in problems:
            click.echo(line, err=True)
        return EXIT_ERROR

    out = _out_console(as_json)
    verdicts: list[str] = []
    hooks = run_hooks.installed                             # a run process of `drivebench serve`, else None
    for path, run in prepared:
        try:
            with _progress(run) as progress:
                result = run_scenario(run, out_root=out_root, rerun_mode=rerun_mode, rerun_url=rerun_url,
                                      progress=progress, warn=lambda line: click.echo(line, err=True),
                                      on_trip=hooks.trip_reporter() if hooks else None)
        except (InputError, FileNotFoundError, tomllib.TOMLDecodeError, LinkError, OSError) as exc:
            _fail(exc)
            verdicts.append("error")
            continue
        except Exception as exc:  # a bug before the run directory existed
            _fail(exc)
            verdicts.append("error")
            continue
        verdicts.append(result.verdict)
        if hooks is not None and (report := hooks.result_reporter()) is not None:
            report(result.run_dir, result.verdict, result.record)
        if as_json:
            click.echo(json.dumps(result.record, default=str))
        print_record(out, result.record, result.run_dir)
        if result.error and as_json:
            click.echo(f"{path}: error: {result.error}", err=True)
        if result.interrupted:
            click.echo("interrupted: not starting further scenarios", err=True)
            break
    if len(verdicts) > 1:
        out.print(f"{sum(v == 'pass' for v in verdicts)}/{len(verdicts)} passed")
    return verdict_exit_code(verdicts)


class _progress:
    """A rich progress bar with ETA on stderr for scenarios of PROGRESS_MIN_DURATION_S or more: the prepared run's
    scenario, the one that runs (validated against --bench like it)."""

    def __init__(self, prepared):
        self.prepared = prepared
        self.bar = None
        self.task = None

    def __enter__(self):
        hooks = run_hooks.installed
        if hooks is not None and (service_progress := hooks.progress_reporter()) is not None:
            return service_progress                         # a run process of `drivebench serve`
        duration = self.prepared.scenario.duration_s
        if duration < PROGRESS_MIN_DURATION_S or not err_console.is_terminal:
            return None
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

        self.bar = Progress(TextColumn("{task.description}"), BarColumn(),
                            TextColumn("{task.completed:.1f}/{task.total:.1f} s drive time"),
                            TimeElapsedColumn(), TimeRemainingColumn(), console=err_console, transient=True)
        self.bar.start()
        self.task = self.bar.add_task(Path(self.prepared.scenario.path).stem, total=duration)

        def update(t_s: float, total: float) -> None:
            self.bar.update(self.task, completed=t_s)

        return update

    def __exit__(self, *exc):
        if self.bar is not None:
            self.bar.stop()
        return False


def _file_kind(raw: dict) -> str:
    """"bench", "campaign" or "scenario": what a TOML file given to `validate` is, by its top-level keys."""
    if isinstance(raw.get("bench"), dict) and "drive" in raw:
        return "bench"
    if "scenarios" in raw and "duration_s" not in raw:
        return "campaign"
    return "scenario"


def _validate_campaign(path: Path) -> int:
    """The campaign file and each of its scenarios on its own bench; the number of problem lines printed."""
    from bench.faces.campaign import axis_points, load_campaign
    from bench.inputs.prepared import prepare_run

    camp = load_campaign(path)
    runs = len(camp.scenarios) * len(camp.seeds) * len(axis_points(camp))
    click.echo(f"{path}: ok (campaign {camp.name!r}, {len(camp.scenarios)} scenarios, {len(camp.seeds)} seeds, "
               f"{runs} runs)")
    bad = 0
    for scenario in camp.scenarios:
        try:
            prepare_run(scenario)
        except (InputError, FileNotFoundError, tomllib.TOMLDecodeError, OSError) as exc:
            for line in _problem_lines(exc):
                click.echo(line, err=True)
                bad += 1
    return bad


@cli.command()
@click.argument("files", nargs=-1, required=True)
@click.option("--bench", "bench_path", type=click.Path(), help="Validate scenarios against this bench config.")
def validate(files, bench_path) -> None:
    """Check scenario, campaign and bench config FILEs; one line per problem, exit 2 if any. For a scenario, also the
    criteria its bench cannot judge (signals it does not measure); for a campaign, each of its scenarios."""
    from bench.inputs.benchconfig import load_bench_config
    from bench.inputs.criteria import signals_of
    from bench.run.load_emulation import emulates_on
    from bench.inputs.prepared import prepare_run
    from bench.inputs.scenario import read_scenario_source

    bad = False
    for name in files:
        path = Path(name)
        try:
            source = read_scenario_source(path)
            kind = _file_kind(source[0])
            if kind == "campaign":
                bad = _validate_campaign(path) > 0 or bad
            elif kind == "bench":
                cfg = load_bench_config(path)
                load = f"load over {cfg.load['transport']}" if cfg.load else "no load machine"
                click.echo(f"{path}: ok (bench config {cfg.bench.name!r}, drive over {cfg.drive['transport']}, "
                           f"{load})")
            else:
                prepared = prepare_run(path, bench_path, source=source)
                scenario, cfg = prepared.scenario, prepared.bench
                click.echo(f"{path}: ok (scenario {scenario.name!r}, {scenario.duration_s:g} s, "
                           f"{len(scenario.criteria)} criteria, bench {cfg.bench.name!r})")
                for i, seg in enumerate(scenario.load_segments):
                    if emulates_on(cfg, seg.mode):
                        click.echo(f"{path}: load[{i}] ({seg.kind}): emulated by the bench on {cfg.bench.name!r}: "
                                   f"its load machine has no {seg.mode.name.lower()} mode; a torque setpoint from the "
                                   f"measured shaft speed every SYNC ({cfg.drive['sync_period_s']:g} s; "
                                   f"docs/scenarios.md, emulated loads)")
                measurable = prepared.measurable
                for i, criterion in enumerate(scenario.criteria):
                    missing = [s for s in signals_of(criterion) if s not in measurable]
                    if missing:
                        click.echo(f"{path}: criteria[{i}] ({criterion.name}): not judged on bench "
                                   f"{cfg.bench.name!r}: {', '.join(missing)} not measured there")
        except (InputError, FileNotFoundError, tomllib.TOMLDecodeError, OSError) as exc:
            bad = True
            for line in _problem_lines(exc):
                click.echo(line, err=True)
    sys.exit(EXIT_ERROR if bad else EXIT_PASS)


@cli.command()
@click.option("--bench", "bench_path", type=click.Path(), required=True, help="The rig's bench config.")
@click.option("--scan", is_flag=True, help="Also list every node on the CAN bus that answers (node ids 1-127).")
@click.option("--drill", is_flag=True, help="Also run the bench-death drill: enables the drive at zero velocity, "
                                            "withholds the bench's heartbeat and the load machine's watchdog feed, "
                                            "and checks both stop themselves (docs/rig.md).")
@click.option("--json", "as_json", is_flag=True, help="Print the report as JSON.")
def probe(bench_path, scan, drill, as_json) -> None:
    """What the drive says about itself before the first run: identity, device type, modes, units and factor
    group, PDO mappings, heartbeat and comm-loss objects, drivebench features, and the profile the bench would use
    (or what to fix in the bench config). Read-only (nothing is written to the drive) unless --drill is given;
    with --drill, exit 1 when the drive or the load machine fails it."""

    def body() -> int:
        from bench.inputs.benchconfig import load_bench_config
        from bench.run.links import started_services

        cfg = load_bench_config(bench_path, for_probe=not drill)
        drive = cfg.drive
        items = None
        with started_services(cfg, 0) as live:
            section = live.drive
            if drive["transport"] == "canopen":
                from drivers.canopen.probe import probe as probe_canopen, scan as scan_bus
                report = {"bench": cfg.bench.name, "drive": probe_canopen(section, find_repo_root(bench_path))}
                if scan:
                    report["nodes"] = scan_bus(section)
                items = True
            else:
                from bench.run.links import make_links
                link, _ = make_links(live, find_repo_root(bench_path))
                try:
                    identity = link.open()
                    report = {"bench": cfg.bench.name, "drive": {
                        "identity": dataclasses.asdict(identity), "control_period_s": link.control_period_s,
                        "parameters": list(link.parameters)}}
                finally:
                    link.close()
            refused = None
            if drill:
                from bench.run.drill import drill_rig, refusal, timings, unverified
                from bench.run.orchestrator import LIVE_SIGNALS
                report["drill"] = drill_rig(live, find_repo_root(bench_path), LIVE_SIGNALS)
                refused = refusal(report["drill"])
        if items:
            from bench.faces.checklist import as_json as items_json, checklist
            items = checklist(report["drive"], cfg, report.get("drill"))
            report["checklist"] = items_json(items)
        if as_json:
            click.echo(json.dumps(report, default=str, indent=2))
        elif items:
            identity = report["drive"]["identity"]
            click.echo(f"node {report['drive']['node_id']}: {identity['device_name'] or '?'} (vendor "
                       f"{identity['vendor_id']}, product {identity['product_code']}, software "
                       f"{identity['software_version'] or '?'})")
            for item in items:
                click.echo(item.line())
            for node in report.get("nodes", []):
                click.echo(f"on the bus: node {node['node_id']} device type {node['device_type']}")
            click.echo("(--json for everything the probe read)")
            if drill:
                for line in (refused, unverified(report["drill"]), timings(report["drill"])):
                    if line:
                        click.echo(line)
        else:
            make_console().print(report)
        return EXIT_FAIL if drill and refused else EXIT_PASS

    sys.exit(_guarded(body))


def _scenario_root() -> Path:
    here = Path("scenarios")
    return here if here.is_dir() else find_repo_root() / "scenarios"


def _first_comment(path: Path) -> str:
    """A scenario without `description`: its leading comment line, if any."""
    for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
        if line.startswith("#"):
            return line.lstrip("# ").strip()
        if line.strip():
            break
    return ""


@cli.command(name="list")
def list_scenarios() -> None:
    """Scenarios under scenarios/ with their one-line descriptions."""
    from bench.inputs.scenario import load_scenario

    root = _scenario_root()
    files = sorted(root.rglob("*.toml"))
    if not files:
        click.echo(f"no scenarios under {root}", err=True)
        sys.exit(EXIT_PASS)
    table = Table(show_header=True, box=None, pad_edge=False)
    table.add_column("scenario")
    table.add_column("description")
    for f in files:
        try:
            description = load_scenario(f).description.strip().splitlines()
            description = description[0] if description else _first_comment(f)
        except InputError as exc:
            description = f"[red]invalid[/red]: {exc.problems[0] if exc.problems else exc}"
        table.add_row(str(f), description)
    make_console().print(table)


@cli.command()
@click.argument("run_dir", type=click.Path())
@click.option("--json", "as_json", is_flag=True, help="Print the record as JSON.")
def show(run_dir, as_json) -> None:
    """The verdict table of a run directory (also of a killed, incomplete run)."""

    def body() -> int:
        from bench.outputs.run_files import load_run

        record, columns, complete = load_run(Path(run_dir))
        n = len(columns.get("t_s", ())) if columns else 0
        if as_json:
            click.echo(json.dumps({**record, "_complete": complete, "_samples": n}, default=str))
            return verdict_exit_code([record.get("verdict") or "aborted"]) if complete else EXIT_FAIL
        console = make_console()
        if not complete:
            last = float(columns["t_s"][-1]) if n else float("nan")
            console.print(f"[bold red]incomplete run[/] ({run_dir}): the bench did not finish the record "
                          f"(killed?); {n} samples recovered, up to t = {_fmt(last)} s")
            return EXIT_FAIL
        print_record(console, record, run_dir)
        console.print(f"  {n} samples, seed {record.get('seed')}, drive "
                      f"{(record.get('drive') or {}).get('firmware_version', '?')}, "
                      f"{record.get('started_utc', '?')} .. {record.get('ended_utc', '?')}")
        return verdict_exit_code([record.get("verdict", "error")])

    sys.exit(_guarded(body))


@cli.command(name="evaluate")
@click.argument("run_dir", type=click.Path())
@click.option("--scenario", "scenario_path", type=click.Path(), help="Judge against this scenario's criteria "
              "(default: the scenario file the record names).")
@click.option("--json", "as_json", is_flag=True, help="Print the new criteria table as JSON.")
def evaluate_cmd(run_dir, scenario_path, as_json) -> None:
    """Re-judge a recorded run offline (e.g. against changed criteria); the record is not modified."""

    def body() -> int:
        import numpy as np

        from bench.inputs.criteria import evaluate, time_axis, verdict
        from bench.outputs.run_files import load_run
        from bench.inputs.scenario import load_scenario

        record, columns, complete = load_run(Path(run_dir))
        path = scenario_path or (record.get("scenario") or {}).get("path")
        if not path:
            raise InputError([f"{run_dir}: record.json: scenario.path: missing; give --scenario FILE"])
        scenario = load_scenario(path)
        t = np.asarray(columns.get("t_s", np.zeros(0)))
        in_test = t <= scenario.duration_s + 1e-9
        measured = record.get("measured_signals")
        from bench.inputs.capture_criteria import judge_with_records
        from bench.outputs.export_instruments import run_records
        results = judge_with_records(scenario.criteria, lambda specs: evaluate(
            specs, t[in_test], {k: np.asarray(v)[in_test] for k, v in columns.items() if k != "t_s"},
            measured=frozenset(measured) if isinstance(measured, list) else None,
            row_period_s=(record.get("time_axis") or {}).get("row_period_s"),
            tolerance=(record.get("time_axis") or {}).get("tolerance", 1.5)), *run_records(Path(run_dir), record))
        aborted = (not complete) or record.get("verdict") in ("aborted", "error")
        holes = time_axis(t[in_test], (record.get("time_axis") or {}).get("row_period_s"),
                          (record.get("time_axis") or {}).get("tolerance", 1.5))
        new_verdict = verdict(results, aborted=aborted, holes=holes)
        if as_json:
            click.echo(json.dumps({"run_dir": str(run_dir), "scenario": str(path), "verdict": new_verdict,
                                  "criteria": [r.to_dict() for r in results]}, default=str))
        else:
            console = make_console()
            console.print(criteria_table(f"{scenario.name} re-evaluated: "
                                         f"[{VERDICT_STYLE.get(new_verdict, 'bold')}]{new_verdict}[/] "
                                         f"(recorded: {record.get('verdict')})", results))
            if (record.get("scenario") or {}).get("sha256") not in (None, scenario.sha256):
                console.print(f"  scenario file differs from the one recorded ({path})")
            if not complete:
                console.print("  the record is incomplete (killed run): judged on the recovered samples")
        return verdict_exit_code([new_verdict])

    sys.exit(_guarded(body))


@cli.command()
@click.argument("run_dirs", nargs=-1, required=True)
@click.option("--out", "out_md", type=click.Path(dir_okay=False), default=None,
              help="Markdown report to write, plots in a folder beside it (default: report.md beside the runs).")
@click.option("--suites", type=click.Path(dir_okay=False), default=None,
              help="Paper-suites file: its scenario folders are reported as the papers' claims "
                   "(config/report/paper-suites.toml makes docs/validation.md).")
def report(run_dirs, out_md, suites) -> None:
    """Report over RUN_DIRs: every criterion with its limit, basis and measured value, a plot per run."""
    from bench.outputs import report as report_module

    sys.exit(_guarded(lambda: int(report_module.main(list(run_dirs), out_md, suites))))


@cli.command()
@click.argument("run_dir", type=click.Path(file_okay=False))
@click.option("--format", "fmt", type=click.Choice(["mf4", "csv"]), required=True,
              help="mf4: ASAM MDF 4 (asammdf, CANape, INCA, DIAdem); csv: a spreadsheet.")
@click.option("--out", type=click.Path(dir_okay=False), default=None,
              help="File to write (default: RUN_DIR/telemetry.mf4 or .csv).")
def export(run_dir, fmt, out) -> None:
    """A run's telemetry for other tools: the drive clock t_s as the master channel, one channel per measured
    signal with its unit, the record attached (mf4)."""
    from bench.outputs.export import export_run

    def go() -> int:
        click.echo(f"wrote {export_run(run_dir, fmt, out)}")
        return EXIT_PASS

    sys.exit(_guarded(go))


@cli.command()
@click.argument("run_a", type=click.Path(file_okay=False))
@click.argument("run_b", type=click.Path(file_okay=False))
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False), default=None,
              help="PNG of the signals overlaid on the drive clock (default: none).")
@click.option("--json", "as_json", is_flag=True, help="Print the comparison as one JSON document.")
def compare(run_a, run_b, plot_path, as_json) -> None:
    """Two runs side by side: what differs in what ran, each criterion in both with its delta, each signal's
    difference over the drive-clock span both cover."""
    from bench.outputs.compare import compare_runs, write_plot

    def go() -> int:
        result = compare_runs(run_a, run_b)
        if plot_path:
            result["plot"] = str(write_plot(run_a, run_b, Path(plot_path)))
        if as_json:
            click.echo(json.dumps(result, default=str))
        else:
            _print_comparison(result)
        return EXIT_PASS

    sys.exit(_guarded(go))


def _print_comparison(result: dict) -> None:
    from bench.faces.compare_text import print_comparison

    print_comparison(result, make_console(), _fmt)


def quiet_third_party_logs() -> None:
    """pymodbus and Rerun write their own lines (a refused connection, a viewer not found) before the bench's one clear
    line: quiet unless asked for (DRIVEBENCH_DEBUG=1, or RUST_LOG set for Rerun)."""
    import logging

    if os.environ.get("DRIVEBENCH_DEBUG"):
        return
    os.environ.setdefault("RUST_LOG", "off")     # Rerun's SDK logs through Rust's env_logger
    for name in ("pymodbus", "pymodbus.logging"):
        logging.getLogger(name).setLevel(logging.CRITICAL)


def main(argv: list[str] | None = None) -> int:
    """Every bad argument, click's own usage errors included, is one line on stderr and exit 2."""
    quiet_third_party_logs()
    try:
        result = cli.main(args=argv, prog_name="drivebench", standalone_mode=False)
    except SystemExit as exc:
        return int(exc.code or 0) if not isinstance(exc.code, str) else EXIT_ERROR
    except click.UsageError as exc:
        where = exc.ctx.command_path if exc.ctx is not None else "drivebench"
        click.echo(f"{where}: {' '.join(exc.format_message().split())}", err=True)
        return EXIT_ERROR
    except click.ClickException as exc:
        click.echo(f"drivebench: {' '.join(exc.format_message().split())}", err=True)
        return EXIT_ERROR
    except click.Abort:                          # Ctrl-C outside a run (a run handles it itself)
        click.echo("drivebench: aborted", err=True)
        return EXIT_FAIL
    return result if isinstance(result, int) else EXIT_PASS

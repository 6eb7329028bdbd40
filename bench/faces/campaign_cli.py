"""`drivebench campaign FILE`: registered through the drivebench.commands entry points (like `sim` and `serve`)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import click

EXIT_ACCEPTED, EXIT_NOT_ACCEPTED, EXIT_ERROR = 0, 1, 2


@click.command("campaign")
@click.argument("campaign_file", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--workers", type=click.IntRange(1, 64), default=2, show_default=True,
              help="Local engine: worker processes (reused from point to point).")
@click.option("--engine", type=click.Choice(["local", "ray"]), default="local", show_default=True)
@click.option("--address", default=None, help="Ray: the cluster's address (default: start or join a local one).")
@click.option("--out", "out_dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Results directory (default: campaigns/out/NAME). An existing one is resumed.")
@click.option("--dry-run", is_flag=True, help="List the points (scenario, seed, axes) and which a resume would "
                                              "skip; run nothing.")
def campaign(campaign_file: Path, workers: int, engine: str, address: str | None, out_dir: Path | None,
             dry_run: bool) -> None:
    """Run a campaign: scenarios x seeds x parameter axes, pass rates with their confidence intervals.

    Exit 0 accepted, 1 not accepted (or a run errored), 2 bad input."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    from bench.faces.campaign import load_campaign
    from bench.faces.campaign_run import done_ids, run_campaign, write_results
    from bench.faces.cli import _fail
    from drivers.contract.errors import InputError

    try:
        camp = load_campaign(campaign_file)
        out = out_dir or Path("campaigns") / "out" / camp.name
        problem = _out_problem(out)
        if problem:
            raise InputError([f"campaign: --out: {problem}"])
        if dry_run:
            sys.exit(_dry_run(camp, out))
        resumed = len(done_ids(out)) if out.is_dir() else 0
        started = time.monotonic()
        with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                      TextColumn("[green]{task.fields[passed]} pass[/] [red]{task.fields[other]} other[/]"),
                      TimeElapsedColumn(), TimeRemainingColumn(), transient=True,
                      disable=not sys.stderr.isatty()) as bar:
            task = bar.add_task(camp.name, total=None, passed=0, other=0)

            def progress(done: int, total: int, passed: int, other: int) -> None:
                bar.update(task, completed=done, total=total, passed=passed, other=other)

            rows = run_campaign(camp, out, workers=workers, engine=engine, address=address, progress=progress)
        result = write_results(camp, out, rows)
    except Exception as exc:
        sys.exit(_fail(exc))
    wall = time.monotonic() - started
    ran = f"{result['runs'] - resumed} run now, {resumed} resumed from {out}" if resumed else "all run now"
    click.echo(f"{camp.name}: {result['runs']} runs ({ran}) in {wall:.1f} s; "
               f"{'accepted' if result['accepted'] else 'NOT accepted'}; report {out / 'report.md'}")
    sys.exit(EXIT_ACCEPTED if result["accepted"] else EXIT_NOT_ACCEPTED)


def _out_problem(out: Path) -> str | None:
    """Why the results directory cannot be made or written (a file on its path, no write permission), or None."""
    import os

    for place in (out, *out.parents):
        if place.exists():
            if not place.is_dir():
                return f"{out}: {place} is a file, not a directory"
            if not os.access(place, os.W_OK | os.X_OK):
                return f"{out}: {place} is not writable"
            return None
    return None


def _dry_run(camp, out: Path) -> int:
    """One line per point and which a resume would skip; nothing written."""
    from bench.faces.campaign import points
    from bench.faces.campaign_run import done_ids

    finished = done_ids(out) if out.is_dir() else {}
    todo = points(camp)
    for p in todo:
        axes = ", ".join(f"{k}={v:g}" for k, v in p.axes) or "-"
        state = "done (a resume skips it)" if p.point_id in finished else "to run"
        click.echo(f"{p.point_id}  {p.source.name}  seed {p.seed}  {axes}  {state}")
    skipped = sum(p.point_id in finished for p in todo)
    click.echo(f"{camp.name}: {len(todo)} points, {len(todo) - skipped} to run, {skipped} done in {out}; "
               "nothing run (--dry-run)")
    return EXIT_ACCEPTED

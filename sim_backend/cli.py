"""The simulator's commands, plugged into `drivebench` through the entry-point group `drivebench.commands`
(pyproject.toml): `drivebench sim serve` and `drivebench design-check`."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from drivers.contract.exits import EXIT_FAIL, EXIT_PASS, guarded as _guarded, json_default as _json_default


@click.command(name="design-check")
@click.argument("motor_config", type=click.Path())
@click.option("--json", "as_json", is_flag=True, help="Print the result as JSON.")
def design_check(motor_config, as_json) -> None:
    """Small-signal stability of the estimator design over the speed range (exit 1 if unstable)."""

    def body() -> int:
        from sim_backend.design_check import format_table, run_design_check

        result = run_design_check(Path(motor_config))
        if as_json:
            click.echo(json.dumps(result, default=_json_default))
        else:
            click.echo(format_table(result))
        return EXIT_PASS if float(result["max_real_part"]) < 0 else EXIT_FAIL

    sys.exit(_guarded(body))


@click.group()
def sim() -> None:
    """The simulated backend."""


@sim.command()
@click.option("--config", "config_path", type=click.Path(), required=True, help="Bench config with [simulator.serve].")
def serve(config_path) -> None:
    """Serve simulated drives over socketcand / serial TCP / Modbus TCP on 127.0.0.1 until Ctrl-C."""

    def body() -> int:
        from sim_backend.serve import main as serve_main

        try:
            return int(serve_main(config_path) or 0)
        except KeyboardInterrupt:
            return EXIT_PASS

    sys.exit(_guarded(body))

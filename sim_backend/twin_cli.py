"""`drivebench twin RUN_DIR [--motor FILE] [--fit] [--json]`, plugged in through the entry-point group
`drivebench.commands` (pyproject.toml). Exit 0: every compared signal inside its tube (with --fit: the fitted twin's),
1: outside, 2: bad input (one line `file: field: reason`)."""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import click

from drivers.contract.errors import InputError

from sim_backend import twin as tw

EXIT_INSIDE, EXIT_OUTSIDE, EXIT_ERROR = 0, 1, 2


def _tolerances(items: tuple[str, ...]) -> dict[str, float]:
    out = {}
    for item in items:
        name, _, value = item.partition("=")
        try:
            number = float(value)
        except ValueError:
            number = math.nan
        if name not in tw.COMPARED or not math.isfinite(number) or number <= 0:
            raise InputError(f"--tol: {item}: expected SIGNAL=VALUE > 0 with SIGNAL one of "
                                    f"{', '.join(tw.COMPARED)}")
        out[name] = number
    return out


def _signals_doc(results: list[tw.TubeResult]) -> list[dict[str, Any]]:
    return [r.to_dict() for r in results]


def _table(title: str, results: list[tw.TubeResult]) -> str:
    lines = [title, f"  {'signal':<24} {'tube':>10} {'result':>8} {'max outside':>12} {'at t_s':>8} "
                    f"{'outside':>8} {'first exit':>10} {'rms diff':>10}"]
    for r in results:
        lines.append(f"  {r.signal:<24} {'+-' + format(r.value_tol, 'g'):>10} {'inside' if r.inside else 'OUTSIDE':>8} "
                     f"{r.max_excess:>12.4g} {'' if r.t_max_excess_s is None else format(r.t_max_excess_s, '.3f'):>8} "
                     f"{r.fraction_outside:>8.1%} "
                     f"{'' if r.first_exit_s is None else format(r.first_exit_s, '.3f'):>10} {r.rms_difference:>10.4g}")
    return "\n".join(lines)


def run_twin(run_dir: str, motor: str | None, do_fit: bool | str, params: tuple[str, ...], write_motor: str | None,
             plot_path: str | None, tolerances: dict[str, float], time_tol_s: float,
             blind_speed: float = tw.BLIND_SPEED) -> dict[str, Any]:
    run = tw.read_run(run_dir)
    motor_path = Path(motor) if motor else run.motor_path
    if motor_path is None:
        raise InputError(f"{Path(run_dir) / tw.RECORD}: bench.path: the run's bench names no [simulator] "
                                f"motor (a real rig): give the motor file with --motor")
    cfg = tw.read_motor(motor_path)
    tw.build_drive(cfg, where=str(motor_path)).step(1)          # a bad motor file fails here; kernels compiled
    t0 = time.perf_counter()
    twin = tw.replay(cfg, run, where=str(motor_path))
    replay_s = time.perf_counter() - t0
    results = tw.compare(run, twin, tolerances, time_tol_s, blind_speed, cfg["motor"]["kind"])
    if not results:
        raise InputError(f"{run.run_dir / tw.TELEMETRY}: (file): none of {', '.join(tw.COMPARED)} is recorded")
    doc: dict[str, Any] = {
        "run_dir": str(run.run_dir), "motor": str(motor_path), "kind": cfg["motor"]["kind"],
        "inside": all(r.inside for r in results), "signals": _signals_doc(results), "replay_s": replay_s,
        "rows": int(run.t.size), "duration_s": float(run.t[-1]), "time_tol_s": time_tol_s,
        "blind_speed_mech_rad_s": blind_speed,
        "injections": {"source": run.injections_source,
                       "replayed": [vars(i) for i in run.injections if i.name not in tw.not_replayed(run)],
                       "not_replayed": tw.not_replayed(run)},
        "notes": run.notes,
    }
    shown = (twin, results, f"twin of {run.run_dir.name} with {motor_path.name}")
    if do_fit:
        from sim_backend.twin_fit import MECHANICS, fit, fit_mechanics, write_motor as write_fitted

        if do_fit == "mechanics":
            result = fit_mechanics(run, start={k: tw.get_key(cfg, k) for k in MECHANICS})
        else:
            result = fit(cfg, run, params or None)
        fitted_cfg = tw.with_values(cfg, result.values)
        twin_fit = tw.replay(fitted_cfg, run)
        after = tw.compare(run, twin_fit, tolerances, time_tol_s, blind_speed, cfg["motor"]["kind"])
        doc["before"] = {"motor": str(motor_path), "inside": doc["inside"], "signals": doc["signals"]}
        doc["inside"] = all(r.inside for r in after)
        if not doc["inside"]:
            # a motor that does not explain the run: its values are where the optimiser stopped, not the rig's motor
            why = ("the fitted twin leaves the tube (" + ", ".join(r.signal for r in after if not r.inside)
                   + "): no motor of this model found that explains the run; the value is where the fit stopped")
            for p in result.params:
                p.identified = False
                p.reason = f"{why}; {p.reason}" if p.reason else why
        doc.update(result.to_dict())
        doc["signals"] = _signals_doc(after)
        if write_motor:
            write_fitted(motor_path, result, run.run_dir.name, Path(write_motor))
            doc["motor_written"] = write_motor
        shown = (twin_fit, after, f"fitted twin of {run.run_dir.name} (from {motor_path.name})")
        doc["_before_results"] = results
        doc["_after_results"] = after
    else:
        doc["_before_results"] = results
    plot_file = Path(plot_path) if plot_path else run.run_dir / "twin.png"
    try:
        tw.plot(run, shown[0], shown[1], plot_file, shown[2])
        doc["plot"] = str(plot_file)
    except OSError as exc:
        doc["plot_error"] = f"{plot_file}: {exc.strerror or exc}"
    return doc


def _text(doc: dict[str, Any]) -> str:
    out = [f"twin of {doc['run_dir']} ({doc['rows']} rows, {doc['duration_s']:.3f} s) replayed in "
           f"{doc['replay_s']:.2f} s; time tolerance +-{doc['time_tol_s'] * 1e3:g} ms; estimates not compared near "
           f"zero speed (|speed_est| < {doc['blind_speed_mech_rad_s']:g} rad/s, +-20 ms)"]
    inj = doc["injections"]
    if inj["replayed"] or inj["not_replayed"]:
        out.append(f"injections ({inj['source']}): replayed {', '.join(i['name'] for i in inj['replayed']) or 'none'}"
                   + (f"; not replayed (rig faults): {', '.join(inj['not_replayed'])}" if inj["not_replayed"] else ""))
    out += [f"note: {n}" for n in doc["notes"]]
    before = doc["_before_results"]
    out.append(_table(f"with {doc['motor']}: {'INSIDE' if all(r.inside for r in before) else 'OUTSIDE'} the tube",
                      before))
    if "fitted" in doc:
        f = doc["fit"]
        how = (f"{f['replays']} replays" if f["replays"] else f["message"])
        out.append(f"fit: {len(doc['fitted'])} parameters over {', '.join(f['signals'])} ({f['residuals']} residuals), "
                   f"{how}, {f['time_s']:.1f} s; cost {f['cost_start']:.4g} -> {f['cost']:.4g}")
        out.append(f"  {'parameter':<28} {'start':>11} {'fitted':>11} {'change':>8}  95 % interval")
        for key, p in doc["fitted"].items():
            flag = "" if p["identified"] else f"   NOT IDENTIFIED: {p['reason']}"
            out.append(f"  {key:<28} {p['start']:>11.5g} {p['value']:>11.5g} {p['change_pct']:>+7.2f}%  "
                       f"[{p['interval'][0]:.5g}, {p['interval'][1]:.5g}]{flag}")
        out.append(_table(f"with the fitted motor: {'INSIDE' if doc['inside'] else 'OUTSIDE'} the tube",
                          doc["_after_results"]))
        if "motor_written" in doc:
            out.append(f"fitted motor written: {doc['motor_written']}")
    if "plot" in doc:
        out.append(f"plot: {doc['plot']}")
    if "plot_error" in doc:
        out.append(f"plot not written: {doc['plot_error']}")
    return "\n".join(out)


@click.command(name="twin")
@click.argument("run_dir", type=click.Path())
@click.option("--motor", type=click.Path(), help="Motor file of the twin (default: the [simulator] motor of the "
              "run's bench config; required for a real rig's run).")
@click.option("--fit", "do_fit", is_flag=True, help="Fit the motor's [plant] and [mechanics] values to the run.")
@click.option("--fit-mechanics", is_flag=True, help="Fit only J and B, by linear least squares on the shaft speed, "
              "the drive's reported torque (torque_est_nm) and the measured load: for a drive whose firmware is a "
              "black box (a vendor EDS drive).")
@click.option("--param", "params", multiple=True, help="Fit only this dotted key (repeatable), e.g. plant.rs_ohm.")
@click.option("--write-motor", type=click.Path(), help="With --fit or --fit-mechanics: write the fitted motor file here.")
@click.option("--plot", "plot_path", type=click.Path(), help="PNG of recorded, twin and tube (default RUN_DIR/twin.png).")
@click.option("--tol", "tol_items", multiple=True, help="Value tolerance SIGNAL=VALUE in the signal's unit (repeatable).")
@click.option("--time-tol", "time_tol_s", type=float, default=tw.TIME_TOL_S, show_default=True,
              help="Time tolerance of the tube, s.")
@click.option("--blind-speed", type=float, default=tw.BLIND_SPEED, show_default=True,
              help="Leave the drive's estimates out of the comparison within 20 ms of |speed estimate| below this, "
                   "mech rad/s (0: compare everything).")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document.")
def twin(run_dir, motor, do_fit, fit_mechanics, params, write_motor, plot_path, tol_items, time_tol_s, blind_speed,
         as_json) -> None:
    """Replay a recorded run through the simulated drive, show where twin and rig part; --fit the motor."""
    try:
        if do_fit and fit_mechanics:
            raise InputError("--fit-mechanics: --fit: give one of them")
        if write_motor and not (do_fit or fit_mechanics):
            raise InputError(f"{write_motor}: --write-motor: needs --fit or --fit-mechanics")
        do_fit = "mechanics" if fit_mechanics else do_fit
        if not (math.isfinite(time_tol_s) and time_tol_s >= 0):
            raise InputError(f"--time-tol: {time_tol_s}: expected a number of seconds >= 0")
        if not (math.isfinite(blind_speed) and blind_speed >= 0):
            raise InputError(f"--blind-speed: {blind_speed}: expected a speed in mech rad/s >= 0")
        for option, target in (("--plot", plot_path), ("--write-motor", write_motor)):
            folder = Path(target).parent if target else None
            if folder is not None and not folder.is_dir():      # asked for a file it cannot write: before the replay
                raise InputError(f"{target}: {option}: {folder} is not a directory")
        doc = run_twin(run_dir, motor, do_fit, params, write_motor, plot_path, _tolerances(tol_items), time_tol_s,
                       blind_speed)
    except InputError as exc:
        click.echo(" ".join(str(exc).split()), err=True)
        sys.exit(EXIT_ERROR)
    except Exception as exc:                    # an unforeseen failure: one line, never a traceback
        click.echo(f"{run_dir}: (twin): {type(exc).__name__}: {' '.join(str(exc).split())}", err=True)
        sys.exit(EXIT_ERROR)
    if as_json:
        public = {k: v for k, v in doc.items() if not k.startswith("_")}
        click.echo(json.dumps(_strict(public), allow_nan=False))
    else:
        click.echo(_text(doc))
    sys.exit(EXIT_INSIDE if doc["inside"] else EXIT_OUTSIDE)


def _strict(value: Any) -> Any:
    """Plain JSON: numpy scalars to Python, paths to strings, non-finite numbers (an unbounded interval) to null."""
    if isinstance(value, dict):
        return {str(k): _strict(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_strict(v) for v in value]
    if hasattr(value, "item") and not isinstance(value, (str, bytes)):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Path):
        return str(value)
    return value

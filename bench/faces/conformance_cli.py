"""`drivebench conformance --bench CFG [--json] [--junit FILE] [--out DIR] [--compare OTHER.json] [--only NAME...]`.

The drive's transport brings its port under the entry-point group `drivebench.conformance_ports` (this module names
none). The reference sensor is the rig's: the load machine's encoder ([reference] source = "load"), else the drive's
own report of the rig encoder where it carries drivebench's extension, else the drive's velocity actual value (said
so in the report: a drive judged on its own word). The load machine, where there is one, is kept at zero torque and
disabled before, during and after the suite.
Exit: 0 no failed test, 1 a test failed (a finding), 2 bad input or the suite could not run.
"""

from __future__ import annotations

import json
import struct
import sys
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any, Callable

import click

from drivers.contract.checks import find_repo_root
from drivers.contract.errors import InputError
from drivers.contract.exits import EXIT_FAIL, EXIT_PASS, guarded



def _port(cfg: Any, base_dir: Path) -> Any:
    transport = cfg.drive.get("transport")
    ports = {e.name: e for e in entry_points(group="drivebench.conformance_ports")}
    if transport not in ports:
        raise InputError([f"{cfg.path}: drive.transport: no conformance port for transport {transport!r} "
                          f"(have: {', '.join(sorted(ports)) or 'none'})"])
    return ports[transport].load()(cfg.drive, base_dir, cfg.bench.timing)


def _reference(cfg: Any, port: Any, load: Any) -> tuple[Callable[[], float | None], str]:
    from drivers.contract import objects as o
    from drivers.contract.signals import SIGNAL_INDEX

    if load is not None and cfg.reference_source == "load":
        return (lambda: load.feedback().speed_mech_rad_s), "the load machine's encoder (Modbus)"
    if cfg.reference_source in (None, "drive") and getattr(port.profile, "extension", False):
        index = o.EXT_SIGNAL_BASE + SIGNAL_INDEX["speed_true_mech_rad_s"]
        return (lambda: struct.unpack("<f", port.read_bytes(index))[0]), \
            f"the rig encoder reported by the drive (0x{index:04X}, drivebench extension)"
    return (lambda: port.from_drive_velocity(port.read(o.VELOCITY_ACTUAL, 0, signed=True))), \
        "NONE: the drive's own velocity actual value (0x606C); stop times are the drive's word"


def run_conformance(bench_path: str, out_root: Path, only: tuple[str, ...] = (),
                    progress: Callable[[Any], None] | None = None) -> tuple[dict, Path]:
    from bench.inputs.benchconfig import load_bench_config
    from bench.outputs.conformance_report import document, keep
    from bench.outputs.provenance import software_identity
    from bench.run.links import make_links, started_services
    from drivers.conformance.motion import Context, Settings
    from drivers.conformance.suite import run_suite

    cfg = load_bench_config(bench_path)
    base = find_repo_root(bench_path)
    with started_services(cfg, 0) as live:
        port = _port(live, base)
        load = None
        if live.load:
            _, load = make_links(live, base)
        try:
            if load is not None:
                load.open()
                load.zero_and_disable()
            opened = port.open()
            reference, reference_name = _reference(live, port, load)
            drive = live.drive
            settings = Settings(consumer_time_ms=int(drive.get("consumer_time_ms") or 500),
                                abort_option=int(drive.get("abort_option") or 3),
                                standstill_mech_rad_s=float(drive.get("standstill_mech_rad_s") or 0.5),
                                stop_timeout_s=float(drive.get("stop_timeout_s") or 5.0),
                                fault_reset=live.bench.fault_reset)
            ctx = Context(port, reference, reference_name, settings, boot=opened["boot"], identity=opened)
            run = run_suite(ctx, only, progress)
        finally:
            port.close()
            load_end = "no load machine on this rig"
            if load is not None:
                try:
                    load.zero_and_disable()
                    load_end = "zero torque, disabled"
                except Exception as exc:        # said in the report, never masking the suite's own error
                    load_end = f"could not confirm zero torque: {exc}"
                finally:
                    load.close()
    doc = document(run, cfg.bench.name, settings.__dict__, reference_name, software_identity())
    doc["load_end"] = load_end
    doc["bench_config"] = str(Path(bench_path).resolve())
    return doc, keep(doc, out_root)


@click.command()
@click.option("--bench", "bench_path", type=click.Path(), required=True, help="The rig's bench config.")
@click.option("--json", "as_json", is_flag=True, help="Print the report as one JSON document.")
@click.option("--junit", "junit_path", type=click.Path(dir_okay=False), help="Also write JUnit XML here.")
@click.option("--out", "out_root", type=click.Path(file_okay=False), default="conformance", show_default=True,
              help="Reports are kept here, one folder per drive identity.")
@click.option("--compare", "compare_path", type=click.Path(dir_okay=False),
              help="An earlier report (JSON) of another drive or firmware: test by test against this one.")
@click.option("--only", multiple=True, help="Run only these tests (repeatable).")
def conformance(bench_path, as_json, junit_path, out_root, compare_path, only) -> None:
    """CiA 402 conformance-and-robustness suite on the drive of a bench (shaft free or on a dynamometer): every test
    with its CiA reference, the drive's answer and the measured times; the drive left disabled, its parameters and
    mapping restored. Exit 1 when a test finds a deviation."""
    from bench.outputs.conformance_report import compare, junit
    from drivers.conformance.suite import NAMES

    def body() -> int:
        unknown = [n for n in only if n not in NAMES]
        if unknown:
            raise InputError([f"--only: unknown test {n!r} (tests: {', '.join(NAMES)})" for n in unknown])
        other = None
        if compare_path:
            try:
                other = json.loads(Path(compare_path).read_text())
                other["tests"]
            except (OSError, ValueError, KeyError, TypeError) as exc:
                raise InputError([f"{compare_path}: not a conformance report: {exc}"]) from None

        def progress(r: Any) -> None:
            if not as_json:
                click.echo(f"{r.outcome:8} {r.name:26} {r.duration_s:6.2f} s  " + (r.findings[0] if r.findings else
                                                                                   r.detail), err=False)
        doc, kept = run_conformance(bench_path, Path(out_root), tuple(only), progress)
        if junit_path:
            Path(junit_path).write_text(junit(doc))
        if other is not None:
            doc["comparison"] = compare(other, doc)
        if as_json:
            click.echo(json.dumps(doc, default=str))
        else:
            c = doc["counts"]
            for line in doc["not_restored"]:
                click.echo(f"NOT RESTORED: {line}")
            click.echo(f"{doc['verdict'].upper()}: {c['pass']} pass, {c['note']} note, {c['fail']} fail, "
                       f"{c['not_run']} not run in {doc['duration_s']} s; drive: {doc['safe_end']}; report: "
                       f"{kept.with_suffix('.md')}")
            for row in (doc.get("comparison") or {}).get("tests", []):
                if not row["same"]:
                    click.echo(f"differs: {row['test']}: {row['a']} (other) -> {row['b']} (this)")
        return EXIT_FAIL if doc["verdict"] == "fail" else EXIT_PASS

    sys.exit(guarded(body))

"""Imported last by the service's fork server (bench.service.worker.preload_modules), once, before it forks any run:
it pays what every forked run would otherwise pay again, then freezes what is alive out of the garbage collector.

- each rig's bench config read, its drive's object dictionary parsed (drivers.contract.eds.load_od keeps it);
- each rig's run service warmed through the warm-up registered beside its starter (entry-point group
  drivebench.warm_ups: the simulator builds and steps the rig's drive model, loading its compiled kernels); a
  warm-up opens no endpoint and moves no motor, so a real rig's config is read but never driven;
- one summary figure drawn (matplotlib's fonts and text layout);
- gc.collect() and gc.freeze(): a run's full collections (after its plot) then walk only what the run made, not the
  fork server's modules (0.19 s a run, measured), and the pages they live on stay shared with the server.

The runner names the bench configs in DRIVEBENCH_WARM_BENCHES (a JSON list of paths) before it starts the fork
server. A warm-up that fails is reported on stderr and skipped: that run pays it itself, as a cold one would.
"""

from __future__ import annotations

import gc
import json
import os
import sys
import tempfile
from pathlib import Path

from bench.service.worker import WARM_BENCHES_ENV as ENV


def warm_bench(path: str) -> None:
    from bench.inputs.benchconfig import load_bench_config
    from bench.inputs.rig_services import warm_up_for
    from bench.run.links import import_object
    from drivers.contract.eds import load_od

    cfg = load_bench_config(path)
    if cfg.drive.get("transport") == "canopen" and cfg.drive.get("eds"):
        load_od(cfg.drive["eds"], int(cfg.drive.get("node_id") or 1))
    target = warm_up_for(cfg.services_start) if cfg.services_start else None
    if target:
        import_object(target, f"{path}: services.start")(cfg.as_dict())


def draw_one_figure() -> None:
    import numpy as np

    from bench.outputs.summary_plot import write_summary_png

    t = np.linspace(0.0, 1.0, 3001)
    row = {"name": "warm", "signal": "speed_est_mech_rad_s", "window_s": [0.2, 0.8], "passed": True, "value": 0.1,
           "limit": 1.0, "unit": "rad/s", "kind": "peak_abs"}
    with tempfile.TemporaryDirectory() as folder:
        write_summary_png(Path(folder) / "warm.png", t, {"speed_ref_mech_rad_s": t, "speed_est_mech_rad_s": t},
                          title="warm-up", criteria=[row], events=[{"t_s": 0.5, "kind": "trip", "label": "x"}])


def warm(benches: list[str]) -> None:
    for path in benches:
        try:
            warm_bench(path)
        except BaseException as exc:        # a SystemExit from a bad config included: the server must stay up
            print(f"drivebench serve: fork server: warm-up of {path}: {type(exc).__name__}: {exc}", file=sys.stderr)
    try:
        draw_one_figure()
    except Exception as exc:
        print(f"drivebench serve: fork server: warm-up figure: {type(exc).__name__}: {exc}", file=sys.stderr)
    gc.collect()
    gc.freeze()


def benches_from_env() -> list[str]:
    try:
        value = json.loads(os.environ.get(ENV) or "[]")
    except ValueError:
        return []
    return [str(p) for p in value] if isinstance(value, list) else []


if ENV in os.environ:           # the fork server's environment; an import anywhere else (a test, a tool) does nothing
    warm(benches_from_env())

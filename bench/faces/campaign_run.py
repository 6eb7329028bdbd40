"""Running a campaign: points on a local process pool (workers reused: imports and the numba cache paid once per
worker), or on a Ray cluster when installed; results appended as each point ends (a killed campaign resumes without
redoing them), then results.parquet, report.md and pass_rates.png."""

from __future__ import annotations

import json
import os
import socket
import time
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from bench.faces.campaign import Acceptance, Campaign, Point, points, runs_needed, wilson_interval

RESULTS_JSONL = "results.jsonl"
RESULTS_PARQUET = "results.parquet"


def run_point(point: dict[str, Any], out_root: str) -> dict[str, Any]:
    """One point through the bench path of `drivebench run` (in a worker process). A row for results.parquet."""
    from drivers.contract.errors import InputError
    from bench.run.orchestrator import run_scenario
    from drivers.contract.errors import LinkError

    started = time.perf_counter()
    row: dict[str, Any] = {"point_id": point["point_id"], "scenario": point["source"], "seed": point["seed"],
                           "axes": json.dumps(point["axes"]), "rig": point.get("rig"), "worker_pid": os.getpid(),
                           "host": socket.gethostname(), "node": _node_id(), "started_unix": time.time()}
    try:
        result = run_scenario(point["prepared"], out_root=out_root, rerun_mode="off")
    except (InputError, LinkError) as exc:
        return {**row, "verdict": "error", "error": str(exc), "wall_s": time.perf_counter() - started,
                "ended_unix": time.time(), "run_dir": None, "criteria": []}
    record = result.record
    return {**row, "verdict": result.verdict, "error": record.get("abort_reason"),
            "wall_s": time.perf_counter() - started, "ended_unix": time.time(), "run_dir": str(result.run_dir),
            "criteria": [{"name": c["name"], "value": c["value"], "limit": c["limit"],
                          "status": c.get("status") or ("pass" if c["passed"] else "fail"),
                          "known_gap": c.get("known_gap")} for c in record["criteria"]]}


def _node_id() -> str:
    """The Ray node a point ran on, else this host."""
    try:
        import ray
        if ray.is_initialized():
            return ray.get_runtime_context().get_node_id()
    except ImportError:
        pass
    return socket.gethostname()


def _worker_init() -> None:
    os.environ.setdefault("RUST_LOG", "off")       # no Rerun logs from workers (rerun is off anyway)


def done_ids(out_dir: Path) -> dict[str, dict]:
    path = out_dir / RESULTS_JSONL
    rows: dict[str, dict] = {}
    if path.exists():
        for line in path.read_text().splitlines():
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                continue                                # a line cut by a kill: that point runs again
            rows[row["point_id"]] = row
    return rows


def run_campaign(campaign: Campaign, out_dir: Path, workers: int = 2, engine: str = "local",
                 address: str | None = None, progress: Callable[[int, int, int, int], None] | None = None
                 ) -> list[dict]:
    """Every point not yet in out_dir/results.jsonl; all rows (old and new) in point order."""
    out_dir.mkdir(parents=True, exist_ok=True)
    todo_all = points(campaign, out_dir)
    finished = done_ids(out_dir)
    todo = [p for p in todo_all if p.point_id not in finished]
    runs_dir = str(out_dir / "runs")
    counts = {"pass": sum(r["verdict"] == "pass" for r in finished.values()), "other": 0}
    counts["other"] = len(finished) - counts["pass"]

    def record(row: dict) -> None:
        with open(out_dir / RESULTS_JSONL, "a") as f:
            f.write(json.dumps(row, default=str) + "\n")
        finished[row["point_id"]] = row
        counts["pass" if row["verdict"] == "pass" else "other"] += 1
        if progress is not None:
            progress(len(finished), len(todo_all), counts["pass"], counts["other"])

    if progress is not None:
        progress(len(finished), len(todo_all), counts["pass"], counts["other"])
    if engine == "ray":
        _run_ray(todo, runs_dir, address, record)
    else:
        _run_local(todo, runs_dir, workers, record)
    return [finished[p.point_id] for p in todo_all if p.point_id in finished]


def _as_dict(point: Point) -> dict[str, Any]:
    return {"point_id": point.point_id, "scenario": str(point.scenario), "source": str(point.source),
            "seed": point.seed, "axes": [list(a) for a in point.axes], "rig": point.rig, "prepared": point.prepared}


def _run_local(todo: list[Point], runs_dir: str, workers: int, record: Callable[[dict], None]) -> None:
    """A process pool; a worker that dies takes its points with it: they are retried once, then reported."""
    import multiprocessing

    attempts: dict[str, int] = {}
    queue = list(todo)
    while queue:
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=max(1, workers), mp_context=ctx, initializer=_worker_init) as pool:
            running: dict[Future, Point] = {}
            broken = False
            while (queue or running) and not broken:
                busy = {p.rig for p in running.values() if p.rig is not None}
                while len(running) < 2 * max(1, workers):
                    point = next((p for p in queue if p.rig is None or p.rig not in busy), None)
                    if point is None:                  # every queued point waits for its rig
                        break
                    queue.remove(point)
                    busy.add(point.rig)
                    attempts[point.point_id] = attempts.get(point.point_id, 0) + 1
                    running[pool.submit(run_point, _as_dict(point), runs_dir)] = point
                done, _ = wait(running, return_when=FIRST_COMPLETED)
                for future in done:
                    point = running.pop(future)
                    try:
                        record(future.result())
                    except BrokenProcessPool:
                        broken = True
                        _retry_or_report(point, attempts, queue, record, "its worker process died")
                    except Exception as exc:       # a bug in the bench: the point is an error, the campaign goes on
                        record(_error_row(point, f"{type(exc).__name__}: {exc}"))
            for future, point in running.items():      # a broken pool: what was in flight
                _retry_or_report(point, attempts, queue, record, "its worker process died")


def _retry_or_report(point: Point, attempts: dict[str, int], queue: list[Point], record, why: str) -> None:
    if attempts.get(point.point_id, 0) < 2:
        queue.append(point)
    else:
        record(_error_row(point, f"{why} twice"))


def _error_row(point: Point, error: str) -> dict[str, Any]:
    """A point that produced no run: it counts as an error in the results."""
    return {"point_id": point.point_id, "scenario": str(point.source), "seed": point.seed,
            "axes": json.dumps([list(a) for a in point.axes]), "rig": point.rig, "verdict": "error", "error": error,
            "wall_s": None, "run_dir": None, "criteria": [], "worker_pid": None, "host": None, "node": None}


RAY_CONNECT_TIMEOUT_S = 5.0


def _check_ray_address(address: str) -> None:
    """ray.init() waits minutes for a cluster that is not there: a dead or wrong --address is one line at once."""
    import socket

    from drivers.contract.errors import InputError

    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise InputError([f"--address: {address!r}: expected HOST:PORT (or ray://HOST:PORT, auto)"])
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=RAY_CONNECT_TIMEOUT_S).close()
    except OSError as exc:
        raise InputError([f"--address: {address}: no Ray cluster answers there ({exc.strerror or exc})"]) from None


def _run_ray(todo: list[Point], runs_dir: str, address: str | None, record: Callable[[dict], None]) -> None:
    try:
        import ray
    except ImportError:
        from drivers.contract.errors import InputError
        raise InputError(["--engine ray: ray is not installed (pip install -e \".[ray]\")"]) from None
    if address not in (None, "auto", "local"):
        _check_ray_address(address)
    ray.init(address=address, ignore_reinit_error=True, log_to_driver=False)
    remote = ray.remote(num_cpus=1, max_retries=1)(run_point)     # a node or worker lost: the point runs once more
    pending = {}
    for p in todo:
        # a real rig is a custom resource of the node its host runs (`ray start --resources '{"rig:NAME": 1}'`):
        # one task holds it at a time, and only that node can run the point
        options = {"resources": {f"rig:{p.rig}": 1}} if p.rig else {"scheduling_strategy": "SPREAD"}
        pending[remote.options(**options).remote(_as_dict(p), runs_dir)] = p
    while pending:
        done, _ = ray.wait(list(pending), num_returns=1)
        for ref in done:
            point = pending.pop(ref)
            try:
                record(ray.get(ref))
            except ray.exceptions.RayTaskError as exc:         # a bug in the bench: an error, the campaign goes on
                record(_error_row(point, f"{type(exc.cause).__name__}: {exc.cause}"))
            except ray.exceptions.RayError as exc:             # its worker or node died, and again on the retry
                record(_error_row(point, f"its worker process died twice ({type(exc).__name__})"))


def summarize(campaign: Campaign, rows: list[dict]) -> list[dict]:
    """Per scenario and criterion: runs judged, passes, the Wilson interval, accepted or not."""
    acc = campaign.acceptance
    table: dict[tuple[str, str], dict] = {}
    for row in rows:
        for c in row.get("criteria") or []:
            entry = table.setdefault((row["scenario"], c["name"]), {"scenario": row["scenario"], "criterion": c["name"],
                                                                    "runs": 0, "passes": 0, "not_judged": 0,
                                                                    "known_gap": c.get("known_gap")})
            if c["status"] == "not_judged":
                entry["not_judged"] += 1
                continue
            entry["runs"] += 1
            entry["passes"] += c["status"] == "pass"
    out = []
    for entry in table.values():
        low, high = wilson_interval(entry["passes"], entry["runs"], acc.confidence)
        if acc.rule == "every_run":
            accepted = entry["runs"] > 0 and entry["passes"] == entry["runs"] and not entry["not_judged"]
        else:
            accepted = entry["runs"] > 0 and low >= acc.min_pass_rate and not entry["not_judged"]
        out.append({**entry, "pass_rate": entry["passes"] / entry["runs"] if entry["runs"] else float("nan"),
                    "wilson_low": low, "wilson_high": high, "accepted": accepted})
    return out


def write_results(campaign: Campaign, out_dir: Path, rows: list[dict]) -> dict[str, Any]:
    """results.parquet (a row per run, a column per criterion value and status), report.md, pass_rates.png."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    out_dir.mkdir(parents=True, exist_ok=True)
    names = sorted({c["name"] for r in rows for c in r.get("criteria") or []})
    flat = []
    for r in rows:
        crit = {c["name"]: c for c in r.get("criteria") or []}
        base = {k: r.get(k) for k in ("point_id", "scenario", "seed", "axes", "rig", "verdict", "error", "wall_s",
                                      "started_unix", "ended_unix", "run_dir", "worker_pid", "host", "node")}
        for n in names:
            base[f"value:{n}"] = crit[n]["value"] if n in crit else None
            base[f"status:{n}"] = crit[n]["status"] if n in crit else None
        flat.append(base)
    pq.write_table(pa.Table.from_pylist(flat), out_dir / RESULTS_PARQUET)
    summary = summarize(campaign, rows)
    accepted = bool(summary) and all(s["accepted"] or s["known_gap"] for s in summary) and not any(
        r["verdict"] == "error" for r in rows)
    _write_report(campaign, out_dir, rows, summary, accepted)
    return {"runs": len(rows), "accepted": accepted, "summary": summary}


def _write_report(campaign: Campaign, out_dir: Path, rows: list[dict], summary: list[dict], accepted: bool) -> None:
    acc = campaign.acceptance
    rule = ("every run passes" if acc.rule == "every_run" else
            f"Wilson {acc.confidence:.0%} lower bound of the pass rate >= {acc.min_pass_rate:.0%}")
    if acc.rule != "every_run":
        needed = runs_needed(acc.min_pass_rate, acc.confidence)
        rule += (f" (met only from {needed} judged runs of a criterion, every one passing; one failure needs more)"
                 if needed else " (no run count can meet it)")
    verdicts: dict[str, int] = {}
    for r in rows:
        verdicts[r["verdict"]] = verdicts.get(r["verdict"], 0) + 1
    lines = [f"# Campaign {campaign.name}", "",
             f"{len(rows)} runs ({', '.join(f'{v} {k}' for k, v in sorted(verdicts.items()))}); acceptance: {rule}; "
             f"**{'accepted' if accepted else 'not accepted'}**.", "",
             "| scenario | criterion | passes / judged | pass rate | interval | not judged | accepted |",
             "|---|---|---|---|---|---|---|"]
    for s in sorted(summary, key=lambda s: (s["scenario"], s["criterion"])):
        gap = " (known gap)" if s["known_gap"] else ""
        lines.append(f"| {Path(s['scenario']).stem} | {s['criterion']}{gap} | {s['passes']} / {s['runs']} | "
                     f"{s['pass_rate']:.1%} | {s['wilson_low']:.1%} - {s['wilson_high']:.1%} | {s['not_judged']} | "
                     f"{'yes' if s['accepted'] else 'no'} |")
    worst = []
    for r in rows:
        for c in r.get("criteria") or []:
            if c["value"] is not None and c["limit"]:
                worst.append((c["value"] / c["limit"], r, c))
    worst.sort(key=lambda w: -w[0])
    lines += ["", "Worst runs (value / limit):", ""]
    for ratio, r, c in worst[:10]:
        lines.append(f"- {ratio:.3g}: {Path(r['scenario']).stem} seed {r['seed']} axes {r['axes']}: {c['name']} "
                     f"({r['run_dir'] and Path(r['run_dir']).name})")
    grid = pass_rate_grid(campaign, rows)
    if grid is not None:
        _plot_heatmap(grid, out_dir / "heatmap.png")
        lines += ["", f"Where it fails: `heatmap.png`, the share of passing runs over {grid.x_name} x {grid.y_name}."]
    (out_dir / "report.md").write_text("\n".join(lines) + "\n")
    _plot(summary, out_dir / "pass_rates.png", acc)


HEATMAP_BINS = 5    # a sampled axis (low..high) is cut into this many equal bins


@dataclass(frozen=True)
class PassRateGrid:
    x_name: str
    y_name: str
    x_labels: tuple[str, ...]
    y_labels: tuple[str, ...]
    passes: np.ndarray       # [y, x] runs that passed
    runs: np.ndarray         # [y, x] runs


def pass_rate_grid(campaign: Campaign, rows: list[dict]) -> PassRateGrid | None:
    """The runs' verdicts over the campaign's first two axes (a grid axis by value, a sampled one in bins); None
    for a campaign with fewer than two axes."""
    if len(campaign.axes) < 2:
        return None
    cuts = []
    for axis in campaign.axes[:2]:
        if axis.values:
            values = sorted(set(axis.values))
            cuts.append((values, [f"{v:g}" for v in values], lambda v, values=values: values.index(v)))
        else:
            edges = np.linspace(axis.low, axis.high, HEATMAP_BINS + 1)
            labels = [f"{edges[k]:.3g}-{edges[k + 1]:.3g}" for k in range(HEATMAP_BINS)]
            cuts.append((labels, labels, lambda v, edges=edges: int(np.clip(np.searchsorted(edges, v, "right") - 1,
                                                                             0, HEATMAP_BINS - 1))))
    (xs, x_labels, x_of), (ys, y_labels, y_of) = cuts
    passes = np.zeros((len(ys), len(xs)), dtype=int)
    runs = np.zeros((len(ys), len(xs)), dtype=int)
    x_name, y_name = campaign.axes[0].parameter, campaign.axes[1].parameter
    for row in rows:
        axes = dict(json.loads(row["axes"]) if isinstance(row["axes"], str) else row["axes"])
        if x_name not in axes or y_name not in axes:
            continue
        i, j = y_of(axes[y_name]), x_of(axes[x_name])
        runs[i, j] += 1
        passes[i, j] += row["verdict"] == "pass"
    return PassRateGrid(x_name, y_name, tuple(x_labels), tuple(y_labels), passes, runs)


def _plot_heatmap(grid: PassRateGrid, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    with np.errstate(invalid="ignore", divide="ignore"):
        rate = np.where(grid.runs > 0, grid.passes / grid.runs, np.nan)
    fig = Figure(figsize=(1.2 * len(grid.x_labels) + 3, 0.8 * len(grid.y_labels) + 2))
    ax = fig.subplots()
    image = ax.imshow(rate, origin="lower", cmap="RdYlGn", vmin=0.0, vmax=1.0, aspect="auto")
    for i in range(rate.shape[0]):
        for j in range(rate.shape[1]):
            if grid.runs[i, j]:
                ax.text(j, i, f"{grid.passes[i, j]}/{grid.runs[i, j]}", ha="center", va="center", fontsize=8)
    ax.set_xticks(range(len(grid.x_labels)), grid.x_labels, fontsize=7)
    ax.set_yticks(range(len(grid.y_labels)), grid.y_labels, fontsize=7)
    ax.set_xlabel(grid.x_name)
    ax.set_ylabel(grid.y_name)
    fig.colorbar(image, ax=ax, label="share of runs that pass")
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def _plot(summary: list[dict], path: Path, acc: Acceptance) -> None:
    """Pass rate and interval per criterion, green when accepted, grey a known gap, red not; the acceptance bound as
    a dashed line; labels whole (wrapped, never clipped: the figure grows to hold them)."""
    import textwrap

    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    items = sorted((s for s in summary if s["runs"]), key=lambda s: (s["scenario"], s["criterion"]), reverse=True)
    if not items:
        return
    labels = ["\n".join(textwrap.wrap(f"{Path(s['scenario']).stem}: {s['criterion']}", 60)) for s in items]
    height = sum(0.16 * (label.count("\n") + 1) + 0.1 for label in labels) + 1.2
    fig = Figure(figsize=(11, max(2.5, height)), layout="constrained")
    ax = fig.subplots()
    for i, s in enumerate(items):
        colour = "tab:gray" if s["known_gap"] else ("tab:green" if s["accepted"] else "tab:red")
        err = [[max(0.0, s["pass_rate"] - s["wilson_low"])], [max(0.0, s["wilson_high"] - s["pass_rate"])]]
        ax.errorbar([s["pass_rate"]], [i], xerr=err, fmt="o", capsize=3, color=colour)
    ax.set_yticks(range(len(items)), labels, fontsize=7)
    ax.set_ylim(-0.7, len(items) - 0.3)
    ax.set_xlim(-0.02, 1.02)
    if acc.rule == "wilson":
        ax.axvline(acc.min_pass_rate, ls="--", color="black", lw=0.8)
        ax.text(acc.min_pass_rate, len(items) - 0.3, f" accepted when the interval's\n lower end >= "
                f"{acc.min_pass_rate:.0%}", fontsize=7, va="bottom", ha="right")
        ax.set_xlabel(f"pass rate, Wilson {acc.confidence:.0%} interval (green accepted, red not, grey known gap)")
    else:
        ax.set_xlabel("pass rate (every run must pass; green accepted, red not, grey known gap)")
    ax.grid(True, axis="x", lw=0.3)
    fig.savefig(path, dpi=100)


def campaign_json(result: dict[str, Any]) -> str:
    return json.dumps(result, default=lambda o: asdict(o) if hasattr(o, "__dataclass_fields__") else str(o))

"""Campaigns: scenarios x seeds x parameter axes, every point a `drivebench run` through the same bench path, the
pass rate of each criterion judged with its confidence interval.

A campaign file (TOML):

    schema_version = 1
    name = "paper-seeds"
    scenarios = ["scenarios/pmsm/fig08-20rads-rs-step.toml"]   # from the repository root, or next to this file
    seeds = { from = 1, count = 20 }                             # or a list: seeds = [1, 2, 3]
    [[axis]]                                                     # optional: a parameter of drivers/contract/parameters.py,
    parameter = "plant_rs"                                       # injected at t = 0 s of every point
    values = [0.8, 1.0, 1.2]                                     # a grid ...
    # low = 0.8, high = 1.2                                      # ... or a range, sampled by [sampling]
    [sampling]                                                   # for ranges: Latin hypercube, scipy.stats.qmc
    points = 8
    seed = 1
    [acceptance]
    rule = "wilson"                                              # or "every_run"
    min_pass_rate = 0.95                                         # wilson: the interval's lower bound must reach it
    confidence = 0.95

A point with axes runs its scenario, prepared once, with each axis as a typed override: an injection at 0 s, checked
as the scenario's own `[[injection]]` tables are (offered parameters, plant_injections, value ranges).
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from drivers.contract.errors import InputError
from drivers.contract.checks import find_repo_root, Problems
from drivers.contract.errors import ContentError
from drivers.contract.toml_file import read_toml_file

if TYPE_CHECKING:
    from bench.inputs.prepared import PreparedRun

SCHEMA_VERSION = 1
RULES = ("wilson", "every_run")
_TOP_KEYS = {"schema_version", "name", "description", "scenarios", "seeds", "axis", "sampling", "acceptance"}
MAX_POINTS = 100_000


@dataclass(frozen=True)
class Axis:
    parameter: str
    values: tuple[float, ...] = ()
    low: float | None = None
    high: float | None = None


@dataclass(frozen=True)
class Acceptance:
    rule: str = "wilson"
    min_pass_rate: float = 0.95
    confidence: float = 0.95


@dataclass(frozen=True)
class Point:
    scenario: Path            # the scenario file a run uses (its axes are overrides in `prepared`)
    source: Path              # the campaign's scenario it comes from
    seed: int
    axes: tuple[tuple[str, float], ...]
    point_id: str
    rig: str | None = None    # a real rig's bench name (a bench without [services]): one point at a time on it
    prepared: PreparedRun | None = None   # what the point runs: the scenario prepared once, axes and seed applied


@dataclass(frozen=True)
class Campaign:
    path: Path
    name: str
    scenarios: tuple[Path, ...]
    seeds: tuple[int, ...]
    axes: tuple[Axis, ...]
    sampling_points: int | None
    sampling_seed: int
    acceptance: Acceptance
    description: str = ""
    settings: dict[str, Any] = field(default_factory=dict)


def wilson_interval(passes: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (E. B. Wilson, JASA 22(158), 1927): good at the extremes
    (0 or n passes) where the normal approximation breaks down. (0, 1) without trials. scipy's implementation."""
    if n <= 0:
        return 0.0, 1.0
    from scipy.stats import binomtest

    ci = binomtest(passes, n).proportion_ci(confidence_level=confidence, method="wilson")
    return max(0.0, float(ci.low)), min(1.0, float(ci.high))


def runs_needed(min_pass_rate: float, confidence: float = 0.95, most: int = 100_000) -> int | None:
    """The fewest judged runs, every one passing, whose Wilson lower bound reaches `min_pass_rate` (at p = 1 the
    bound is n / (n + z^2), so n >= z^2 p / (1 - p)); None when no run count up to `most` can (a rate of 100 %)."""
    if min_pass_rate <= 0:
        return 1
    from scipy.stats import norm

    z = float(norm.ppf(0.5 + confidence / 2))
    if min_pass_rate >= 1:
        return None
    n = max(1, int(z * z * min_pass_rate / (1 - min_pass_rate)) - 1)
    while n <= most and wilson_interval(n, n, confidence)[0] < min_pass_rate:
        n += 1
    return n if n <= most else None


def load_campaign(path: str | Path) -> Campaign:
    path = Path(path)
    try:
        raw, _ = read_toml_file(path)
    except ContentError as exc:
        raise InputError([f"{path}: (file): {exc}"]) from None
    p = Problems(path)
    p.unknown_keys(raw, _TOP_KEYS, "")
    version = p.integer(raw, "schema_version", "")
    if version is not None and version != SCHEMA_VERSION:
        p.add("schema_version", f"unsupported version {version} (this bench reads {SCHEMA_VERSION})")
    name = p.string(raw, "name", "", required=False, default=path.stem) or path.stem
    description = p.string(raw, "description", "", required=False, default="") or ""
    scenarios = _scenarios(p, raw, path)
    seeds = _seeds(p, raw)
    axes = _axes(p, raw)
    sampling = p.table(raw, "sampling", "", required=False) or {}
    p.unknown_keys(sampling, {"points", "seed", "method"}, "sampling")
    method = p.string(sampling, "method", "sampling", required=False, default="lhs", choices=("lhs",))
    points = p.integer(sampling, "points", "sampling", required=False, min_value=1, max_value=MAX_POINTS)
    sampling_seed = p.integer(sampling, "seed", "sampling", required=False, default=0, min_value=0) or 0
    ranged = [a for a in axes if a.low is not None]
    if ranged and points is None:
        p.add("sampling.points", f"missing: axis {ranged[0].parameter!r} is a range, say how many points to draw")
    if axes and ranged and len(ranged) != len(axes):
        p.add("axis", "give every axis as values (a grid) or every axis as low/high (sampled), not both")
    acc = p.table(raw, "acceptance", "", required=False) or {}
    p.unknown_keys(acc, {"rule", "min_pass_rate", "confidence"}, "acceptance")
    rule = p.string(acc, "rule", "acceptance", required=False, default="wilson", choices=RULES) or "wilson"
    rate = p.number(acc, "min_pass_rate", "acceptance", required=False, default=0.95)
    confidence = p.number(acc, "confidence", "acceptance", required=False, default=0.95)
    if rate is not None and not 0.0 <= rate <= 1.0:
        p.add("acceptance.min_pass_rate", f"must be within 0..1, got {rate:g}")
    if confidence is not None and not 0.5 <= confidence < 1.0:
        p.add("acceptance.confidence", f"must be within 0.5..1 (exclusive), got {confidence:g}")
    if scenarios and seeds:
        total = len(scenarios) * len(seeds) * (points or math.prod(len(a.values) for a in axes) if axes else 1)
        if total > MAX_POINTS:
            p.add("", f"{total} points: more than a campaign may have ({MAX_POINTS})")
    p.raise_if_any()
    return Campaign(path, name, tuple(scenarios), tuple(seeds), tuple(axes), points if ranged else None,
                    sampling_seed, Acceptance(rule, rate or 0.95, confidence or 0.95), description,
                    {"method": method})


def _scenarios(p: Problems, raw: dict, path: Path) -> list[Path]:
    items = raw.get("scenarios")
    if not isinstance(items, list) or not items or not all(isinstance(s, str) for s in items):
        p.add("scenarios", f"must be a non-empty list of scenario paths, got {items!r}")
        return []
    root = find_repo_root(path)
    found = []
    for i, item in enumerate(items):
        candidates = [Path(item)] if Path(item).is_absolute() else [root / item, path.parent / item]
        hit = next((c.resolve() for c in candidates if c.is_file()), None)
        if hit is None:
            p.add(f"scenarios[{i}]", f"file not found: {item!r} (relative paths: from the repository root {root})")
        else:
            found.append(hit)
    return found


def _seeds(p: Problems, raw: dict) -> list[int]:
    seeds = raw.get("seeds")
    if isinstance(seeds, dict):
        p.unknown_keys(seeds, {"from", "count"}, "seeds")
        start = p.integer(seeds, "from", "seeds", min_value=0, max_value=2**63 - 1)
        count = p.integer(seeds, "count", "seeds", min_value=1, max_value=MAX_POINTS)
        return [] if start is None or count is None else list(range(start, start + count))
    if isinstance(seeds, list) and seeds and all(isinstance(s, int) and not isinstance(s, bool) and 0 <= s < 2**63
                                                 for s in seeds):
        if len(set(seeds)) != len(seeds):
            p.add("seeds", "a seed is listed twice")
        return list(dict.fromkeys(seeds))
    p.add("seeds", f"give {{ from = N, count = M }} or a list of integers 0..2^63-1, got {seeds!r}")
    return []


def _axes(p: Problems, raw: dict) -> list[Axis]:
    from drivers.contract import parameters

    tables = raw.get("axis", [])
    if not isinstance(tables, list) or not all(isinstance(t, dict) for t in tables):
        p.add("axis", "must be an array of tables ([[axis]])")
        return []
    axes = []
    for i, table in enumerate(tables):
        where = f"axis[{i}]"
        p.unknown_keys(table, {"parameter", "values", "low", "high"}, where)
        name = p.string(table, "parameter", where)
        if name is not None and parameters.lookup(name) is None:
            p.add(f"{where}.parameter", f"unknown parameter {name!r} (drivers/contract/parameters.py lists them)")
            name = None
        values = table.get("values")
        if values is not None:
            if (not isinstance(values, list) or not values
                    or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                               for v in values)):
                p.add(f"{where}.values", f"must be a non-empty list of finite numbers, got {values!r}")
                continue
            if name is not None:
                axes.append(Axis(name, tuple(float(v) for v in values)))
            continue
        low = p.number(table, "low", where)
        high = p.number(table, "high", where)
        if low is not None and high is not None and not low < high:
            p.add(f"{where}.high", f"must be above low ({low:g}), got {high:g}")
            continue
        if name is not None and low is not None and high is not None:
            axes.append(Axis(name, (), low, high))
    names = [a.parameter for a in axes]
    if len(set(names)) != len(names):
        p.add("axis", "a parameter is given twice")
    return axes


def axis_points(campaign: Campaign) -> list[tuple[tuple[str, float], ...]]:
    """The parameter settings of the campaign: () without axes; the grid; or Latin-hypercube samples (scipy.stats.qmc,
    seeded, so a campaign draws the same points every time)."""
    if not campaign.axes:
        return [()]
    if campaign.sampling_points is None:
        grid = itertools.product(*[a.values for a in campaign.axes])
        return [tuple(zip([a.parameter for a in campaign.axes], combo)) for combo in grid]
    from scipy.stats import qmc

    unit = qmc.LatinHypercube(d=len(campaign.axes), seed=campaign.sampling_seed).random(campaign.sampling_points)
    lows = [a.low for a in campaign.axes]
    highs = [a.high for a in campaign.axes]
    scaled = qmc.scale(unit, lows, highs)
    return [tuple((a.parameter, float(v)) for a, v in zip(campaign.axes, row)) for row in scaled]


def points(campaign: Campaign, out_dir: Path | None = None) -> list[Point]:
    """Every run of the campaign, in a fixed order. Each scenario is read and checked once (prepare_run); a point is
    that prepared run with its axes as typed overrides (injections at 0 s, checked like the file's own) and its
    seed. `out_dir` is not used (points once wrote derived scenario files there); kept for callers."""
    from bench.inputs.prepared import prepare_run

    out = []
    for scenario in campaign.scenarios:
        base = prepare_run(scenario)
        text = scenario.read_text()
        for axes in axis_points(campaign):
            with_axes = base.with_injections(axes)
            for seed in campaign.seeds:
                digest = hashlib.sha256(text.encode())
                digest.update(json.dumps([list(a) for a in axes]).encode())
                digest.update(str(seed).encode())
                out.append(Point(scenario, scenario, seed, axes, digest.hexdigest()[:16], base.rig,
                                 with_axes.with_seed(seed)))
    return out

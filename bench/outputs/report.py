"""Report: `drivebench report RUN_DIR... [--out FILE] [--suites FILE]` -> a Markdown file (default report.md beside
the runs) with plots in a folder of the same name.

A table of every criterion of every run: test, the limit and the stated basis (the criterion's comments in the
scenario file), the measured value, the verdict (pass, FAIL, known gap), and a PNG per run. With a suites file the
runs of its folders are grouped per suite, their criteria read as the suite's claims, and the deviations (list items
of the firmware docs and the suite's own) follow; any other run is reported as what it is. Everything a suite says
in the report (title, headings, notes) comes from its suites file: this module knows no suite.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import sys
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from drivers.contract.errors import InputError
from bench.outputs.report_suites import OTHER, Suites, Wording, load_suites
from bench.outputs.run_files import load_run

KIND_UNITS = {
    "speed_error_max_pct": "%", "speed_error_rms_pct": "%", "flux_error_max_pct": "%",
    "flux_error_rms_pct": "%", "overshoot_pct": "%", "pos_error_max": "rad", "pos_error_rms": "rad",
    "flux_recovery_time": "s", "settling_time": "s", "reversal_time": "s",
}
SIGNAL_UNITS = (("_rad_s", "rad/s"), ("_rad", "rad"), ("_wb", "Wb"), ("_a", "A"), ("_nm", "N·m"), ("_v", "V"))



@dataclass
class Run:
    run_dir: Path
    record: dict[str, Any]
    columns: dict[str, np.ndarray]
    complete: bool
    suite: str                  # the suite key (a suite's scenario folder) or OTHER
    name: str
    scenario_path: Path | None
    basis: dict[str, str] = field(default_factory=dict)
    params: dict[str, dict] = field(default_factory=dict)      # criterion name -> its parameters (scenario file)


# -- reading -------------------------------------------------------------------------------------------------

def criteria_comments(scenario_text: str) -> dict[str, str]:
    """criterion name -> its comment lines in the scenario file (the stated basis), joined."""
    out: dict[str, str] = {}
    for block in re.split(r"^\[\[criteria\]\]\s*$", scenario_text, flags=re.M)[1:]:
        block = re.split(r"^\[", block, maxsplit=1, flags=re.M)[0]
        m = re.search(r'^name\s*=\s*"((?:[^"\\]|\\.)*)"', block, flags=re.M)
        if not m:
            continue
        comments = [line.strip().lstrip("#").strip() for line in block.splitlines() if line.strip().startswith("#")]
        out[m.group(1)] = " ".join(c for c in comments if c)
    return out


def read_run(run_dir: Path, suites: Suites = Suites()) -> Run:
    record, columns, complete = load_run(run_dir)
    scenario = record.get("scenario") or {}
    name = str(scenario.get("name") or run_dir.name)
    path = Path(scenario["path"]) if scenario.get("path") else None
    basis: dict[str, str] = {}
    params: dict[str, dict] = {}
    if path is not None and path.is_file():
        data = path.read_bytes()
        if hashlib.sha256(data).hexdigest() == scenario.get("sha256"):  # the file the run used
            basis = criteria_comments(data.decode("utf-8"))
            try:
                params = {str(c.get("name")): c for c in tomllib.loads(data.decode("utf-8")).get("criteria") or []
                          if isinstance(c, dict)}
            except (tomllib.TOMLDecodeError, UnicodeDecodeError):
                params = {}
    return Run(run_dir, record, columns, complete, suites.key_of(path), name, path, basis, params)


# -- formatting ----------------------------------------------------------------------------------------------

def unit_of(criterion: dict, params: dict | None = None) -> str:
    if criterion.get("unit"):                      # records since the unit was recorded; older ones: inferred
        return str(criterion["unit"]).replace("N*m", "N·m")
    kind = criterion.get("kind", "")
    if kind in KIND_UNITS:
        return KIND_UNITS[kind]
    if "% of" in str(criterion.get("detail", "")) and kind == "steady_state_error":
        return "%"
    signal = str(criterion.get("signal", ""))
    for suffix, unit in SIGNAL_UNITS:
        if signal.endswith(suffix):
            return unit
    return ""


def fmt_number(value: Any) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a" if value is None or (isinstance(value, float) and math.isnan(value)) else "∞"
    v = float(value)
    if v == 0.0:
        return "0"
    if abs(v) >= 1e4 or abs(v) < 1e-3:
        return f"{v:.3g}"
    return f"{v:.4g}"


SEED_DEPENDENT = "seed-dependent"


def verdict_of(criterion: dict) -> str:
    """pass, seed-dependent (passed with this run's seed, a known gap for others: never a clean pass), not judged,
    known gap, **FAIL**."""
    if criterion.get("passed"):
        return SEED_DEPENDENT if criterion.get("known_gap") else "pass"
    if criterion.get("status") == "not_judged":
        return "not judged"
    return "known gap" if criterion.get("known_gap") else "**FAIL**"


def md_cell(text: str) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def measured_text(criterion: dict) -> str:
    unit = unit_of(criterion)
    value = fmt_number(criterion.get("value"))
    detail = re.sub(r"^value \S+ > limit \S+; ", "", str(criterion.get("detail") or ""))
    return f"{value} {unit}".strip() + (f" ({detail})" if detail else "")


def claim_text(run: Run, criterion: dict) -> str:
    unit = unit_of(criterion)
    lo, hi = criterion.get("window_s") or (None, None)
    limit = f"≤ {fmt_number(criterion.get('limit'))} {unit}".strip()
    window = f", window {fmt_number(lo)}–{fmt_number(hi)} s" if lo is not None else ""
    basis = run.basis.get(criterion.get("name", ""), "")
    return f"{limit}{window}" + (f"; {basis}" if basis else "")


# -- plots ---------------------------------------------------------------------------------------------------

def write_plot(run: Run, path: Path) -> Path | None:
    """The run's verdict figure (bench.outputs.summary_plot: the same as its summary.png), criteria and markers included."""
    from bench.outputs.summary_plot import events_of, write_summary_png

    t = np.asarray(run.columns.get("t_s", np.zeros(0)), dtype=float)
    if len(t) < 2:
        return None
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_summary_png(path, t, run.columns, title=f"{run.name} - {run.record.get('verdict')}",
                             criteria=run.record.get("criteria") or [], params=run.params,
                             events=events_of(run.record))


# -- deviations ----------------------------------------------------------------------------------------------

LIST_ITEM = re.compile(r"^\s*(?:\d+\.|[-*])\s+(.*?)(?=^\s*(?:\d+\.|[-*])\s+|\Z)", re.M | re.S)


def _items(list_text: str) -> list[str]:
    return [" ".join(m.group(1).split()) for m in LIST_ITEM.finditer(list_text)]


def firmware_deviations(docs_dir: Path, glob: str = Wording.firmware_docs_glob,
                        list_intro: str = Wording.firmware_list_intro) -> list[tuple[str, list[str]]]:
    """(doc file, items) from the docs matching `glob`: every list item of a section whose heading says
    'deviation', and of a list introduced by a line matching `list_intro` (e.g. "... chosen:"), whole (with the
    reasons)."""
    intro_re = re.compile(f"^(?:{list_intro})", re.I | re.M)
    out = []
    for doc in sorted(docs_dir.glob(glob)):
        text = doc.read_text(encoding="utf-8")
        items: list[str] = []
        for section in re.split(r"^#+ ", text, flags=re.M):
            heading, _, body = section.partition("\n")
            if "deviation" in heading.lower():
                items += _items(body)
                continue
            for intro in intro_re.finditer(body):
                rest = body[intro.end():]
                block = re.split(r"\n\s*\n", rest.lstrip("\n"), maxsplit=1)[0]   # the list: up to a blank line
                items += _items(block)
        if items:
            out.append((doc.name, items))
    return out


# -- report --------------------------------------------------------------------------------------------------

def _rel(path: Path, start: Path) -> str:
    try:
        return Path(path).resolve().relative_to(start.resolve()).as_posix()
    except ValueError:
        import os
        return Path(os.path.relpath(Path(path).resolve(), start.resolve())).as_posix()


def _anchor(heading: str) -> str:
    """GitHub-style anchor of a '### heading'."""
    return re.sub(r"[^a-z0-9 _-]", "", heading.lower()).replace(" ", "-")


def _safe_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "-", name).strip("-.") or "run"


def default_out(run_dirs: Sequence[Path]) -> Path:
    """Beside the runs: report.md in the directory that holds them (their common parent)."""
    import os

    parents = [str(Path(d).resolve().parent) for d in run_dirs] or ["."]
    return Path(os.path.commonpath(parents)) / "report.md"


def write_report(run_dirs: Sequence[Path], out_md: Path | None = None, suites: Suites = Suites()) -> Path:
    """Write the report for `run_dirs` to `out_md` (default: beside the runs) and its plots beside it; returns the
    path. With `suites` (a suites file) runs of its folders are grouped under their suite.

    Raises InputError when a run directory cannot be read.
    """
    run_dirs = [Path(d) for d in run_dirs if Path(d).name != MUTANTS_DIR]   # `report DIR/*` also names the table
    out_md = Path(out_md) if out_md is not None else default_out(run_dirs)
    plot_dir = out_md.parent / out_md.stem
    all_runs = [read_run(d, suites) for d in run_dirs]
    if not all_runs:
        raise InputError(["report: no run directories given"])
    latest: dict[str, Run] = {}
    for r in sorted(all_runs, key=lambda r: str(r.record.get("started_utc"))):
        latest[r.name] = r  # one section per scenario: the latest of its runs
    runs = list(latest.values())
    superseded = [r for r in all_runs if latest[r.name] is not r]
    runs.sort(key=lambda r: (suites.keys.index(r.suite), r.name))
    out_md.parent.mkdir(parents=True, exist_ok=True)

    lines = [f"# {suites.title}", ""]
    revisions = sorted({str((r.record.get("software") or {}).get("git_revision")) for r in runs})
    dirty = any((r.record.get("software") or {}).get("git_dirty") for r in runs)
    started = sorted(str(r.record.get("started_utc")) for r in runs)
    lines += [
        f"Generated by `drivebench report` from {len(runs)} run(s), {started[0]} to {started[-1]} UTC, "
        f"software {', '.join(revisions)}{' (work tree with uncommitted changes)' if dirty else ''}.",
        "Each test is a criterion of a scenario file; its claim column gives the limit, the window and the basis "
        "written in the scenario file. A **known gap** keeps its limit and fails without failing the run.",
    ]
    lines += [suites.regenerate, ""] if suites.regenerate else [""]
    counts = {"pass": 0, SEED_DEPENDENT: 0, "known gap": 0, "**FAIL**": 0, "not judged": 0}
    for r in runs:
        for c in r.record.get("criteria") or []:
            counts[verdict_of(c)] += 1
    lines += [f"Criteria: {counts['pass']} pass, {counts[SEED_DEPENDENT]} seed-dependent "
              f"({suites.text.seed_dependent_note}), {counts['known gap']} known gap(s), "
              f"{counts['**FAIL**']} fail. "
              f"Runs: " + ", ".join(f"{r.name} {r.record.get('verdict')}" for r in runs) + ".", ""]
    if superseded:
        lines += ["Older runs of the same scenarios, not reported: "
                  + ", ".join(f"`{r.run_dir.name}` ({r.record.get('verdict')})" for r in superseded) + ".", ""]

    for key in suites.keys:
        group = [r for r in runs if r.suite == key]
        if not group:
            continue
        lines += [f"## {suites.heading(key)}", "", "| scenario | verdict | pass | known gap | fail |", "|---|---|---|---|---|"]
        for r in group:
            verdicts = [verdict_of(c) for c in r.record.get("criteria") or []]
            passed = verdicts.count("pass") + verdicts.count(SEED_DEPENDENT)
            lines.append(f"| [{r.name}](#{_anchor(r.name)}) | {r.record.get('verdict')} | {passed} "
                         f"| {verdicts.count('known gap')} | {verdicts.count('**FAIL**')} |")
        lines.append("")
        for r in group:
            lines += _run_section(r, out_md, plot_dir, suites)
        gaps = [(r, c) for r in group for c in r.record.get("criteria") or [] if c.get("known_gap")]
        if gaps:
            lines += ["### Known gaps", ""]
            for r, c in gaps:
                lines.append(f"- {r.name}: *{md_cell(c['name'])}* ({verdict_of(c)} with seed {r.record.get('seed')}) — "
                             f"measured {md_cell(measured_text(c))}, limit {fmt_number(c.get('limit'))} {unit_of(c)}. "
                             f"Why: {md_cell(c['known_gap'])}")
            lines.append("")

    lines += mutation_section(sorted({d.parent for d in run_dirs}), suites)
    if suites.folders:
        lines += _deviations(suites, out_md)
    for section in suites.sections:
        lines += section.read_text(encoding="utf-8").rstrip("\n").splitlines() + [""]
    out_md.write_text("\n".join(lines), encoding="utf-8")
    return out_md


def _deviations(suites: Suites, out_md: Path) -> list[str]:
    text = suites.text
    lines = [f"## {text.deviations_heading}", "", f"### {text.firmware_deviations_heading}", ""]
    found = (firmware_deviations(suites.firmware_docs, text.firmware_docs_glob, text.firmware_list_intro)
             if suites.firmware_docs else [])
    if not found:
        lines.append(f"- (no `{text.firmware_docs_glob}` with a deviations section found)")
    for doc, items in found:
        lines.append(f"From [{doc}]({_rel(suites.firmware_docs / doc, out_md.parent)}):")
        lines.append("")
        lines += [f"{i}. {md_cell(item)}" for i, item in enumerate(items, 1)]
        lines.append("")
    lines += [f"### {text.suite_deviations_heading}", ""]
    lines += [f"- {d}" for d in suites.deviations]
    lines.append("")
    return lines


MUTANTS_DIR = "mutants"


def mutation_section(dirs: Sequence[Path], suites: Suites = Suites()) -> list[str]:
    """The kill table tests/system/test_mutants.py leaves beside the runs (DIR/mutants/<drive>-<name>.json), if any."""
    table: dict[str, Any] = {}
    for path in sorted(p for d in dirs for p in (d / MUTANTS_DIR).glob("*.json")):
        try:
            loaded = json.loads(path.read_text(encoding="utf-8"))
            if not isinstance(loaded, dict) or not isinstance(loaded.get("killed_by"), dict) \
                    or not isinstance(loaded.get("drive"), str) or not isinstance(loaded.get("name"), str):
                raise ValueError("not a mutant with drive, name and killed_by")
        except (OSError, ValueError) as exc:
            raise InputError([f"{path}: mutants: {exc}"]) from None
        table[f"{loaded['drive']}/{loaded['name']}"] = loaded
    if not table:
        return []
    lines = ["## Mutation testing", "", suites.text.mutants_intro, "",
             "| mutant | what it does | rejected by |", "|---|---|---|"]
    order = suites.keys
    for key in sorted(table, key=lambda k: (order.index(k.split("/")[0]) if k.split("/")[0] in order
                                            else len(order), k)):
        m = table[key]
        by = "; ".join(f"**{scenario}**: " + ", ".join(md_cell(str(w)) for w in why)
                       for scenario, why in sorted(m["killed_by"].items()))
        lines.append(f"| {md_cell(key)} | {md_cell(str(m.get('what', '')))} | {by or '**survives**'} |")
    lines.append("")
    return lines


def _run_section(r: Run, out_md: Path, plot_dir: Path, suites: Suites = Suites()) -> list[str]:
    rec = r.record
    scenario_rel = rec.get("scenario", {}).get("path", "")
    lines = [f"### {r.name}", ""]
    desc = f"Scenario `{_rel(Path(scenario_rel), Path.cwd()) if scenario_rel else '?'}`, seed {rec.get('seed')}, " \
           f"run `{r.run_dir.name}`: verdict **{rec.get('verdict')}**"
    if rec.get("abort_reason"):
        desc += f" ({md_cell(rec['abort_reason'])})"
    if not r.complete:
        desc += " — record incomplete (recovered from the journal)"
    requirements = rec.get("scenario", {}).get("requirements") or []
    lines += [desc + ".", ""] + ([f"Requirements: {', '.join(md_cell(q) for q in requirements)}.", ""]
                                 if requirements else [])
    plot = None
    try:
        plot = write_plot(r, plot_dir / f"{_safe_name(r.name)}.png")
    except Exception as exc:  # a plot must not cost the table
        lines += [f"(plot failed: {type(exc).__name__}: {exc})", ""]
    claim = suites.text.claim_heading if r.suite != OTHER else "limit / basis"
    lines += [f"| test | {claim} | measured | verdict |", "|---|---|---|---|"]
    for c in rec.get("criteria") or []:
        lines.append(f"| {md_cell(c.get('name', ''))} | {md_cell(claim_text(r, c))} | {md_cell(measured_text(c))} "
                     f"| {verdict_of(c)} |")
    lines.append("")
    if plot is not None:
        lines += [f"![{r.name}]({_rel(plot, out_md.parent)})", ""]
    return lines


def main(run_dirs: Sequence[str | Path], out_md: str | Path | None = None, suites: str | Path | None = None) -> int:
    """CLI entry: 0 written, 2 bad input (one line per problem on stderr)."""
    try:
        path = write_report([Path(d) for d in run_dirs], Path(out_md) if out_md else None, load_suites(suites))
    except InputError as exc:
        for problem in exc.problems:
            print(problem, file=sys.stderr)
        return 2
    except OSError as exc:       # an unwritable --out (a file on its path, no permission): one line, as bad input
        why = ("is a file, not a directory" if isinstance(exc, (FileExistsError, NotADirectoryError))
               else f"cannot write: {exc.strerror or exc}")
        print(f"{exc.filename or out_md}: --out: {why}", file=sys.stderr)
        return 2
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

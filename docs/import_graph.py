"""The picture in docs/architecture.md, drawn from the code: which group of modules imports which.

    python docs/import_graph.py           # rewrite the diagram between the markers in docs/architecture.md
    python docs/import_graph.py --check   # exit 1 if the diagram there is not what the code gives now
    python docs/import_graph.py --explain # the module imports behind every arrow
    python docs/import_graph.py --table [ROOT]  # imports between groups counted, as a Markdown table (ROOT: a checkout)

Modules are grouped by path prefix (GROUPS below: the longest matching prefix wins), so a module that moves
into a grouped folder is placed without editing this file; a module no prefix matches is drawn in an
"ungrouped" node of its package, where a reader sees it. An arrow A --> B: some module of A imports one of B
at run time (function-level imports included); A -.-> B: only inside `if TYPE_CHECKING:` blocks.
Standard library only.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "architecture.md"
PACKAGES = ("drivers", "bench", "sim_backend")
BEGIN = "<!-- import-graph:begin (python docs/import_graph.py) -->"
END = "<!-- import-graph:end -->"

# node, label, package (the subgraph it is drawn in), path prefixes relative to the repository root
GROUPS: tuple[tuple[str, str, str, tuple[str, ...]], ...] = (
    ("contract", "contract: CiA 402, objects, EDS, parameters, signals, units, formats, errors, config checks", "drivers",
     ("drivers/contract/",)),
    ("clients", "clients: CANopen, serial, Modbus links, reference sensor, config sections", "drivers", ("drivers/",)),
    ("inputs", "inputs: scenario, criteria, bench config, rig starters, prepared run", "bench", ("bench/inputs/",)),
    ("machinery", "run machinery: orchestrator, links, drill, step loop, supervisor, verdict", "bench",
     ("bench/run/",)),
    ("outputs", "outputs: recorder, record files, JUnit, Rerun, plot, report, export, compare", "bench",
     ("bench/outputs/",)),
    ("cli", "face: CLI (drivebench, probe checklist)", "bench",
     ("bench/__init__.py", "bench/__main__.py", "bench/faces/__init__.py", "bench/faces/cli.py",
      "bench/faces/checklist.py", "bench/faces/conformance_cli.py")),
    ("service", "face: HTTP service (queue, DB, runner)", "bench", ("bench/service/",)),
    ("campaigns", "face: campaigns, drawn signatures", "bench", ("bench/faces/campaign", "bench/signatures/")),
    ("pytest", "face: pytest plugin", "bench", ("bench/faces/pytest_plugin.py",)),
    ("sim_drives", "simulated drives: plant, inverter, firmware, instruments", "sim_backend",
     ("sim_backend/pmsm/", "sim_backend/spim/", "sim_backend/drive.py", "sim_backend/drive_model.py",
      "sim_backend/toy.py", "sim_backend/mechanics.py", "sim_backend/three_phase_inverter.py",
      "sim_backend/numerics.py", "sim_backend/instruments.py", "sim_backend/terminals.py",
      "sim_backend/analyser_sim.py", "sim_backend/scope_sim.py")),
    ("sim_front", "device and protocol servers: CANopen node, EtherCAT slave, serial, Modbus, socketcand, rig builder", "sim_backend",
     ("sim_backend/__init__.py", "sim_backend/canopen/", "sim_backend/ethercat/", "sim_backend/device.py", "sim_backend/cia402_device.py",
      "sim_backend/faults.py",
      "sim_backend/comm_watchdog.py", "sim_backend/trace.py", "sim_backend/serial_server.py", "sim_backend/serial_protocol.py",
      "sim_backend/modbus_server.py", "sim_backend/socketcand_server.py", "sim_backend/wire_faults.py",
      "sim_backend/sessions.py", "sim_backend/rig.py", "sim_backend/serve.py", "sim_backend/od_gen.py",
      "sim_backend/scpi_server.py", "sim_backend/lab_rig.py")),
    ("sim_tools", "simulator tools: sim CLI, twin, design check", "sim_backend",
     ("sim_backend/cli.py", "sim_backend/twin", "sim_backend/design_check.py")),
)


def module_files(root: Path = REPO) -> dict[str, str]:
    """{dotted module name: path relative to root (posix)} for every module of PACKAGES."""
    out = {}
    for package in PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            rel = path.relative_to(root)
            parts = rel.with_suffix("").parts
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = rel.as_posix()
    return out


def group_of(rel_path: str, groups=GROUPS) -> str:
    """The node of the group whose longest prefix matches, else '<package>_ungrouped'."""
    best, best_len = None, -1
    for node, _, _, prefixes in groups:
        for prefix in prefixes:
            if rel_path.startswith(prefix) and len(prefix) > best_len:
                best, best_len = node, len(prefix)
    return best or f"{rel_path.split('/')[0]}_ungrouped"


def _type_only(tree: ast.AST) -> set[int]:
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skip.update(id(n) for child in node.body for n in ast.walk(child))
    return skip


def _resolve(name: str, modules: dict[str, str]) -> str | None:
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def imports(module: str, modules: dict[str, str], root: Path = REPO) -> dict[str, bool]:
    """{imported project module: True if any import of it runs, False if all are type-only}."""
    rel = modules[module]
    tree = ast.parse((root / rel).read_text(encoding="utf-8"))
    type_only = _type_only(tree)
    found: dict[str, bool] = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [_resolve(a.name, modules) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                here = module.split(".")
                keep = len(here) - node.level + rel.endswith("__init__.py")
                base = ".".join(here[:keep] + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else _resolve(base, modules)
                       for a in node.names]
        else:
            continue
        runs = id(node) not in type_only
        for target in targets:
            if target and target != module:
                found[target] = found.get(target, False) or runs
    return found


def group_graph(root: Path = REPO, groups=GROUPS) -> tuple[list[str], dict[tuple[str, str], bool]]:
    """(nodes in use, {(from, to): runs}) over groups; edges inside a group are left out."""
    modules = module_files(root)
    node_of = {m: group_of(rel, groups) for m, rel in modules.items()}
    edges: dict[tuple[str, str], bool] = {}
    for module in modules:
        for target, runs in imports(module, modules, root).items():
            a, b = node_of[module], node_of[target]
            if a != b:
                edges[(a, b)] = edges.get((a, b), False) or runs
    return sorted(set(node_of.values())), edges


def mermaid(root: Path = REPO, groups=GROUPS) -> str:
    nodes, edges = group_graph(root, groups)
    info = {node: (label, package) for node, label, package, _ in groups}
    for node in nodes:
        if node not in info:
            package = node.rsplit("_ungrouped", 1)[0]
            info[node] = (f"{package}: ungrouped (add to docs/import_graph.py GROUPS)", package)
    lines = ["```mermaid", "flowchart TB"]
    for package in PACKAGES:
        members = [n for n, _, p, _ in groups if p == package and n in nodes]
        members += [n for n in nodes if n not in members and info[n][1] == package]
        if not members:
            continue
        lines.append(f'  subgraph {package}_pkg["{package}/"]')
        lines += [f'    {n}["{info[n][0]}"]' for n in members]
        lines.append("  end")
    order = {n: i for i, n in enumerate(n for n, *_ in groups)}
    for (a, b), runs in sorted(edges.items(), key=lambda e: (order.get(e[0][0], 99), order.get(e[0][1], 99), e[0])):
        lines.append(f"  {a} {'-->' if runs else '-.->'} {b}")
    lines.append("```")
    return "\n".join(lines)


def embedded(doc_text: str) -> str:
    """The diagram between the markers of doc_text."""
    if BEGIN not in doc_text or END not in doc_text:
        raise ValueError(f"{DOC.name}: the import-graph markers are missing")
    return doc_text.split(BEGIN, 1)[1].split(END, 1)[0].strip("\n")


def explain(root: Path = REPO, groups=GROUPS) -> list[str]:
    """One line per module import that crosses groups: 'from -> to: module -> module'."""
    modules = module_files(root)
    out = []
    for module, rel in modules.items():
        for target, runs in sorted(imports(module, modules, root).items()):
            a, b = group_of(rel, groups), group_of(modules[target], groups)
            if a != b:
                out.append(f"{a} -> {b}: {module} -> {target}{'' if runs else ' (type only)'}")
    return sorted(out)


def count_table(root: Path = REPO, groups=GROUPS) -> str:
    """Markdown: module imports (importer, imported pairs; type-only included) from each group (rows) to each group
    (columns)."""
    modules = module_files(root)
    counts: dict[tuple[str, str], int] = {}
    for module, rel in modules.items():
        for target in imports(module, modules, root):
            key = (group_of(rel, groups), group_of(modules[target], groups))
            counts[key] = counts.get(key, 0) + 1
    order = [n for n, *_ in groups]
    nodes = order + sorted({n for pair in counts for n in pair} - set(order))
    nodes = [n for n in nodes if any(n in pair for pair in counts)]
    lines = ["| from \\ to | " + " | ".join(nodes) + " |", "|---" * (len(nodes) + 1) + "|"]
    lines += [f"| {a} | " + " | ".join(str(counts.get((a, b), "")) for b in nodes) + " |" for a in nodes]
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    if "--table" in argv:
        rest = [a for a in argv if not a.startswith("--")]
        print(count_table(Path(rest[0]).resolve() if rest else REPO))
        return 0
    if "--explain" in argv:
        print("\n".join(explain()))
        return 0
    text = DOC.read_text(encoding="utf-8")
    diagram = mermaid()
    if "--check" in argv:
        if embedded(text) != diagram:
            print(f"{DOC.relative_to(REPO)}: the import graph differs from the code: run python docs/import_graph.py",
                  file=sys.stderr)
            return 1
        return 0
    head, rest = text.split(BEGIN, 1)
    DOC.write_text(f"{head}{BEGIN}\n{diagram}\n{END}{rest.split(END, 1)[1]}", encoding="utf-8")
    print(f"wrote {DOC.relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

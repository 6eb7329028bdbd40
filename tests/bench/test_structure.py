"""The structure the layout promises: bench/ never imports the simulator, firmware never imports a plant model, no
import cycle in any package, and a bench config without [services] (a real rig) reaches its links with its own
[bench] settings."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
PACKAGES = ("bench", "drivers", "sim_backend")


def _module_name(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for pkg in PACKAGES for p in (REPO / pkg).rglob("*.py")}


def _type_checking_nodes(tree: ast.AST) -> set[int]:
    """ids of import nodes inside `if TYPE_CHECKING:` blocks (annotations only, never executed)."""
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skip.update(id(n) for child in node.body for n in ast.walk(child))
    return skip


def imports_of(module: str, type_only: bool = False) -> set[str]:
    """Project modules `module` imports anywhere in its body (functions included); TYPE_CHECKING blocks excluded
    unless `type_only` (a circle through annotations is still a circle in the design)."""
    path = MODULES[module]
    tree = ast.parse(path.read_text())
    skip = set() if type_only else _type_checking_nodes(tree)
    found: set[str] = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                package = module.split(".")[:len(module.split(".")) - node.level + (path.name == "__init__.py")]
                base = ".".join(package + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            names = [base] + [f"{base}.{a.name}" for a in node.names]
        else:
            continue
        for name in names:
            while name and name not in MODULES:
                name = name.rpartition(".")[0]
            if name and name != module:
                found.add(name)
    return found


GRAPH = {m: imports_of(m) for m in MODULES}
GRAPH_WITH_TYPES = {m: imports_of(m, type_only=True) for m in MODULES}
CONTRACT = "drivers.contract"


def _in_contract(module: str) -> bool:
    return module == CONTRACT or module.startswith(CONTRACT + ".")


def test_the_graph_sees_imports():
    assert "drivers.contract.cia402" in GRAPH["drivers.canopen.link"]
    assert "sim_backend.device" in GRAPH["sim_backend.rig"]         # a function-level import counts too


def test_bench_never_imports_the_simulator():
    offending = {m: sorted(d for d in deps if d.split(".")[0] == "sim_backend")
                 for m, deps in GRAPH.items() if m.split(".")[0] == "bench"}
    assert {m: d for m, d in offending.items() if d} == {}


def test_drivers_import_neither_bench_nor_the_simulator():
    offending = {m: sorted(d for d in deps if d.split(".")[0] in ("bench", "sim_backend"))
                 for m, deps in GRAPH.items() if m.split(".")[0] == "drivers"}
    assert {m: d for m, d in offending.items() if d} == {}


PLANT_SIDE = ("plant", "mechanics", "inverter", "three_phase_inverter", "kernel", "model", "drive_model", "device",
              "drive")


def test_firmware_never_imports_a_plant_module():
    firmware = [m for m in MODULES if m.endswith(".firmware")]
    assert len(firmware) == 2
    for module in firmware:
        plant = [d for d in GRAPH[module] if d.startswith("sim_backend") and d.rpartition(".")[2] in PLANT_SIDE]
        assert plant == [], f"{module} imports {plant}"


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    return out


def test_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_cycle_in_any_package():
    assert _cycles(GRAPH) == []


def test_the_type_only_graph_sees_type_checking_imports():
    with_types = {m for m, deps in GRAPH_WITH_TYPES.items() if deps - GRAPH[m]}
    assert with_types, "no module has a TYPE_CHECKING import: the variant would test nothing"


def test_no_import_cycle_even_through_type_only_imports():
    assert _cycles(GRAPH_WITH_TYPES) == []


def test_the_contract_imports_nothing_outside_itself():
    contract = [m for m in MODULES if _in_contract(m)]
    assert len(contract) >= 10
    offending = {m: sorted(d for d in GRAPH_WITH_TYPES[m] if not _in_contract(d)) for m in contract}
    assert {m: d for m, d in offending.items() if d} == {}


def test_the_simulator_imports_no_bench_module_and_of_drivers_only_the_contract():
    offending = {m: sorted(d for d in deps if d.split(".")[0] == "bench" or
                           (d.split(".")[0] == "drivers" and not _in_contract(d)))
                 for m, deps in GRAPH_WITH_TYPES.items() if m.split(".")[0] == "sim_backend"}
    assert {m: d for m, d in offending.items() if d} == {}


@pytest.mark.parametrize("transport", ["canopen", "serial"])
def test_a_bench_without_services_hands_its_own_settings_to_the_drive_link(tmp_path, transport):
    """A real rig has no [services]: its [bench] timing and fault_reset must still reach the link (before, they
    only travelled through a simulator starter and a rig silently ran lockstep while the record said realtime)."""
    from bench.inputs.benchconfig import load_bench_config
    from bench.run.links import make_links

    drive = (f'transport = "canopen"\ninterface = "socketcand"\nchannel = "can0@127.0.0.1:29536"\nnode_id = 1\n'
             f'eds = "{REPO}/config/od/drivebench-pmsm.eds"\n' if transport == "canopen"
             else 'transport = "serial"\nport = "/dev/ttyUSB0"\n')
    path = tmp_path / "rig.toml"
    path.write_text(f"""[bench]
name = "a rig"
timing = "realtime"
fault_reset = "never"

[drive]
{drive}
[load]
transport = "modbus-tcp"
map = "config/load-machines/drivebench-sim.toml"
host = "127.0.0.1"
port = 502
""")
    cfg = load_bench_config(path)
    assert cfg.services_start is None
    link, _ = make_links(cfg, REPO)
    assert link.timing == "realtime"
    assert link.fault_reset_policy == "never"


def _layer(module: str) -> str:
    return "contract" if _in_contract(module) else module.split(".")[0]


def test_layers_import_only_downwards():
    """contract <- drivers' clients <- bench; contract <- sim_backend (counting type-only imports)."""
    allowed = {("drivers", "contract"), ("bench", "contract"), ("bench", "drivers"), ("sim_backend", "contract")}
    edges = {(_layer(m), _layer(d)) for m, deps in GRAPH_WITH_TYPES.items() for d in deps if _layer(m) != _layer(d)}
    assert edges <= allowed, sorted(edges - allowed)
    assert {("bench", "contract"), ("sim_backend", "contract"), ("drivers", "contract")} <= edges


BENCH_FLOORS = ("bench.inputs", "bench.outputs", "bench.run", "bench.faces", "bench.service")   # bottom to top


def _floor(module: str) -> int | None:
    return next((i for i, prefix in enumerate(BENCH_FLOORS) if module == prefix or module.startswith(prefix + ".")),
                None)


def test_bench_groups_import_only_downwards_but_for_the_stated_exceptions():
    """inputs <- outputs <- run machinery <- faces (CLI, campaigns) <- the HTTP service: the CLI installs the
    service's reporters through bench.faces.run_hooks, it does not import the service (docs/architecture.md)."""
    stated = {("bench.inputs.scenario", "bench.run.load_emulation")}     # the emulable load modes, checked at parse
    upward = {(m, d) for m, deps in GRAPH_WITH_TYPES.items() for d in deps
              if _floor(m) is not None and _floor(d) is not None and _floor(d) > _floor(m)}
    assert upward - stated == set(), sorted(upward - stated)
    assert ("bench.faces.cli", "bench.service.child") not in upward


def test_bench_calls_the_links_through_their_declared_protocols_not_by_probing_attributes():
    """What a link may lack is declared on DriveLink / LoadLink with the default the bench gets (drill: None, keepalive
    and interrupt: nothing), so the bench never asks a link with getattr/hasattr whether it has a member."""
    from drivers.api import DriveLink, LoadLink

    members = {name for proto in (DriveLink, LoadLink) for name in vars(proto) if not name.startswith("_")}
    probes = []
    for path in sorted((REPO / "bench").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in ("getattr", "hasattr")
                    and len(node.args) >= 2 and isinstance(node.args[1], ast.Constant)
                    and node.args[1].value in members):
                probes.append(f"{path.relative_to(REPO)}:{node.lineno}: {node.func.id}(..., {node.args[1].value!r})")
    assert {"drill", "keepalive", "interrupt", "begin_quick_stop", "set_reference_speed"} <= members
    assert probes == []

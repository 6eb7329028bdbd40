"""docs/architecture.md stays true: its import graph is what docs/import_graph.py computes from the code now, the
grouping follows modules by path prefix when they move, and every file its concept table names exists."""

from __future__ import annotations

import importlib.util
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "architecture.md"


def _load_script():
    spec = importlib.util.spec_from_file_location("import_graph", ROOT / "docs" / "import_graph.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["import_graph"] = module
    spec.loader.exec_module(module)
    return module


graph = _load_script()


def test_the_diagram_in_the_doc_is_the_code_now():
    assert graph.embedded(DOC.read_text(encoding="utf-8")) == graph.mermaid(), \
        "docs/architecture.md: the import graph is out of date: run python docs/import_graph.py"


def test_the_real_graph_sees_imports_and_keeps_the_layers():
    nodes, edges = graph.group_graph()
    assert {"contract", "clients", "inputs", "machinery", "outputs", "cli", "service", "sim_front"} <= set(nodes)
    assert edges[("cli", "machinery")] and edges[("machinery", "outputs")]      # bench.faces.cli, bench.run.orchestrator
    assert edges[("sim_front", "contract")]
    bench = {n for n, _, package, _ in graph.GROUPS if package == "bench"}
    sim = {n for n, _, package, _ in graph.GROUPS if package == "sim_backend"}
    assert not [e for e in edges if e[0] in bench and e[1] in sim]
    assert not [e for e in edges if e[0] in ("contract", "clients") and e[1] in bench | sim]


def _write(root: Path, rel: str, text: str = "") -> None:
    path = root / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


GROUPS = (
    ("contract", "contract", "drivers", ("drivers/contract/",)),
    ("clients", "clients", "drivers", ("drivers/",)),
    ("run", "run", "bench", ("bench/run", "bench/run/")),
    ("faces", "faces", "bench", ("bench/cli.py",)),
)


def test_groups_follow_a_module_by_its_path_and_show_what_no_prefix_matches(tmp_path):
    for package in graph.PACKAGES:
        _write(tmp_path, f"{package}/__init__.py")
    _write(tmp_path, "drivers/contract/__init__.py")
    _write(tmp_path, "drivers/contract/units.py")
    _write(tmp_path, "drivers/link.py", "from drivers.contract import units\n")
    _write(tmp_path, "bench/run_loop.py", "from drivers.link import x\n")
    _write(tmp_path, "bench/cli.py", "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                                     "    from drivers import link\ndef main():\n    from . import run_loop\n")
    _write(tmp_path, "bench/new_thing.py", "import bench.cli\n")
    nodes, edges = graph.group_graph(tmp_path, GROUPS)
    assert edges == {("clients", "contract"): True, ("run", "clients"): True, ("faces", "clients"): False,
                     ("faces", "run"): True, ("bench_ungrouped", "faces"): True}
    assert "bench_ungrouped" in nodes and "ungrouped" in graph.mermaid(tmp_path, GROUPS)
    assert "faces -.-> clients" in graph.mermaid(tmp_path, GROUPS)

    # the link moves into the contract folder: no table edit, it is drawn there
    (tmp_path / "drivers/link.py").rename(tmp_path / "drivers/contract/link.py")
    (tmp_path / "bench/run_loop.py").write_text("from drivers.contract.link import x\n")
    assert graph.group_of("drivers/contract/link.py", GROUPS) == "contract"
    _, edges = graph.group_graph(tmp_path, GROUPS)
    assert ("run", "contract") in edges and ("run", "clients") not in edges


@pytest.mark.slow
def test_check_fails_on_a_stale_diagram_and_the_script_rewrites_it(tmp_path, monkeypatch, capsys):
    doc = tmp_path / "architecture.md"
    text = DOC.read_text(encoding="utf-8")
    stale = text.replace("  cli --> machinery\n", "")
    assert stale != text
    doc.write_text(stale)
    monkeypatch.setattr(graph, "DOC", doc)
    monkeypatch.setattr(graph, "REPO", tmp_path)
    assert graph.main(["--check"]) == 1
    assert "run python docs/import_graph.py" in capsys.readouterr().err
    assert graph.main([]) == 0
    assert doc.read_text() == text and graph.main(["--check"]) == 0


def _concept_paths() -> list[str]:
    """Every path the concept table names; a bare file name after a path is in that path's folder."""
    table = DOC.read_text(encoding="utf-8").split("## Where each concept lives", 1)[1].split("\n## ", 1)[0]
    paths = []
    for line in table.splitlines():
        if not line.startswith("| ") or line.startswith("| concept") or line.startswith("| ---"):
            continue
        module_cell = line.rstrip(" |").rsplit(" | ", 1)[1]
        folder = ""
        for name in re.findall(r"`([^`]+)`", module_cell):
            if "/" in name:
                folder = name if name.endswith("/") else name.rpartition("/")[0] + "/"
                paths.append(name)
            else:
                paths.append(folder + name)
    return paths


@pytest.mark.parametrize("path", _concept_paths())
def test_every_file_the_concept_table_names_exists(path):
    assert (ROOT / path).exists(), f"docs/architecture.md names {path}, which is not there"

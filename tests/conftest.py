"""The test layout's markers (declared in pyproject.toml; docs/testing.md).

Everything under tests/system/ is marked `system`: tests that start real processes, browsers, databases or clusters,
or run long simulations. `slow` is set on each test that takes more than about a second on the 2-core machine.
The inner loop (`python3 dev.py quick`) leaves both out; `python3 dev.py test` (CI) runs everything.
"""

from __future__ import annotations

from pathlib import Path

import pytest

SYSTEM = Path(__file__).resolve().parent / "system"


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if SYSTEM in item.path.parents:
            item.add_marker(pytest.mark.system)

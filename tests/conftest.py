"""The test layout's markers (declared in pyproject.toml; docs/testing.md).

Everything under tests/system/ is marked `system`: tests that start real processes, browsers, databases or clusters,
or run long simulations. `slow` is set on each test that takes more than about a second on the 2-core machine.
The inner loop (`python3 dev.py quick`) leaves both out; `python3 dev.py test` (CI) runs everything.
"""

from __future__ import annotations

import types
from pathlib import Path

import pytest

SYSTEM = Path(__file__).resolve().parent / "system"


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if SYSTEM in item.path.parents:
            item.add_marker(pytest.mark.system)


@pytest.fixture(autouse=True)
def _no_pyserial_close_pause(monkeypatch: pytest.MonkeyPatch) -> None:
    """pyserial's socket:// close() sleeps 0.3 s "in case of quick reconnects": every serial link a test closed cost
    0.3 s of nothing. The simulated serial server takes a bench reconnecting at once
    (tests/sim_backend/test_server_abuse.py proves it), so the tests run without the pause."""
    from serial.urlhandler import protocol_socket

    monkeypatch.setattr(protocol_socket, "time", types.SimpleNamespace(sleep=lambda _seconds: None))

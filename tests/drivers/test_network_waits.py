"""Every network wait of the bench is bounded: a port that accepts and never speaks (a hung server, a typo that
points the CAN link at the Modbus port or the other way round) ends in a LinkError naming the endpoint, not a hang
(issue: `drivebench run` against a silent socketcand listener hung for good)."""

from __future__ import annotations

import socket
import threading
import time
from pathlib import Path

import pytest

import drivers.canopen.bus as canbus
from drivers.contract.errors import LinkError
from drivers.api import LinkSettings
from drivers.canopen.link import CanopenDriveLink
from drivers.modbus_load import ModbusLoadLink

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def silent_port():
    """A TCP listener that accepts every connection and never sends a byte."""
    server = socket.create_server(("127.0.0.1", 0))
    conns: list[socket.socket] = []
    stop = threading.Event()

    def accept():
        server.settimeout(0.1)
        while not stop.is_set():
            try:
                conns.append(server.accept()[0])
            except OSError:
                pass

    thread = threading.Thread(target=accept, daemon=True)
    thread.start()
    yield server.getsockname()[1]
    stop.set()
    thread.join(2)
    for c in conns:
        c.close()
    server.close()


@pytest.mark.slow
def test_socketcand_link_to_a_silent_port_fails_within_the_connect_timeout(silent_port, monkeypatch):
    monkeypatch.setattr(canbus, "CONNECT_TIMEOUT_S", 1.0)
    monkeypatch.setattr(canbus.open_bus, "__defaults__", (None, 1.0))
    monkeypatch.setattr(canbus.socketcand_greeting, "__defaults__", (1.0,))
    section = {"transport": "canopen", "interface": "socketcand", "channel": f"can0@127.0.0.1:{silent_port}",
               "node_id": 1, "eds": str(REPO / "config/od/drivebench-pmsm.eds"), "sync_period_s": 0.01}
    link = CanopenDriveLink(section, REPO, LinkSettings())
    t0 = time.monotonic()
    with pytest.raises(LinkError, match=f"no socketcand greeting from 127.0.0.1:{silent_port}"):
        link.open()
    assert time.monotonic() - t0 < 2.0


def test_socketcand_link_to_a_server_that_is_not_socketcand(monkeypatch):
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]

    def greet_wrong():
        conn, _ = server.accept()
        conn.sendall(b"HTTP/1.1 400 Bad Request\r\n\r\n")
        time.sleep(0.5)
        conn.close()

    threading.Thread(target=greet_wrong, daemon=True).start()
    with pytest.raises(ConnectionError, match="not a socketcand server"):
        canbus.socketcand_greeting("127.0.0.1", port, 1.0)
    server.close()


def test_a_hung_interface_driver_is_abandoned_at_the_timeout():
    release = threading.Event()
    t0 = time.monotonic()
    with pytest.raises(TimeoutError, match="took longer than 0.5 s"):
        canbus.open_bus({"interface": "virtual", "channel": "x"}, lambda: release.wait(30), timeout_s=0.5)
    assert time.monotonic() - t0 < 1.0
    release.set()


@pytest.mark.slow
def test_modbus_link_to_a_silent_port_fails_within_its_timeouts(silent_port):
    link = ModbusLoadLink({"transport": "modbus-tcp", "host": "127.0.0.1", "port": silent_port,
                           "map": "config/load-machines/drivebench-sim.toml", "timeout_s": 0.3, "retries": 1}, REPO)
    t0 = time.monotonic()
    with pytest.raises(LinkError, match=f"127.0.0.1:{silent_port}"):
        link.open()
    assert time.monotonic() - t0 < 3.0
    link.close()

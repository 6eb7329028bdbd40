"""`drivebench sim serve`: the out-of-process simulator's endpoints, and a clean exit on SIGINT/SIGTERM."""

from __future__ import annotations

import re
import signal
import socket
import threading

import pytest

from drivers.api import LinkSettings
from drivers.canopen.link import CanopenDriveLink
from tests.canopen_helpers import EDS, REPO
from tests.sim_process import read_endpoints, serve_sim

CONFIG = """
[simulator]
motor = "toy"
[simulator.serve]
canopen_socketcand = "127.0.0.1:0"
serial_tcp = "127.0.0.1:0"
modbus_tcp = "127.0.0.1:0"
[drive]
node_id = 3
eds = "{eds}"
"""


@pytest.mark.parametrize("stop_signal", [signal.SIGINT, signal.SIGTERM])
def test_serve_prints_its_endpoints_answers_on_them_and_exits_cleanly(tmp_path, stop_signal):
    config = tmp_path / "bench.toml"
    config.write_text(CONFIG.format(eds=EDS))
    proc = serve_sim(config)
    try:
        lines = read_endpoints(proc)
        canopen_line = next(l for l in lines if l.startswith("canopen "))
        m = re.fullmatch(r"canopen socketcand://127\.0\.0\.1:(\d+)/can0 node=3", canopen_line)
        assert m, canopen_line
        serial_port = int(re.fullmatch(r"serial socket://127\.0\.0\.1:(\d+)",
                                       next(l for l in lines if l.startswith("serial "))).group(1))
        modbus_port = int(re.fullmatch(r"modbus tcp://127\.0\.0\.1:(\d+) unit=1",
                                       next(l for l in lines if l.startswith("modbus "))).group(1))
        link = CanopenDriveLink(dict(transport="canopen", interface="socketcand",
                                     channel=f"can0@127.0.0.1:{m.group(1)}", node_id=3, eds=str(EDS),
                                     sync_period_s=0.01, sdo_timeout_s=2.0, heartbeat_timeout_s=2.0), REPO,
                                LinkSettings())
        try:
            identity = link.open()
            assert identity.device_name == "drivebench simulated PMSM drive"
            link.configure(["speed_est_mech_rad_s"], ["speed_est_mech_rad_s"], 10)
            link.enable_velocity_mode()
            link.set_speed_ref(5.0)
            samples = [s for _ in range(5) for s in link.sync()]
            assert [round(s.t_s, 6) for s in samples] == [0.01, 0.02, 0.03, 0.04, 0.05]
            assert len(link.fetch_trace()["t_s"]) == 50
            link.disable()
        finally:
            link.close()
        for port in (serial_port, modbus_port):
            socket.create_connection(("127.0.0.1", port), timeout=5).close()
        proc.send_signal(stop_signal)
        assert proc.wait(timeout=20) == 0, proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_serve_bad_config_is_one_line_and_exit_2(tmp_path):
    config = tmp_path / "bench.toml"
    config.write_text("[simulator]\nmotor = 'toy'\n[simulator.serve]\ncanopen_socketcand = 'localhost'\n")
    proc = serve_sim(config)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 2
    assert err.strip().splitlines() == [
        f"error: {config}: simulator.serve.canopen_socketcand: expected 'host:port', got 'localhost'"]


def test_an_endpoint_that_dies_ends_sim_serve_with_exit_1_and_one_line(tmp_path, monkeypatch):
    """A dead endpoint is a dead process: the supervisor (systemd, a CI job) sees the exit, never a silent server."""
    import io
    import time

    from sim_backend import serve as serve_module
    from sim_backend.serial_server import SerialTcpServer

    def broken(self, backoff):
        raise RuntimeError("accept broke")
    monkeypatch.setattr(SerialTcpServer, "_accept", broken)
    config = tmp_path / "serve.toml"
    config.write_text(CONFIG.format(eds=EDS))
    out = io.StringIO()
    result: dict = {}

    def run():
        try:
            serve_module.serve(serve_module.load_serve_config(config), threading.Event(), out)
        except BaseException as exc:
            result["error"] = exc
    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while "ready" not in out.getvalue() and time.monotonic() < deadline:
        time.sleep(0.05)
    port = int(re.search(r"serial socket://127\.0\.0\.1:(\d+)", out.getvalue()).group(1))
    socket.create_connection(("127.0.0.1", port)).close()
    thread.join(10)
    assert not thread.is_alive()
    assert isinstance(result.get("error"), serve_module.EndpointDied)
    assert "accept broke" in str(result["error"])

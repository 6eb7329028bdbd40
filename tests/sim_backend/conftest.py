"""Fixtures shared by the simulator tests."""

from __future__ import annotations

import pytest

from sim_backend.canopen.node import start_node
from sim_backend.device import SimulatedDevice
from sim_backend.rig import private_channel
from sim_backend.socketcand_server import SocketcandServer
from sim_backend.toy import ToyDrive
from tests.canopen_helpers import EDS


@pytest.fixture
def served():
    """A toy drive behind the simulated CANopen node on a private virtual channel, served by a socketcand server on
    127.0.0.1 (an ephemeral port): (server, node, device, channel)."""
    channel = private_channel()
    device = SimulatedDevice(ToyDrive())
    node = start_node(device, EDS, 1, interface="virtual", channel=channel)
    server = SocketcandServer(channel, "127.0.0.1", 0)
    yield server, node, device, channel
    server.stop()
    node.stop()

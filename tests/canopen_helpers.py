"""Shared set-up for the CANopen tests: a ToyDrive behind the simulated node on a private virtual channel,
the bench's link, and a passive sniffer on the same channel that sees every frame on the wire."""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import can

from drivers.api import LinkSettings
from drivers.canopen.link import CanopenDriveLink
from sim_backend.canopen.node import SimCanopenNode, start_node
from sim_backend.device import SimulatedDevice
from sim_backend.canopen.generic import DriveSpec
from sim_backend.rig import RigSpec, build, private_channel
from sim_backend.toy import ToyDrive

REPO = Path(__file__).resolve().parent.parent
EDS = REPO / "config" / "od" / "drivebench-pmsm.eds"
MOTOR = REPO / "config/motors/pmsm-paper.toml"
LIVE = ["speed_ref_mech_rad_s", "speed_est_mech_rad_s", "i_sy_a", "vdc_v"]


class Sniffer:
    """A bus that only listens; frames() returns what arrived since the last call, in wire order."""

    def __init__(self, channel: str):
        self.bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)

    def frames(self) -> list[can.Message]:
        out = []
        while (msg := self.bus.recv(0)) is not None:
            out.append(msg)
        return out

    def with_id(self, can_id: int) -> list[bytes]:
        return [bytes(m.data) for m in self.frames() if m.arbitration_id == can_id]

    def inject(self, can_id: int, data: bytes) -> None:
        self.bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))

    def close(self) -> None:
        self.bus.shutdown()


@dataclass
class Rig:
    toy: ToyDrive
    device: SimulatedDevice
    node: SimCanopenNode
    link: CanopenDriveLink
    sniffer: Sniffer
    channel: str


def link_section(channel: str, **overrides) -> dict:
    section = dict(transport="canopen", interface="virtual", channel=channel, bitrate=1_000_000, node_id=1,
                   eds=str(EDS), sync_period_s=0.01, heartbeat_timeout_s=1.0, sdo_timeout_s=1.0,
                   trace_decimation=1, consumer_time_ms=2000)
    section.update(overrides)
    return section


@contextlib.contextmanager
def rig(node_eds: Path = EDS, open_link: bool = True, **section) -> Iterator[Rig]:
    channel = private_channel()
    sniffer = Sniffer(channel)
    toy = ToyDrive()
    device = SimulatedDevice(toy)
    node = start_node(device, node_eds, 1, interface="virtual", channel=channel)
    settings = LinkSettings(**{k: section.pop(k) for k in ("timing", "fault_reset") if k in section})
    link = CanopenDriveLink(link_section(channel, **section), REPO, settings)
    try:
        if open_link:
            link.open()
        yield Rig(toy, device, node, link, sniffer, channel)
    finally:
        link.close()
        node.stop()
        sniffer.close()


# A generic CiA 402 drive built from a third-party EDS (config/od/third-party), on the paper PMSM, behind the bench's
# CANopen link (the third-party drive and comm-loss drill tests).
def eds_path(name: str) -> Path:
    return REPO / "config/od/third-party" / f"{name}.eds"


@contextlib.contextmanager
def generic_link(eds: str, spec: DriveSpec, motor=MOTOR, settings: LinkSettings = LinkSettings(), **section):
    with build(RigSpec(motor=motor, seed=1, eds=eds_path(eds), drive=spec)) as rig:
        fields = dict(transport="canopen", interface="virtual", channel=rig.channel, node_id=1, eds=str(eds_path(eds)),
                      sync_period_s=0.01, heartbeat_timeout_s=2.0, sdo_timeout_s=2.0, consumer_time_ms=2000)
        link = CanopenDriveLink(fields | section, REPO, settings)
        try:
            yield link, rig
        finally:
            link.close()


def sync_for(link, seconds: float):
    return [s for _ in range(round(seconds / link.sync_period_s)) for s in link.sync()]

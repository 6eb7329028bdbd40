"""The CAN bus under the link: python-can arguments from a [drive] table, bus-load arithmetic, bus health."""

from __future__ import annotations

from typing import Any

import can

ERROR_PASSIVE_LEVEL = 128    # CAN receive error counter at which a controller goes error passive (ISO 11898-1)

# [drive] keys the link itself reads; every other key passes through to python-can's Bus(...)
LINK_KEYS = frozenset({"transport", "sync_period_s", "heartbeat_timeout_s", "trace_decimation", "trace_signals",
                       "node_id", "eds", "sdo_timeout_s", "interface", "channel", "bitrate", "can", "profile",
                       "velocity_unit", "encoder_increments_per_rev", "gear_ratio", "rated_torque_nm",
                       "rated_current_a", "signals", "pdo", "comm_loss", "consumer_time_ms", "abort_option",
                       "error_behaviour", "bench_node_id", "standstill_mech_rad_s", "stop_timeout_s"})


def frame_bits(n_data_bytes: int) -> int:
    """Bits of a CAN 2.0A data frame on the wire, with worst-case bit stuffing (ISO 11898-1)."""
    unstuffed = 47 + 8 * n_data_bytes
    return unstuffed + (34 + 8 * n_data_bytes - 1) // 4


def bus_kwargs(section: dict) -> dict[str, Any]:
    """python-can Bus(...) arguments from a [drive] table.

    python-can's own options (fd, data_bitrate, app_name, serial, host, port, ...) pass through from the [drive.can]
    table, verbatim; the channel may be a name or a number, as the interface wants it. For socketcand the endpoint
    may also be written in the channel as `can0@127.0.0.1:29536`.
    """
    kwargs: dict[str, Any] = {"interface": section["interface"], "channel": section["channel"]}
    if section.get("bitrate"):
        kwargs["bitrate"] = section["bitrate"]
    kwargs.update({k: v for k, v in section.items() if k not in LINK_KEYS})
    kwargs.update(section.get("can") or {})
    channel = str(kwargs["channel"])
    if kwargs["interface"] == "socketcand" and "@" in channel and "host" not in kwargs:
        name, _, endpoint = channel.partition("@")
        host, _, port = endpoint.rpartition(":")
        kwargs.update(channel=name, host=host, port=int(port))
    if kwargs["interface"] == "virtual":
        kwargs.setdefault("receive_own_messages", False)
    return kwargs


class BusErrorCounter(can.Listener):
    """Error frames as a receive error counter would count them (+8 per error frame, -1 per good frame), and
    the interface's own bus state where it reports one (python-can BusState; socketcan, pcan, ... do)."""

    def __init__(self):
        self.counter = 0
        self.error_frames = 0

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            self.error_frames += 1
            self.counter += 8
        elif self.counter:
            self.counter -= 1

    def problem(self, bus: can.BusABC | None) -> str | None:
        try:
            state = bus.state if bus is not None else can.BusState.ACTIVE
        except (NotImplementedError, can.CanError, OSError):
            state = can.BusState.ACTIVE
        if state is can.BusState.ERROR:
            return "CAN bus off (the interface reports BusState.ERROR)"
        if state is can.BusState.PASSIVE:
            return "CAN controller error passive (the interface reports BusState.PASSIVE)"
        if self.counter >= ERROR_PASSIVE_LEVEL:
            return (f"CAN bus errors: {self.error_frames} error frames, receive error count ~{self.counter} "
                    f">= {ERROR_PASSIVE_LEVEL} (error passive)")
        return None

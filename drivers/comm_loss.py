"""How a drive is told to stop itself when the bench dies, whatever the transport: the bench config's comm-loss
settings. CANopen applies them with 0x1016/0x6007/0x1029 (drivers.canopen.comm_loss), the serial line with its
WATCHDOG command."""

from __future__ import annotations

from dataclasses import dataclass

from drivers.canopen.objects import HEARTBEAT_BENCH_NODE_ID


MODES = ("heartbeat", "external")   # the serial line's WATCHDOG command is its "heartbeat"


@dataclass(frozen=True)
class CommLossConfig:
    mode: str = "heartbeat"             # "external": the rig stops the drive itself (e.g. STO on a watchdog relay)
    consumer_time_ms: int = 300         # the drive reacts this long after the bench's last heartbeat
    abort_option: int = 3               # 0x6007: 1 fault, 2 disable voltage, 3 quick stop (the drive manual decides)
    error_behaviour: int | None = 0     # 0x1029 sub 1 (communication error): 0 pre-operational; None: leave it
    bench_node_id: int = HEARTBEAT_BENCH_NODE_ID

    @property
    def producer_period_s(self) -> float:
        """The bench's heartbeat period: a quarter of the consumer time, so three can be lost without a reaction."""
        return max(0.01, self.consumer_time_ms / 4000.0)

    @classmethod
    def from_section(cls, section: dict) -> "CommLossConfig":
        kw = {k: section[k] for k in ("consumer_time_ms", "abort_option", "bench_node_id") if k in section}
        if "comm_loss" in section:
            kw["mode"] = section["comm_loss"]
        if "error_behaviour" in section:
            kw["error_behaviour"] = section["error_behaviour"]
        return cls(**kw)


STOP_KEYS = ("comm_loss", "consumer_time_ms", "abort_option", "standstill_mech_rad_s", "stop_timeout_s")


def _int_in(value, low: int, high: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and low <= value <= high


def check_keys(section: dict, keys: tuple[str, ...] = STOP_KEYS) -> tuple[dict, list[tuple[str, str]]]:
    """The comm-loss and safe-stop keys of a [drive] table (any transport): normalised values and (field, reason)."""
    out: dict = {}
    problems: list[tuple[str, str]] = []
    rules = {
        "comm_loss": (lambda v: v in MODES, f"must be one of {', '.join(repr(m) for m in MODES)}"),
        "consumer_time_ms": (lambda v: _int_in(v, 50, 65535), "must be an integer of ms within 50..65535"),
        "abort_option": (lambda v: _int_in(v, -32768, 32767),
                         "must be the drive's 0x6007 code (1 fault, 2 disable voltage, 3 quick stop)"),
        "error_behaviour": (lambda v: _int_in(v, 0, 255), "must be the 0x1029 code (0 pre-operational, 1 no change, "
                                                         "2 stopped)"),
        "bench_node_id": (lambda v: _int_in(v, 1, 127), "must be a node id within 1..127"),
        "standstill_mech_rad_s": (lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and 0 < v < 1e6,
                                  "must be a number > 0 (mech rad/s)"),
        "stop_timeout_s": (lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and 0 < v <= 600,
                           "must be a number of seconds within (0, 600]"),
    }
    for key in keys:
        if key in section:
            ok, reason = rules[key]
            if ok(section[key]):
                out[key] = section[key]
            else:
                problems.append((f"drive.{key}", f"{reason}, got {section[key]!r}"))
    return out, problems

"""How a drive is told to stop itself when the bench dies, whatever the transport: the bench config's comm-loss
settings. CANopen applies them with 0x1016/0x6007/0x1029 (drivers.canopen.comm_loss_guard), the serial line with its
WATCHDOG command."""

from __future__ import annotations

from dataclasses import dataclass

from drivers.contract.objects import HEARTBEAT_BENCH_NODE_ID


MODES = ("heartbeat", "external")   # the serial line's WATCHDOG command is its "heartbeat"


@dataclass(frozen=True)
class CommLossConfig:
    mode: str = "heartbeat"             # "external": the rig stops the drive itself (e.g. STO on a watchdog relay)
    external_stop: str = ""             # with "external": what stops it, in words (mandatory; shown as unverified)
    consumer_time_ms: int = 300         # the drive reacts this long after the bench's last heartbeat
    abort_option: int = 3               # 0x6007: 1 fault, 2 disable voltage, 3 quick stop (the drive manual decides)
    error_behaviour: int | None = 0     # 0x1029 sub 1 (communication error): 0 pre-operational; None: leave it
    bench_node_id: int = HEARTBEAT_BENCH_NODE_ID
    drill_margin_ms: int | None = None  # the drill allows consumer time + this (None: DEFAULT_MARGIN)

    @property
    def margin_ms(self) -> int:
        """How late after the consumer time the drive may leave OPERATION ENABLED in the drill: its own check period
        and the bench's statusword polls by SDO, whose round trips a loaded host stretches (stated; default the larger
        of 200 ms and a quarter of the consumer time)."""
        if self.drill_margin_ms is not None:
            return self.drill_margin_ms
        return max(200, self.consumer_time_ms // 4)

    @property
    def producer_period_s(self) -> float:
        """The bench's heartbeat period: a quarter of the consumer time, so three can be lost without a reaction."""
        return max(0.01, self.consumer_time_ms / 4000.0)

    @classmethod
    def from_section(cls, section: dict) -> "CommLossConfig":
        kw = {k: section[k] for k in ("consumer_time_ms", "abort_option", "bench_node_id", "external_stop",
                                      "drill_margin_ms") if k in section}
        if "comm_loss" in section:
            kw["mode"] = section["comm_loss"]
        if "error_behaviour" in section:
            kw["error_behaviour"] = section["error_behaviour"]
        return cls(**kw)


STOP_KEYS = ("comm_loss", "external_stop", "consumer_time_ms", "abort_option", "drill_margin_ms",
             "standstill_mech_rad_s", "stop_timeout_s")
EXTERNAL_HINT = 'comm_loss = "external" and external_stop = "<what stops it, e.g. STO relay on watchdog K3>"'


def external_stop_problem(section: dict, table: str) -> tuple[str, str] | None:
    """comm_loss = "external" switches the drill off: only with a stated stop chain (shown as unverified)."""
    if section.get("comm_loss") == "external":
        text = section.get("external_stop")
        if not isinstance(text, str) or len(text.strip()) < 3:
            return (f"{table}.external_stop", 'comm_loss = "external" needs the rig\'s stop chain stated, e.g. '
                    'external_stop = "STO relay on watchdog K3": the bench cannot check it and shows the run as '
                    "unverified comm-loss reaction")
    elif "external_stop" in section:
        return (f"{table}.external_stop", 'only with comm_loss = "external"')
    return None


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
        "external_stop": (lambda v: isinstance(v, str) and 0 < len(v) <= 200,
                          "must be a text of at most 200 characters saying what stops the drive"),
        "drill_margin_ms": (lambda v: _int_in(v, 10, 10000), "must be an integer of ms within 10..10000"),
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
    if "comm_loss" in keys:
        problem = external_stop_problem(section, "drive")
        if problem is not None:
            problems.append(problem)
    return out, problems

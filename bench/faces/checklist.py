"""`drivebench probe`'s checklist: a lab's first step, one line per item — ok / fix / unknown — with the bench config
line to write. Built from what the probe read from the drive (drivers.canopen.probe), the bench config and, with
--drill, the drill's result."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

from canopen.emcy import EmcyError

from drivers.contract.comm_loss import EXTERNAL_HINT
from drivers.contract.load_map import read_load_map

PV, CSV = "profile_velocity", "cyclic_sync_velocity"
SYNC_TYPES = range(1, 241)


@dataclass(frozen=True)
class Item:
    item: str
    status: str                 # ok | fix | unknown
    detail: str
    config_line: str = ""       # what to write in the bench config ("" when nothing)

    def line(self) -> str:
        write = f"  -> write: {self.config_line}" if self.config_line else ""
        return f"{self.status.upper():8s}{self.item}: {self.detail}{write}"


def checklist(drive: dict[str, Any], cfg: Any, drill: dict[str, Any] | None = None) -> list[Item]:
    items = [_cia402(drive), _remote(drive), _mode(drive), *_units(drive, cfg), _pdos(drive),
             *_comm_loss(drive, drill),
             _load(cfg, drill), _node_id(drive), _fault(drive)]
    return items


def as_json(items: list[Item]) -> list[dict[str, str]]:
    return [asdict(i) for i in items]


def _cia402(d: dict) -> Item:
    dt = d["device_type"]
    if dt["cia402"]:
        return Item("402 device", "ok", f"device type {dt['raw']} (CiA 402 drive profile)")
    return Item("402 device", "fix", f"device type {dt['raw']} is profile {dt['profile']}, not a CiA 402 drive: "
                                     "wrong node id, or not a drive the bench can run")


def _remote(d: dict) -> Item:
    word = d.get("statusword")
    if word is None:
        return Item("remote (statusword bit 9)", "unknown", "no statusword (0x6041) answered")
    if word & 0x0200:
        return Item("remote (statusword bit 9)", "ok", f"= 1: the drive follows the bench's controlword "
                                                       f"(statusword 0x{word:04X})")
    return Item("remote (statusword bit 9)", "fix", f"statusword bit 9 (remote) = 0: the drive is in local control "
                                                    f"(statusword 0x{word:04X}) and ignores the bench's controlword; "
                                                    f"switch it to remote (local/remote switch, panel, enable input)")


def _mode(d: dict) -> Item:
    modes = d.get("supported_modes")
    if modes is None:
        return Item("usable mode", "unknown", "no 0x6502 (supported drive modes): the enable will show whether "
                                               "profile velocity (3) is accepted")
    if PV in modes:
        return Item("usable mode", "ok", "profile velocity (3) supported")
    if CSV in modes:
        return Item("usable mode", "ok", "no profile velocity, only cyclic synchronous velocity (9): the bench runs "
                                         "it in CSV, a target with every SYNC (velocity_mode = \"auto\" chooses it)")
    return Item("usable mode", "fix", f"neither profile velocity nor CSV among {', '.join(modes) or 'none'}")


def _units(d: dict, cfg: Any = None) -> list[Item]:
    profile, units = d.get("profile") or {}, d["units"]
    out = []
    if "error" in profile:
        text = profile["error"]
        line = ('velocity_unit = "rpm"   # or "inc/s" + encoder_increments_per_rev, from the drive\'s manual'
                if "velocity unit" in text else "")
        out.append(Item("units", "fix", text, line))
    else:
        source = (profile.get("units_from") or {}).get("velocity_unit", "")
        out.append(Item("units", "ok", f"velocity in {units['velocity_0x60A9']}" if "not on" not in
                        units["velocity_0x60A9"] else f"velocity unit {source}"))
    gear = units.get("gear_0x6091", "not on this drive")
    stated = ((cfg.drive if cfg is not None else None) or {}).get("gear_ratio")
    if gear == "not on this drive" and stated:
        out.append(Item("gear", "ok", f"no gear ratio object (0x6091); the bench config states gear_ratio = "
                                      f"[{', '.join(f'{v:g}' for v in stated)}] (motor : shaft)"))
    elif gear == "not on this drive":
        out.append(Item("gear", "unknown", "no gear ratio object (0x6091): state it where the velocity unit counts "
                                           "motor revolutions or increments", "gear_ratio = [1, 1]   # motor : shaft"))
    else:
        out.append(Item("gear", "ok", gear))
    return out


def _pdos(d: dict) -> Item:
    valid = [t for t in d.get("tpdos", []) if t["valid"]]
    event = [t for t in valid if t["transmission_type"] not in SYNC_TYPES]
    if not d.get("tpdos"):
        return Item("PDO transmission", "unknown", "no TPDO communication parameters answered")
    if not valid:
        return Item("PDO transmission", "unknown", f"none of the {len(d['tpdos'])} TPDOs is valid (all disabled): "
                                                   "the drive sends no process data now; the bench maps and enables "
                                                   "its own where the drive lets it, else it has no live samples")
    if event:
        names = ", ".join(f"TPDO{t['number']} type {t['transmission_type']}" for t in event)
        return Item("PDO transmission", "unknown", f"{names}: not on SYNC; the bench writes type 1 (every SYNC) "
                                                   "where the drive lets it, else its samples are not SYNC-aligned")
    return Item("PDO transmission", "ok", f"{len(valid)} valid TPDO(s), all on SYNC")


def _comm_loss(d: dict, drill: dict | None) -> list[Item]:
    hb = d["heartbeat"]
    out = []
    if hb["consumer_0x1016"] is None:
        out.append(Item("0x1016 consumer heartbeat", "fix", "absent: the drive cannot stop itself when the bench dies",
                        f"[drive] {EXTERNAL_HINT}"))
    else:
        out.append(Item("0x1016 consumer heartbeat", "ok", f"{len(hb['consumer_0x1016'])} entr(y/ies)"))
    option = hb.get("abort_connection_0x6007")
    if option is None:
        out.append(Item("0x6007 abort connection", "fix" if drill is None else "unknown",
                        "absent: the drive's reaction to a lost heartbeat is its own default (maybe none); run "
                        "`drivebench probe --drill` to see it", ""))
    else:
        out.append(Item("0x6007 abort connection", "ok", f"= {option} now; the bench writes abort_option (default 3, "
                                                         "quick stop)"))
    if drill is not None:
        result = drill.get("drive") or {}
        if result.get("result") == "passed":
            out.append(Item("drill: drive", "ok", f"left OPERATION ENABLED {result['left_operation_enabled_ms']:.0f} "
                                                  f"ms after the bench's heartbeat stopped (consumer "
                                                  f"{result['consumer_ms']} ms)"))
        elif result.get("result") == "unverified":
            out.append(Item("drill: drive", "unknown", f"not drilled: external stop chain stated "
                                                       f"({result.get('external_stop')})"))
        else:
            out.append(Item("drill: drive", "fix", result.get("refusal", "failed"), f"[drive] {EXTERNAL_HINT}"))
    return out


def _load(cfg: Any, drill: dict | None) -> Item:
    load = cfg.load if cfg is not None else {}
    if not load:
        return Item("load machine watchdog", "ok", "no load machine (free shaft)")
    if load.get("comm_loss") == "external":
        return Item("load machine watchdog", "unknown", f"external stop chain stated ({load.get('external_stop')}): "
                                                        "unverified comm-loss reaction")
    if not load.get("map"):
        return Item("load machine watchdog", "unknown", "no register map readable")
    has = bool(read_load_map(load["map"]).watchdog_timeout_ms)
    result = (drill or {}).get("load") if drill else None
    if not has:
        return Item("load machine watchdog", "fix", "its register map has no watchdog register: it keeps its torque "
                                                    "when the bench dies", f"[load] {EXTERNAL_HINT}")
    if isinstance(result, dict) and result.get("result") == "failed":
        return Item("load machine watchdog", "fix", result.get("refusal", "drill failed"), f"[load] {EXTERNAL_HINT}")
    if isinstance(result, dict) and result.get("result") == "passed":
        return Item("load machine watchdog", "ok", f"drill: disabled within {result['disabled_within_ms']:.0f} ms of "
                                                   f"silence (watchdog {result['timeout_ms']} ms)")
    return Item("load machine watchdog", "ok", "watchdog register in its map (`--drill` proves it)")


def _node_id(d: dict) -> Item:
    bench = d.get("bench_node_id") or {}
    if bench.get("id") == d["node_id"]:
        return Item("bench node id", "fix", f"the bench's heartbeat id {bench['id']} is the drive's own node id",
                    "bench_node_id = 126   # any id no node on the bus uses")
    if bench.get("answers_on_the_bus"):
        return Item("bench node id", "fix", f"node {bench['id']} answers on the bus: the bench's heartbeat "
                                            f"(0x{0x700 + bench['id']:03X}) would clash with it",
                    "bench_node_id = 126   # any id no node on the bus uses")
    return Item("bench node id", "ok", f"{bench.get('id')}: no node answers there")


def _fault(d: dict) -> Item:
    state = d.get("state") or "unknown"
    code = d.get("error_code_0x603F")
    if "FAULT" not in state:
        return Item("fault state", "ok", f"{state}" + (f", error code 0x{code:04X}" if code else ""))
    text = EmcyError(code or 0, 0, b"", 0.0).get_desc() if code is not None else "no 0x603F"
    return Item("fault state", "fix", f"{state}: error code 0x{(code or 0):04X} ({text or 'vendor-specific'}); the "
                                      "bench resets it only with fault_reset = \"once\" — look at the drive first",
                "[bench] fault_reset = \"once\"   # after the cause is understood")

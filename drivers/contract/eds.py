"""What a drive's EDS (or DCF) says before anything is connected: its identity numbers, whether it carries
drivebench's extension, and which catalogue parameters (drivers.contract.parameters) it offers.

The bench reads this at validation time, so `drivebench validate` and `drivebench run` judge a scenario against the
same description of the drive.
"""

from __future__ import annotations

import functools
import pickle
from dataclasses import dataclass
from pathlib import Path

import canopen
from canopen import objectdictionary

from drivers.contract import extension, parameters
from drivers.contract.errors import ContentError
from drivers.contract import objects as o

MAX_EDS_BYTES = 4 * 1024 * 1024      # real EDS files are tens of kB; a DCF with data a few hundred


@dataclass(frozen=True)
class DeviceDescription:
    path: Path
    vendor_id: int | None
    product_code: int | None
    product_name: str
    od: canopen.ObjectDictionary

    @property
    def drivebench_kind(self) -> str | None:
        """'pmsm' / 'spim' when the EDS is of a drive carrying drivebench's extension."""
        if self.vendor_id is None or self.product_code is None:
            return None
        return extension.kind_of(self.vendor_id, self.product_code)

    def has(self, index: int, subindex: int | None = None) -> bool:
        if index not in self.od:
            return False
        obj = self.od[index]
        return subindex is None or isinstance(obj, objectdictionary.ODVariable) or subindex in obj

    def offered_parameters(self) -> tuple[parameters.Parameter, ...]:
        """Catalogue parameters the drive has as writable manufacturer objects of the same name (catalogue order)."""
        kind = self.drivebench_kind
        offered = []
        for param in parameters.CATALOGUE:
            if kind is not None and kind not in param.drive_kinds:
                continue
            obj = self.od[param.name] if param.name in self.od else None
            if (isinstance(obj, objectdictionary.ODVariable) and obj.index in o.MANUFACTURER_RANGE
                    and obj.writable and all(p.name != param.name for p in offered)):
                offered.append(param)
        return tuple(offered)


def load_od(path: str | Path, node_id: int) -> canopen.ObjectDictionary:
    """canopen.import_od(path, node_id), parsed once per file version (size, mtime) in a process: every call gets its
    own copy (callers add objects and change defaults), unpickled in ~3 ms instead of parsed in ~35 ms — each run of a
    campaign worker, a test session or a benchmark opened the same EDS twice (the link and the simulated node)."""
    path = Path(path)
    stat = path.stat()
    return pickle.loads(_od_snapshot(str(path), stat.st_size, stat.st_mtime_ns, node_id))


@functools.lru_cache(maxsize=16)
def _od_snapshot(path: str, size: int, mtime_ns: int, node_id: int) -> bytes:
    return pickle.dumps(canopen.import_od(path, node_id), protocol=pickle.HIGHEST_PROTOCOL)


def read_eds(path: str | Path, node_id: int = 1) -> DeviceDescription:
    """Parse an EDS/DCF; ContentError with the reason when it is not a regular, bounded, parseable object dictionary
    with a statusword (0x6041) — what every CiA 402 drive has."""
    path = Path(path)
    try:
        if not path.is_file():
            raise ContentError("not a regular file")
        size = path.stat().st_size
    except OSError as exc:
        raise ContentError(f"cannot read: {exc.strerror or exc}") from None
    if size == 0:
        raise ContentError("empty file")
    if size > MAX_EDS_BYTES:
        raise ContentError(f"{size} bytes, larger than any object dictionary ({MAX_EDS_BYTES} bytes at most)")
    if path.suffix.lower() not in (".eds", ".dcf"):
        raise ContentError("not an EDS or DCF file (the name must end in .eds or .dcf)")
    try:
        text = path.read_bytes()
        if b"\0" in text:
            raise ContentError("binary data, not an EDS text file")
        od = canopen.import_od(str(path), node_id)
    except ContentError:
        raise
    except Exception as exc:       # configparser, ValueError, KeyError, UnicodeDecodeError: all "not an EDS"
        reason = " ".join(str(exc).split()) or type(exc).__name__
        raise ContentError(f"not a valid EDS: {reason[:200]}") from None
    if o.STATUSWORD not in od:
        raise ContentError("no statusword 0x6041: not a CiA 402 drive")
    info = od.device_information
    return DeviceDescription(path=path, vendor_id=info.vendor_number, product_code=info.product_number,
                             product_name=str(info.product_name or ""), od=od)

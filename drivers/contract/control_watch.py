"""Does the drive still obey the bench? CiA 402 statusword bit 9 (remote) and the manufacturer bits a bench config
names as enable conditions ([drive] enable_bits), watched on every statusword the link gets, whatever the transport.

A drive whose bit 9 drops has left remote control — an operator turned a local/remote switch, a wire to its enable
input came loose, a panel took over — and from then on it ignores the controlword and keeps its last target. While
it is enabled or moving that is a trip of its own (`remote_lost`): the bench cannot stop it by the controlword, only
by letting its comm-loss reaction act (drivers.contract.last_resort). The first drop is latched with the time it was
seen, so a 20 ms status poll never misses one that came and went between polls.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from drivers.contract.cia402 import POWERED_STATES, StatusBit, decode, state_name

REMOTE_BIT = 9
MANUFACTURER_BITS = (8, 14, 15)       # CiA 402 Table 30: manufacturer-specific statusword bits
TRIP = "remote_lost"


def enable_bits_problem(value: object) -> str | None:
    """[drive] enable_bits: manufacturer statusword bits the drive sets while it obeys the bench."""
    if (not isinstance(value, (list, tuple)) or not value
            or not all(isinstance(v, int) and not isinstance(v, bool) for v in value)):
        return "must be a non-empty list of statusword bit numbers"
    wrong = [v for v in value if v not in MANUFACTURER_BITS]
    if wrong:
        return (f"bit(s) {', '.join(map(str, wrong))} are not manufacturer-specific statusword bits "
                f"({', '.join(map(str, MANUFACTURER_BITS))}); bit 9 (remote) is always watched")
    return None


def local_control_line(word: int) -> str:
    """Why a drive with bit 9 = 0 does not follow the bench's controlword, in CiA terms and what to do."""
    return (f"statusword bit 9 (remote) = 0: the drive is in local control (statusword 0x{word:04X}, "
            f"{state_name(word)}) and ignores the bench's controlword; switch it to remote (its local/remote switch, "
            f"panel or enable input) and connect again")


@dataclass
class ControlWatch:
    """Fed every statusword; `lost` is one line once the drive stopped obeying while it was enabled or moving."""

    enable_bits: tuple[int, ...] = ()
    lost: str | None = None
    lost_at_s: float | None = None
    last_word: int | None = None
    _armed: bool = field(default=False, repr=False)

    @property
    def required_mask(self) -> int:
        mask = int(StatusBit.REMOTE)
        for bit in self.enable_bits:
            mask |= 1 << bit
        return mask

    def missing(self, word: int) -> list[int]:
        return [b for b in (REMOTE_BIT, *self.enable_bits) if not word >> b & 1]

    def obeys(self, word: int) -> bool:
        return not self.missing(word)

    def feed(self, word: int | None, t_s: float | None = None) -> None:
        """One statusword. Watching starts once the drive is powered with every bit set (the bench enabled it); a drop
        after that, while the drive is still powered, is latched."""
        if word is None:
            return
        self.last_word = word
        powered = decode(word) in POWERED_STATES
        if not self._armed:
            self._armed = powered and self.obeys(word)
            return
        if self.lost is None and powered and not self.obeys(word):
            self.lost, self.lost_at_s = self._line(word, t_s), t_s
        if not powered and self.lost is None:
            self._armed = False         # disabled by the bench: watched again at the next enable

    def refuse(self, where: str, what: str) -> None:
        """A controlword step is pointless once the drive left the bench's control: fail at once, so the safe stop
        reaches its last resort in milliseconds, not after a step timeout per step."""
        if self.lost is not None:
            from drivers.contract.errors import LinkError
            raise LinkError(f"{where}: {what}: not obeyed, statusword 0x{self.last_word or 0:04X}: the drive left the "
                            f"bench's control ({TRIP})")

    def _line(self, word: int, t_s: float | None) -> str:
        bits = self.missing(word)
        names = ", ".join("bit 9 (remote)" if b == REMOTE_BIT else f"bit {b} (enable condition, [drive] enable_bits)"
                          for b in bits)
        when = "" if t_s is None else f" at t={t_s:.4f} s"
        return (f"statusword {names} dropped{when} while {state_name(word)} (0x{word:04X}): the drive left the bench's "
                f"control (a local/remote switch, a loose enable input) and ignores the controlword; the bench stops "
                f"it by withholding its heartbeat, the drive's comm-loss reaction")

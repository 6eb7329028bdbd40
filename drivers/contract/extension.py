"""drivebench's drive-side extension: how a drive identifies itself as carrying drivebench's manufacturer objects.

The extension is the drive clock, the trace recorder, the estimator telemetry and the test hooks. A bench uses
them only when the drive's identity says it carries them (vendor ID and product code), whatever the transport —
never because an object index happens to exist: third-party drives put their own objects at those indices.
The simulated drivebench drives report this identity over CANopen (0x1018) and over the serial protocol alike.
"""

from __future__ import annotations

VENDOR_ID = 0x00DB0001
PRODUCT_CODES: dict[str, int] = {"pmsm": 0x0402_0001, "spim": 0x0402_0002}
REVISION = 0x0001_0000
FIRMWARE_VERSION = "drivebench-sim 0.1.0"


def device_name(kind: str) -> str:
    return f"drivebench simulated {kind.upper()} drive"


def kind_of(vendor_id: int, product_code: int) -> str | None:
    """'pmsm' / 'spim' for a drive carrying the extension, else None."""
    if vendor_id != VENDOR_ID:
        return None
    return next((kind for kind, code in PRODUCT_CODES.items() if code == product_code), None)


def carries_extension(vendor_id: int, product_code: int) -> bool:
    return kind_of(vendor_id, product_code) is not None

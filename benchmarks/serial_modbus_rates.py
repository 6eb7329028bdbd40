"""Protocol overhead of the serial drive link and the Modbus load link against the simulated backends.

Measures lockstep SYNC round trips per second (1 ms of drive time each) over TCP and a pty with the toy drive
(protocol cost only) and with the PMSM paper drive (real-time factor: drive seconds per wall second, over
serial in this process and to a server process vs calling the device directly), a full trace upload, and Modbus feedback reads per second over TCP
and RTU on a pty. Numbers on a shared 2-core machine are pessimistic.

    python benchmarks/serial_modbus_rates.py [--syncs N]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

from drivers.modbus_load import ModbusLoadLink
from drivers.api import LinkSettings
from drivers.serial_link import SerialDriveLink
from drivers.contract.signals import SIGNAL_NAMES
from sim_backend.device import SimulatedDevice
from sim_backend.modbus_server import start_modbus_rtu_pty, start_modbus_tcp
from sim_backend.serial_server import start_serial_pty, start_serial_tcp
from sim_backend.toy import ToyDrive

ROOT = Path(__file__).resolve().parents[1]


def enabled_link(port: str) -> SerialDriveLink:
    """A serial link at 1 ms SYNC tracing every signal, the drive enabled at 2 rad/s after one SYNC."""
    link = SerialDriveLink({"port": port, "timeout_s": 5.0, "sync_period_s": 0.001}, ROOT, LinkSettings())
    link.open()
    link.configure(list(SIGNAL_NAMES), list(SIGNAL_NAMES), 1)
    link.enable_velocity_mode()
    link.set_speed_ref(2.0)
    link.sync()
    return link


def timed_syncs(link: SerialDriveLink, n: int) -> float:
    t0 = time.perf_counter()
    for _ in range(n):
        link.sync()
    return time.perf_counter() - t0


def sync_rate(device: SimulatedDevice, start, n: int) -> tuple[float, float, float]:
    """(syncs per second, drive s per wall s, trace upload MB/s)"""
    server = start(device)
    link = enabled_link(getattr(server, "url", None) or server.path)
    wall = timed_syncs(link, n)
    t0 = time.perf_counter()
    trace = link.fetch_trace()
    upload = time.perf_counter() - t0
    rows = len(trace["t_s"])
    mb = rows * (4 + 4 * len(SIGNAL_NAMES)) / 1e6
    link.disable()
    link.close()
    server.stop()
    return n / wall, n * 1e-3 / wall, mb / upload


SERVER_SCRIPT = """
import sys, threading
from sim_backend.device import SimulatedDevice
from sim_backend.drive import make_drive
from sim_backend.serial_server import start_serial_tcp
drive = make_drive(sys.argv[1], 1)
drive.step(1)
server = start_serial_tcp(SimulatedDevice(drive))
print(server.port, flush=True)
sys.stdin.read()
server.stop()
"""


def out_of_process_rtf(motor: Path, n: int) -> float:
    """Drive s per wall s with the simulator in its own process (as `drivebench sim serve` runs it)."""
    proc = subprocess.Popen([sys.executable, "-c", SERVER_SCRIPT, str(motor)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        port = int(proc.stdout.readline())
        link = enabled_link(f"socket://127.0.0.1:{port}")
        rtf = n * 1e-3 / timed_syncs(link, n)
        link.close()
    finally:
        proc.stdin.close()
        proc.wait(30)
    return rtf


def direct_rtf(device: SimulatedDevice, n: int) -> float:
    for word in (0x06, 0x07, 0x0F):
        device.write_controlword(word)
    device.target_speed_mech_rad_s = 2.0
    steps = round(1e-3 / device.model.control_period_s)
    device.advance(steps)
    t0 = time.perf_counter()
    for _ in range(n):
        device.advance(steps)
    return n * 1e-3 / (time.perf_counter() - t0)


def modbus_rate(start, section: dict, n: int) -> float:
    device = SimulatedDevice(ToyDrive())
    server = start(device)
    link = ModbusLoadLink(section | ({"port": server.port} if "host" in section else {"port": server.path}), ROOT)
    link.open()
    t0 = time.perf_counter()
    for _ in range(n):
        link.feedback()
    rate = n / (time.perf_counter() - t0)
    link.close()
    server.stop()
    return rate


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--syncs", type=int, default=3000)
    args = parser.parse_args()
    n = args.syncs
    toy_tcp, _, _ = sync_rate(SimulatedDevice(ToyDrive()), start_serial_tcp, n)
    toy_pty, _, _ = sync_rate(SimulatedDevice(ToyDrive()), start_serial_pty, n)
    print(f"toy drive, SYNC round trips/s: TCP {toy_tcp:,.0f}  pty {toy_pty:,.0f}")

    from sim_backend.drive import make_drive
    motor = ROOT / "config/motors/pmsm-paper.toml"
    make = lambda: SimulatedDevice(make_drive(motor, 1))          # noqa: E731
    direct_rtf(make(), 50)                                         # JIT warm-up
    rtf_direct = direct_rtf(make(), n)
    _, rtf_tcp, trace_mb_s = sync_rate(make(), start_serial_tcp, n)
    _, rtf_pty, _ = sync_rate(make(), start_serial_pty, n)
    rtf_oop = out_of_process_rtf(motor, n)
    print(f"PMSM drive, drive s per wall s: direct {rtf_direct:.1f}  serial TCP {rtf_tcp:.1f}  pty {rtf_pty:.1f}"
          f"  TCP to another process {rtf_oop:.1f}  (in-process serial/direct {rtf_tcp / rtf_direct:.2f})")
    print(f"trace upload over TCP, all {len(SIGNAL_NAMES)} signals: {trace_mb_s:.1f} MB/s")

    mb_tcp = modbus_rate(start_modbus_tcp, {"transport": "modbus-tcp", "host": "127.0.0.1"}, 500)
    mb_rtu = modbus_rate(start_modbus_rtu_pty, {"transport": "modbus-rtu", "baudrate": 115200}, 200)
    print(f"Modbus feedback reads/s: TCP {mb_tcp:,.0f}  RTU/pty {mb_rtu:,.0f}")
    print(f"RESULT toy_sync_tcp_per_s={toy_tcp:.0f} toy_sync_pty_per_s={toy_pty:.0f} pmsm_rtf_direct={rtf_direct:.1f} "
          f"pmsm_rtf_serial_tcp={rtf_tcp:.1f} pmsm_rtf_serial_pty={rtf_pty:.1f} pmsm_rtf_serial_oop={rtf_oop:.1f} "
          f"serial_over_direct={rtf_tcp / rtf_direct:.2f} trace_upload_mb_s={trace_mb_s:.1f} "
          f"modbus_tcp_reads_per_s={mb_tcp:.0f} modbus_rtu_reads_per_s={mb_rtu:.0f}")


if __name__ == "__main__":
    main()

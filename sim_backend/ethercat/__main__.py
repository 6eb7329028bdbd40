"""Run a simulated EtherCAT slave on a network interface (raw AF_PACKET socket: root or CAP_NET_RAW):

    python -m sim_backend.ethercat --iface IFACE [--motor toy|config/motors/pmsm-paper.toml] [--eds FILE]
        [--seed N] [--refuse-safeop CODE] [--fixed-mapping]

It prints one line `ready IFACE vendor=... product=...` once it answers, and serves until SIGTERM/SIGINT. Frames
are answered in this process's one thread (the drive's comm-loss watchdog runs beside it)."""

from __future__ import annotations

import argparse
import os
import signal
import socket
import sys

from sim_backend.ethercat.frames import ETHERTYPE

DEFAULT_EDS = "config/od/drivebench-pmsm.eds"


def serve(iface: str, slave, stop) -> None:
    sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETHERTYPE))
    sock.bind((iface, ETHERTYPE))
    sock.settimeout(0.002)
    print(f"ready {iface} vendor=0x{slave.identity.vendor_id:08X} product=0x{slave.identity.product_code:08X}",
          flush=True)
    try:
        while not stop():
            try:
                frame = sock.recv(2048)
            except socket.timeout:
                frame = None
            if frame is not None:
                answer = slave.frame(frame)
                if answer is not None:
                    sock.send(answer)
            slave.watch_power()
            while slave.events:
                what, ms, state = slave.events.pop(0)
                print(f"event {what} after_last_frame_ms={ms} drive={state}", flush=True)
    finally:
        sock.close()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sim_backend.ethercat", description=__doc__.splitlines()[0])
    parser.add_argument("--iface", required=True)
    parser.add_argument("--motor", default="toy")
    parser.add_argument("--eds", default=None)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--refuse-safeop", type=lambda s: int(s, 0), default=0)
    parser.add_argument("--fixed-mapping", action="store_true")
    args = parser.parse_args(argv)
    from sim_backend.device import SimulatedDevice
    from sim_backend.ethercat.slave import Quirks, Slave
    try:                                  # an ESC answers in hardware; this one at least ahead of busy loops
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(60))
    except (PermissionError, OSError, AttributeError):
        pass
    from sim_backend.rig import make_model
    eds = args.eds or (DEFAULT_EDS if args.motor == "toy" or "pmsm" in args.motor else
                       "config/od/drivebench-spim.eds")
    device = SimulatedDevice(make_model(args.motor, args.seed))
    slave = Slave(device, eds, Quirks(refuse_safeop=args.refuse_safeop, fixed_mapping=args.fixed_mapping))
    stopping = []
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stopping.append(True))
    try:
        serve(args.iface, slave, lambda: bool(stopping))
    except OSError as exc:
        print(f"{args.iface}: {exc}", file=sys.stderr)
        return 2
    finally:
        device.stop_watchdogs()
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The simulator's three protocol servers under sustained abuse (the long version of tests/sim_backend/test_server_abuse.py).

`drivebench sim serve` runs as its own process (toy drive: the servers, not the physics, are measured). Rounds of:
32 MiB lines without '>' (before and after the socketcand handshake), socketcand clients that never read while the
bus is full, bursts of connections, a flood of maximum-length serial headers, garbage and half-open connections on
Modbus. Baseline from the same run: a normal client's round trip on each endpoint (socketcand SDO read, serial HELLO,
Modbus read) before any abuse; after every round the same client must still be served, and the server process's RSS
is read from /proc.

    python benchmarks/abuse.py [--rounds 5]

Last line: RESULT rounds=... rss_start_mb=... rss_end_mb=... rss_growth_mb=... normal_client_ok=...
           latency_ratio_socketcand=... latency_ratio_serial=... latency_ratio_modbus=... dropped_long_lines=...
"""

from __future__ import annotations

import argparse
import os
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from drivers.contract.serial_frames import SOF, Cmd, FrameDecoder, crc8, encode_frame  # noqa: E402

ENDPOINTS = ("canopen_socketcand", "serial_tcp", "modbus_tcp")     # every front end, on free loopback ports
# one_bench = false: the abuse clients and the normal client share the simulator
CONFIG = ('[simulator]\nmotor = "toy"\n[simulator.serve]\n' + "".join(f'{e} = "127.0.0.1:0"\n' for e in ENDPOINTS)
          + 'one_bench = false\n[drive]\nnode_id = 1\neds = "{eds}"\n')


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def expect(sock: socket.socket, marker: bytes) -> bytes:
    data = b""
    while marker not in data:
        chunk = sock.recv(4096)
        if not chunk:
            raise ConnectionError(f"closed before {marker!r}")
        data += chunk
    return data


def socketcand_client(port: int) -> float:
    t0 = time.perf_counter()
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        expect(s, b"< hi >")
        s.sendall(b"< open can0 >")
        expect(s, b"< ok >")
        s.sendall(b"< rawmode >")
        expect(s, b"< ok >")
        s.sendall(b"< send 601 8 40 0 10 0 0 0 0 0 >")
        expect(s, b"< frame 581 ")
    return time.perf_counter() - t0


def serial_client(port: int) -> float:
    t0 = time.perf_counter()
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.sendall(encode_frame(1, Cmd.HELLO, bytes([1, 1])))
        decoder = FrameDecoder()
        while not decoder.feed(s.recv(4096)):
            pass
    return time.perf_counter() - t0


def modbus_client(port: int) -> float:
    t0 = time.perf_counter()
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.sendall(struct.pack(">HHHBBHH", 1, 0, 6, 1, 3, 0, 1))     # read holding register 0
        got = b""
        while len(got) < 9:
            chunk = s.recv(256)
            if not chunk:
                raise ConnectionError("modbus closed")
            got += chunk
    return time.perf_counter() - t0


def long_lines(port: int, handshake: bool) -> None:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
            if handshake:
                expect(s, b"< hi >")
                s.sendall(b"< open can0 >")
                expect(s, b"< ok >")
                s.sendall(b"< rawmode >")
                expect(s, b"< ok >")
            for _ in range(512):
                s.sendall(b"A" * 65536)
    except OSError:
        pass


def slow_readers(port: int, n: int, hold_s: float) -> None:
    socks = []
    for _ in range(n):
        s = socket.create_connection(("127.0.0.1", port), timeout=5)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        expect(s, b"< hi >")
        s.sendall(b"< open can0 >")
        expect(s, b"< ok >")
        s.sendall(b"< rawmode >")
        expect(s, b"< ok >")
        socks.append(s)
    with socket.create_connection(("127.0.0.1", port), timeout=5) as talker:
        expect(talker, b"< hi >")
        talker.sendall(b"< open can0 >")
        expect(talker, b"< ok >")
        talker.sendall(b"< rawmode >")
        expect(talker, b"< ok >")
        end = time.monotonic() + hold_s
        while time.monotonic() < end:
            talker.sendall(b"< send 123 8 1 2 3 4 5 6 7 8 >" * 160)
            time.sleep(0.01)
    for s in socks:
        s.close()


def connection_burst(port: int, n: int) -> None:
    socks = []
    for _ in range(n):
        try:
            socks.append(socket.create_connection(("127.0.0.1", port), timeout=2))
        except OSError:
            break
    for s in socks:
        s.close()


def serial_header_flood(port: int) -> None:
    head = struct.pack("<HBB", 65535, 0, Cmd.SYNC)
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
            s.sendall((SOF + head + bytes([crc8(head)])) * (1 << 17))
    except OSError:
        pass


def modbus_garbage(port: int) -> None:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
            s.sendall(os.urandom(1 << 20))
    except OSError:
        pass
    half_open = [socket.create_connection(("127.0.0.1", port), timeout=2) for _ in range(50)]
    for s in half_open:
        s.sendall(b"\x00\x01\x00")
    time.sleep(0.2)
    for s in half_open:
        s.close()


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        config = Path(tmp) / "serve.toml"
        config.write_text(CONFIG.format(eds=REPO / "config/od/drivebench-pmsm.eds"))
        proc = subprocess.Popen([sys.executable, "-m", "sim_backend.serve", "--config", str(config)], cwd=REPO,
                                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                                env={**os.environ, "PYTHONUNBUFFERED": "1"})
        ports = {}
        for line in proc.stdout:
            if line.startswith("ready"):
                break
            name, url = line.split()[:2]
            ports[name] = int(url.split(":")[2].split("/")[0].split()[0])
        threading.Thread(target=lambda: [None for _ in proc.stdout], daemon=True).start()
        clients = {"socketcand": (socketcand_client, ports["canopen"]), "serial": (serial_client, ports["serial"]),
                   "modbus": (modbus_client, ports["modbus"])}

        def normal_round() -> dict[str, float]:
            return {name: min(fn(port) for _ in range(5)) for name, (fn, port) in clients.items()}

        try:
            baseline = normal_round()
            rss_start = rss_mb(proc.pid)
            ok = True
            after = baseline
            for r in range(args.rounds):
                long_lines(ports["canopen"], handshake=False)
                long_lines(ports["canopen"], handshake=True)
                slow_readers(ports["canopen"], 4, 3.0)
                connection_burst(ports["canopen"], 300)
                connection_burst(ports["serial"], 300)
                serial_header_flood(ports["serial"])
                modbus_garbage(ports["modbus"])
                time.sleep(0.5)
                try:
                    after = normal_round()
                except OSError as exc:
                    print(f"round {r + 1}: a normal client was not served: {exc}")
                    ok = False
                    break
                print(f"round {r + 1}: server RSS {rss_mb(proc.pid):.1f} MB; normal clients "
                      + ", ".join(f"{k} {v * 1e3:.1f} ms" for k, v in after.items()), flush=True)
            rss_end = rss_mb(proc.pid)
        finally:
            proc.terminate()
            proc.wait(10)
    ratios = {k: after[k] / baseline[k] for k in baseline}
    print(f"RESULT rounds={args.rounds} rss_start_mb={rss_start:.1f} rss_end_mb={rss_end:.1f} "
          f"rss_growth_mb={rss_end - rss_start:.1f} normal_client_ok={int(ok)} "
          + " ".join(f"latency_ratio_{k}={v:.2f}" for k, v in ratios.items()))
    return 0 if ok and rss_end - rss_start < 5.0 else 1


if __name__ == "__main__":
    sys.exit(main())

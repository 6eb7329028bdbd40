"""The simulated EtherCAT slave as a rig front end in this process: a veth pair whose slave end sits in a private
network namespace, the slave's raw socket opened inside it (setns on this thread only, then back), served by a
thread. The bench's master gets the other end's name. Needs root (namespaces, raw sockets)."""

from __future__ import annotations

import ctypes
import os
import socket
import subprocess
import threading
import uuid

from sim_backend.ethercat.frames import ETHERTYPE

CLONE_NEWNET = 0x40000000
NETNS_DIR = "/run/netns"


def _ip(*args: str) -> None:
    done = subprocess.run(("ip", *args), capture_output=True, text=True, timeout=10)
    if done.returncode:
        raise RuntimeError(f"ip {' '.join(args)}: {done.stderr.strip() or done.returncode}")


def _socket_in(namespace: str, iface: str) -> socket.socket:
    libc = ctypes.CDLL(None, use_errno=True)
    here = os.open("/proc/thread-self/ns/net", os.O_RDONLY)
    there = os.open(os.path.join(NETNS_DIR, namespace), os.O_RDONLY)
    try:
        if libc.setns(there, CLONE_NEWNET) != 0:
            raise OSError(ctypes.get_errno(), f"setns into {namespace}")
        try:
            sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETHERTYPE))
            sock.bind((iface, ETHERTYPE))
        finally:
            if libc.setns(here, CLONE_NEWNET) != 0:
                raise OSError(ctypes.get_errno(), "setns back")
    finally:
        os.close(here)
        os.close(there)
    return sock


class EthercatFront:
    """`master_iface` is where the bench's master opens; `stop()` removes the namespace and the pair."""

    def __init__(self, slave):
        if os.geteuid() != 0:
            raise RuntimeError("the simulated EtherCAT slave needs root: a network namespace, a veth pair and raw "
                               "sockets (docs/ethercat.md)")
        tag = uuid.uuid4().hex[:6]
        self.namespace, self.master_iface, self.slave_iface = f"dbec{tag}", f"dbm{tag}", f"dbs{tag}"
        self.slave = slave
        self._stop = threading.Event()
        self._why: str | None = None
        _ip("netns", "add", self.namespace)
        try:
            _ip("link", "add", self.master_iface, "type", "veth", "peer", "name", self.slave_iface)
            _ip("link", "set", self.slave_iface, "netns", self.namespace)
            subprocess.run(("sysctl", "-qw", f"net.ipv6.conf.{self.master_iface}.disable_ipv6=1"),
                           capture_output=True, timeout=10)
            _ip("link", "set", self.master_iface, "up")
            _ip("netns", "exec", self.namespace, "ip", "link", "set", self.slave_iface, "up")
            self.sock = _socket_in(self.namespace, self.slave_iface)
        except Exception:
            self._remove()
            raise
        self.sock.settimeout(0.002)
        self.thread = threading.Thread(target=self._serve, name="ethercat-slave", daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        try:                                  # an ESC answers in hardware; this thread at least ahead of busy loops
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(60))
        except (PermissionError, OSError, AttributeError):
            pass
        try:
            while not self._stop.is_set():
                try:
                    frame = self.sock.recv(2048)
                except socket.timeout:
                    continue
                answer = self.slave.frame(frame)
                if answer is not None:
                    self.sock.send(answer)
        except Exception as exc:              # dead() names it to the bench
            self._why = f"EtherCAT slave on {self.slave_iface}: {type(exc).__name__}: {exc}"

    def dead(self) -> str | None:
        return self._why

    def _remove(self) -> None:
        for args in (("netns", "del", self.namespace), ("link", "del", self.master_iface)):
            try:
                _ip(*args)
            except RuntimeError:
                pass

    def stop(self) -> None:
        self._stop.set()
        self.thread.join(timeout=2.0)
        self.sock.close()
        self._remove()

"""The one TOML reader keeps parsed tables by their bytes: a copy for each caller, a new parse for new bytes."""

from __future__ import annotations

import os

import drivers.contract.toml_file as toml_file
from drivers.contract.toml_file import PARSED_KEPT, parse_toml_bytes, read_toml_file

DOC = b'name = "a"\n[limits]\noverspeed_mech_rad_s = 40.0\n[[speed]]\nat_s = 0.0\nspeed_mech_rad_s = 20.0\n'


def counting_loads(monkeypatch) -> list[str]:
    calls: list[str] = []
    real = toml_file.tomllib.loads

    def loads(text: str):
        calls.append(text)
        return real(text)

    monkeypatch.setattr(toml_file.tomllib, "loads", loads)
    return calls


def test_the_same_bytes_are_parsed_once_and_every_caller_gets_a_table_of_its_own(monkeypatch):
    calls = counting_loads(monkeypatch)
    first = parse_toml_bytes(DOC + b"# one\n")
    first["limits"]["overspeed_mech_rad_s"] = -1.0      # a caller that edits what it got
    first["speed"].append({"at_s": 9.0})
    second = parse_toml_bytes(DOC + b"# one\n")
    assert len(calls) == 1
    assert second == {"name": "a", "limits": {"overspeed_mech_rad_s": 40.0},
                      "speed": [{"at_s": 0.0, "speed_mech_rad_s": 20.0}]}
    assert second["speed"] is not first["speed"]


def test_a_file_rewritten_with_the_same_size_and_timestamp_is_read_as_it_now_is(tmp_path, monkeypatch):
    calls = counting_loads(monkeypatch)
    path = tmp_path / "s.toml"
    tag = f"# {tmp_path.name}\n".encode()               # bytes no other test parsed
    path.write_bytes(b"limit = 0.5\n" + tag)
    stamp = os.stat(path)
    assert read_toml_file(path)[0] == {"limit": 0.5}
    path.write_bytes(b"limit = 0.6\n" + tag)
    os.utime(path, ns=(stamp.st_atime_ns, stamp.st_mtime_ns))
    assert os.stat(path).st_size == stamp.st_size and os.stat(path).st_mtime_ns == stamp.st_mtime_ns
    assert read_toml_file(path)[0] == {"limit": 0.6}
    assert read_toml_file(path)[0] == {"limit": 0.6}
    assert len(calls) == 2


def test_the_kept_tables_are_bounded():
    for i in range(PARSED_KEPT + 20):
        parse_toml_bytes(f"k = {i}\n".encode())
    assert len(toml_file._parsed) <= PARSED_KEPT
    assert parse_toml_bytes(f"k = {PARSED_KEPT + 19}\n".encode()) == {"k": PARSED_KEPT + 19}

"""Every bad argument of every command is one line on stderr and exit 2, never a traceback or a hang (issue 23).

Each case runs `python -m bench ...` as a subprocess, as a user or a CI job would, with a bound on its time: a connect
to something that never answers (a silent PostgreSQL, a dead Ray address) must end within its own timeout."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SCENARIO = "scenarios/pmsm/fig08-20rads-rs-step.toml"
CAMPAIGN = "campaigns/paper-seeds.toml"
CASE_TIMEOUT_S = 30.0          # the slowest bounded connect is 5 s; the interpreter's start-up is the rest


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("bad-args")
    (tmp / "binary.toml").write_bytes(bytes(range(256)) * 4)
    (tmp / "a-file").write_text("not a directory\n")
    (tmp / "dir.toml").mkdir()
    return tmp


@pytest.fixture(scope="module")
def silent_port():
    """A port that accepts TCP connections and never says a word (a hung server, a firewall's tarpit)."""
    with socket.create_server(("127.0.0.1", 0), backlog=16) as listener:
        yield listener.getsockname()[1]


@pytest.fixture(scope="module")
def dead_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]                        # closed again: nothing listens there


CASES = [
    # (id, argv with {tmp}, {silent}, {dead} placeholders[, a mark])
    ("cli-unknown-command", ["frobnicate"]),
    ("cli-unknown-option", ["--frobnicate"]),
    ("run-no-scenario", ["run"]),
    ("run-missing-file", ["run", "{tmp}/missing.toml"]),
    ("run-binary-file", ["run", "{tmp}/binary.toml"]),
    ("run-directory", ["run", "{tmp}/dir.toml"]),
    ("run-seed-not-int", ["run", SCENARIO, "--seed", "abc"]),
    ("run-rerun-mode", ["run", SCENARIO, "--rerun", "bogus"]),
    ("run-bench-missing", ["run", SCENARIO, "--bench", "{tmp}/missing-bench.toml"]),
    ("validate-no-file", ["validate"]),
    ("validate-missing-file", ["validate", "{tmp}/missing.toml"]),
    ("validate-binary-file", ["validate", "{tmp}/binary.toml"]),
    ("validate-directory", ["validate", "{tmp}/dir.toml"]),
    ("submit-no-scenario", ["submit", "--server", "http://127.0.0.1:1", "--token", "t", "--rig", "r"]),
    ("submit-non-url-server", ["submit", "--server", "not-a-url", "--token", "t", "--rig", "r", SCENARIO]),
    ("submit-port-out-of-range", ["submit", "--server", "http://127.0.0.1:99999", "--token", "t", "--rig", "r",
                                  SCENARIO]),
    ("submit-binary-file", ["submit", "--server", "http://127.0.0.1:{dead}", "--token", "t", "--rig", "r",
                            "{tmp}/binary.toml"]),
    ("submit-junit-missing-dir", ["submit", "--server", "http://127.0.0.1:{dead}", "--token", "t", "--rig", "r",
                                  "--wait", "--junit", "{tmp}/no/such/dir/junit.xml", SCENARIO]),
    ("submit-no-token", ["submit", "--server", "http://127.0.0.1:{dead}", "--rig", "r", SCENARIO]),
    ("submit-rig-and-tag", ["submit", "--server", "http://127.0.0.1:{dead}", "--token", "t", "--rig", "r",
                            "--tag", "t", SCENARIO]),
    ("submit-negative-timeout", ["submit", "--server", "http://127.0.0.1:{dead}", "--token", "t", "--rig", "r",
                                 "--wait", "--timeout", "-1", SCENARIO]),
    ("submit-unreachable", ["submit", "--server", "http://127.0.0.1:{dead}", "--token", "t", "--rig", "r",
                            SCENARIO]),
    ("token-create-bad-role", ["token", "create", "--role", "boss", "--name", "x", "--data", "{tmp}/svc"]),
    ("token-create-no-name", ["token", "create", "--role", "viewer", "--data", "{tmp}/svc"]),
    ("token-create-empty-name", ["token", "create", "--role", "viewer", "--name", " ", "--data", "{tmp}/svc"]),
    ("token-create-data-under-file", ["token", "create", "--role", "viewer", "--name", "x", "--data",
                                      "{tmp}/a-file/svc"]),
    ("token-create-silent-postgres", ["token", "create", "--role", "viewer", "--name", "x", "--db",
                                      "postgresql://u@127.0.0.1:{silent}/db"]),
    ("token-create-bad-db-url", ["token", "create", "--role", "viewer", "--name", "x", "--db", "nonsense://"]),
    ("token-revoke-2**70", ["token", "revoke", str(2**70), "--data", "{tmp}/svc"]),
    ("token-revoke-not-int", ["token", "revoke", "abc", "--data", "{tmp}/svc"]),
    ("token-revoke-zero", ["token", "revoke", "0", "--data", "{tmp}/svc"]),
    ("token-list-data-under-file", ["token", "list", "--data", "{tmp}/a-file/svc"]),
    ("serve-missing-certfile", ["serve", "--data", "{tmp}/svc", "--ssl-certfile", "{tmp}/missing.pem"]),
    ("serve-missing-keyfile", ["serve", "--data", "{tmp}/svc", "--ssl-keyfile", "{tmp}/missing.key"]),
    ("serve-unknown-option", ["serve", "--frobnicate"]),
    ("serve-port-not-int", ["serve", "--port", "http"]),
    ("serve-port-99999", ["serve", "--data", "{tmp}/svc", "--port", "99999"]),
    ("serve-lease-ttl-negative", ["serve", "--data", "{tmp}/svc", "--lease-ttl", "-1"]),
    ("serve-lease-ttl-nan", ["serve", "--data", "{tmp}/svc", "--lease-ttl", "nan"]),
    ("serve-max-parallel-negative", ["serve", "--data", "{tmp}/svc", "--max-parallel", "-1"]),
    ("campaign-missing-file", ["campaign", "{tmp}/missing.toml"]),
    ("campaign-binary-file", ["campaign", "{tmp}/binary.toml"]),
    ("campaign-workers-zero", ["campaign", CAMPAIGN, "--workers", "0"]),
    ("campaign-engine", ["campaign", CAMPAIGN, "--engine", "spark"]),
    ("campaign-ray-dead-address", ["campaign", CAMPAIGN, "--engine", "ray", "--address", "127.0.0.1:{dead}",
                                   "--out", "{tmp}/camp"]),
    ("campaign-ray-bad-address", ["campaign", CAMPAIGN, "--engine", "ray", "--address", "nowhere",
                                  "--out", "{tmp}/camp2"]),
    ("probe-no-bench", ["probe"]),
    ("probe-missing-bench", ["probe", "--bench", "{tmp}/missing.toml"]),
    ("probe-binary-bench", ["probe", "--bench", "{tmp}/binary.toml"]),
    ("show-missing-dir", ["show", "{tmp}/no-run"]),
    ("evaluate-missing-dir", ["evaluate", "{tmp}/no-run"]),
    ("sim-serve-missing-config", ["sim", "serve", "--config", "{tmp}/missing.toml"]),
    ("design-check-missing", ["design-check", "{tmp}/missing.toml"]),
    ("export-missing-dir", ["export", "{tmp}/no-run", "--format", "csv"]),
    ("export-no-format", ["export", "{tmp}/no-run"]),
    ("export-bad-format", ["export", "{tmp}/no-run", "--format", "xls"]),
    ("compare-missing-dirs", ["compare", "{tmp}/no-run", "{tmp}/no-run-either"]),
    ("compare-one-dir", ["compare", "{tmp}/no-run"]),
    ("twin-missing-dir", ["twin", "{tmp}/no-run"]),
    ("twin-missing-motor", ["twin", "{tmp}/no-run", "--motor", "{tmp}/missing-motor.toml"]),
    ("report-missing-dir", ["report", "{tmp}/no-run"]),
    ("report-missing-suites", ["report", "{tmp}/no-run", "--suites", "{tmp}/missing-suites.toml"]),
]


@pytest.mark.parametrize("argv", [pytest.param(c[1], id=c[0], marks=c[2:]) for c in CASES])
def test_bad_argument_is_one_line_and_exit_2(argv, files, silent_port, dead_port):
    args = [a.format(tmp=files, silent=silent_port, dead=dead_port) for a in argv]
    env = {k: v for k, v in os.environ.items() if k not in ("DRIVEBENCH_TOKEN", "DRIVEBENCH_SERVER", "DRIVEBENCH_DB",
                                                            "DRIVEBENCH_DEBUG")}
    done = subprocess.run([sys.executable, "-m", "bench", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=CASE_TIMEOUT_S, env={**env, "COLUMNS": "200"}, stdin=subprocess.DEVNULL)
    lines = done.stderr.splitlines()
    assert done.returncode == 2, (done.returncode, done.stderr)
    assert len(lines) == 1, done.stderr
    assert "Traceback" not in done.stderr + done.stdout
    assert lines[0].strip(), done.stderr


def test_the_table_covers_every_command():
    from bench.faces.cli import cli

    covered = {c[1][0] for c in CASES}
    assert set(cli.commands) - {"list"} <= covered               # list takes no argument to get wrong

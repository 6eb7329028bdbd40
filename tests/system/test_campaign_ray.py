"""Campaigns on a real two-node Ray cluster on this machine (`ray start --head` plus a second node that owns a rig
resource): points bound to a rig run one at a time on the rig's node; simulated points spread over both nodes."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

ray = pytest.importorskip("ray", reason="ray is not installed (pip install -e \".[ray]\")")

from bench.faces.campaign import load_campaign, points  # noqa: E402
from bench.faces.campaign_run import run_campaign, write_results  # noqa: E402
from tests.service_fixtures import free_port  # noqa: E402
from tests.sim_process import EDS, SCENARIO, serve_pmsm, sim_bench  # noqa: E402

RAY = Path(sys.executable).with_name("ray")
RIG = "served-rig"


def _start_node(*args: str, temp_dir: str) -> subprocess.Popen:
    """`ray start ... --block`: the node lives as long as this process (SIGTERM takes it down), whatever else runs
    Ray on the machine."""
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0"}
    return subprocess.Popen([str(RAY), "start", "--block", "--node-ip-address", "127.0.0.1",
                             "--disable-usage-stats", *args], env=env, cwd=temp_dir,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)


@pytest.fixture
def cluster(monkeypatch):
    if not RAY.exists():
        pytest.skip(f"no ray command beside {sys.executable}")
    # one auth mode for every process of this loopback cluster: a token left in ~/.ray by an earlier local
    # ray.init (Ray 2.60 writes one) made the head require it while `ray status` sent none
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    temp_dir = tempfile.mkdtemp(prefix="ray", dir="/tmp")   # Ray's socket paths must stay short
    port = free_port()
    address = f"127.0.0.1:{port}"
    head = _start_node("--head", "--num-cpus", "1", "--port", str(port), "--include-dashboard=false",
                       "--temp-dir", temp_dir, temp_dir=temp_dir)
    nodes = [head]
    try:
        deadline = time.monotonic() + 90
        second_started = False
        while True:
            assert head.poll() is None, "ray start --head exited"
            if not second_started:
                probe = subprocess.run([str(RAY), "status", "--address", address], capture_output=True, text=True,
                                       timeout=60)
                if probe.returncode == 0:
                    # the rig's host: one CPU for the rig's runs, one for simulated points
                    nodes.append(_start_node("--address", address, "--num-cpus", "2",
                                             "--resources", json.dumps({f"rig:{RIG}": 1}), temp_dir=temp_dir))
                    second_started = True
            else:
                status = subprocess.run([str(RAY), "status", "--address", address], capture_output=True, text=True,
                                        timeout=60).stdout
                if f"rig:{RIG}" in status and status.count("node_") >= 2:
                    break
            assert time.monotonic() < deadline, "the two-node Ray cluster did not come up within 90 s"
            time.sleep(1.0)
        yield address
    finally:
        if ray.is_initialized():
            ray.shutdown()
        for proc in reversed(nodes):
            _stop(proc)
        shutil.rmtree(temp_dir, ignore_errors=True)


def test_rig_points_hold_their_rig_and_simulated_points_spread_over_both_nodes(tmp_path, cluster):
    sim_proc, endpoints = serve_pmsm(tmp_path)          # the "real rig": a served simulator, one bench at a time
    try:
        # The drills run in wall time beside three runs and two Ray nodes on two cores: a margin for the host, not
        # for the drive (tests/drivers/test_comm_loss_drill.py holds the default margins: 200 ms drive, 100 ms load).
        # Under that load a point was once refused here by a drill that answered late.
        rig_bench = sim_bench(
            tmp_path, RIG, 'served_by = "drivebench sim serve"\n',   # lockstep without [services]: say who serves
            f'transport = "canopen"\ninterface = "socketcand"\nchannel = "can0@127.0.0.1:{endpoints["socketcand"]}"\n'
            f'node_id = 1\neds = "{EDS}"\nsdo_timeout_s = 5.0\ndrill_margin_ms = 2000\n',
            f'port = {endpoints["modbus"]}\ndrill_margin_ms = 2000')
        simulated_bench = sim_bench(tmp_path, "simulated", '[services]\nstart = "sim_backend.rig:start"\n',
                                     f'transport = "canopen"\ninterface = "virtual"\nchannel = "x"\nnode_id = 1\n'
                                     f'eds = "{EDS}"\nsdo_timeout_s = 5.0\n', "port = 0")
        # the 1.5 s scenario of test_transports_agree (speed step, load step, R_s injection, two criteria)
        (tmp_path / "scenario-on-rig.toml").write_text(SCENARIO.format(bench=rig_bench, seed=1))
        (tmp_path / "scenario-simulated.toml").write_text(SCENARIO.format(bench=simulated_bench, seed=1))
        (tmp_path / "campaign.toml").write_text('schema_version = 1\nname = "ray-two-nodes"\n'
                                                'scenarios = ["scenario-on-rig.toml", "scenario-simulated.toml"]\n'
                                                'seeds = [1, 2, 3, 4]\n[acceptance]\nrule = "every_run"\n')
        campaign = load_campaign(tmp_path / "campaign.toml")
        assert [p.rig for p in points(campaign, tmp_path / "out")] == [RIG] * 4 + [None] * 4
        rows = run_campaign(campaign, tmp_path / "out", engine="ray", address=cluster)
        rig_nodes = {n["NodeID"] for n in ray.nodes() if n["Alive"] and f"rig:{RIG}" in n["Resources"]}
        all_nodes = {n["NodeID"] for n in ray.nodes() if n["Alive"]}
    finally:
        sim_proc.send_signal(signal.SIGINT)
        sim_proc.wait(30)
    assert len(rows) == 8 and len(all_nodes) == 2 and len(rig_nodes) == 1
    assert [r["verdict"] for r in rows] == ["pass"] * 8, "\n".join(      # each point's whole error line
        f"{Path(r['scenario']).name} seed {r.get('seed')}: {r['verdict']}: {r['error']}" for r in rows)
    on_rig = sorted((r for r in rows if r["rig"] == RIG), key=lambda r: r["started_unix"])
    assert {r["node"] for r in on_rig} == rig_nodes                      # only the node that owns the rig
    for before, after in zip(on_rig, on_rig[1:]):                       # never two runs on the rig at once
        assert before["ended_unix"] <= after["started_unix"], (before, after)
    simulated = [r for r in rows if r["rig"] is None]
    assert {r["node"] for r in simulated} == all_nodes                   # spread over both nodes
    result = write_results(campaign, tmp_path / "out", rows)
    assert result["accepted"] and result["runs"] == 8

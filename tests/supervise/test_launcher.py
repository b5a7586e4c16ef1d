"""``crosspath up``: command lines, ports, and real runs of every daemon as its own process."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from services.model.scenario import load_scenario
from services.model.types import RunMode
from services.sim.harness import TRACE_FIELDS, SimOptions, simulate
from services.supervise.launcher import (
    Endpoints,
    actor_commands,
    free_ports,
    loopback_endpoints,
    node_order,
)

REPO = Path(__file__).resolve().parents[2]
PAPER = REPO / "scenarios" / "paper-blind-intersection.toml"
SPEED = 2.0


def up_command(tmp_path: Path, *extra: str) -> list[str]:
    return [
        sys.executable, "-m", "services.cli.main", "up", str(PAPER),
        "--run-dir", str(tmp_path / "run"), *extra,
    ]  # fmt: skip


def child_env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(REPO)}


def children(tmp_path: Path) -> dict[str, Any]:
    path = tmp_path / "run" / "children.json"
    data: dict[str, Any] = json.loads(path.read_text()) if path.exists() else {}
    return data


def gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


# --------------------------------------------------------------------------- pure parts


def test_actor_commands_order_listen_and_connect() -> None:
    scenario = load_scenario(PAPER)
    nodes = node_order(scenario, RunMode.RSU)
    assert nodes == ["monitor", "rsu1", "A", "B"]
    assert node_order(scenario, RunMode.FP_ONLY) == ["monitor", "A", "B"]
    eps = {
        n: Endpoints(f"udp/10.231.1.{i + 1}:7447", f"tcp/10.231.2.{i + 1}:7447")
        for i, n in enumerate(nodes)
    }
    cmds = actor_commands(
        PAPER, "rsu", "slot", 3, 2.0, eps, json_out=Path("out.json"), run_id="r1", python="py"
    )
    assert list(cmds) == nodes
    mon, rsu, a, b = (cmds[n] for n in nodes)
    assert mon[:4] == ["py", "-m", "services.cli.main", "monitor"]
    for flag, value in (
        ("--mode", "rsu"),
        ("--policy", "slot"),
        ("--seed", "3"),
        ("--speed", "2.0"),
        ("--run-id", "r1"),
    ):
        assert mon[mon.index(flag) + 1] == value
    assert mon[mon.index("--json") + 1] == str(Path("out.json").resolve())
    assert rsu[3:6] == ["rsu", "--scenario", str(PAPER)] and rsu[rsu.index("--id") + 1] == "rsu1"
    assert b[3] == "vehicle" and b[b.index("--id") + 1] == "B"

    def values(argv: list[str], flag: str) -> list[str]:
        return [argv[i + 1] for i, item in enumerate(argv) if item == flag]

    assert values(mon, "--connect") == []
    assert values(a, "--listen") == ["udp/10.231.1.3:7447", "tcp/10.231.2.3:7447"]
    assert values(b, "--connect") == [
        "udp/10.231.1.1:7447", "tcp/10.231.2.1:7447",
        "udp/10.231.1.2:7447", "tcp/10.231.2.2:7447",
        "udp/10.231.1.3:7447", "tcp/10.231.2.3:7447",
    ]  # fmt: skip
    # every node opens its pair links one after another (connect_in_turn)
    for argv in (mon, rsu, a, b):
        assert "zenoh.connect_in_turn=true" in values(argv, "--set")
    # a monitor started after the others (lab up) is connected to in the background
    later = actor_commands(PAPER, "rsu", "slot", 3, 2.0, eps, started_later=["monitor"])
    assert values(later["B"], "--connect") == [
        "udp/10.231.1.1:7447#exit_on_failure=false", "tcp/10.231.2.1:7447#exit_on_failure=false",
        "udp/10.231.1.2:7447", "tcp/10.231.2.2:7447",
        "udp/10.231.1.3:7447", "tcp/10.231.2.3:7447",
    ]  # fmt: skip


def test_actor_commands_refuse_missing_endpoints_and_bad_locators() -> None:
    with pytest.raises(ValueError, match="no endpoints for rsu1"):
        actor_commands(
            PAPER, RunMode.RSU, "paper", 0, 1.0, loopback_endpoints(["monitor", "A", "B"])
        )
    fp_only = actor_commands(
        PAPER, RunMode.FP_ONLY, "paper", 0, 1.0, loopback_endpoints(["monitor", "A", "B"])
    )
    assert list(fp_only) == ["monitor", "A", "B"]
    with pytest.raises(ValueError, match="expected udp"):
        Endpoints("tcp/127.0.0.1:1", "tcp/127.0.0.1:2")
    with pytest.raises(ValueError, match="expected tcp"):
        Endpoints("udp/127.0.0.1:1", "tcp/127.0.0.1")


def test_free_ports_are_distinct() -> None:
    pairs = free_ports(8)
    udp = [u for u, _ in pairs]
    tcp = [t for _, t in pairs]
    assert len(set(udp)) == 8 and len(set(tcp)) == 8 and all(p > 0 for p in udp + tcp)


def test_up_refuses_bad_arguments(tmp_path: Path) -> None:
    from services.cli.main import build_parser

    args = build_parser().parse_args(["up", str(tmp_path / "missing.toml")])
    assert args._run(args) == 2
    with pytest.raises(SystemExit) as exc:  # refused while parsing, before any process
        build_parser().parse_args(["up", str(PAPER), "--speed", "0"])
    assert exc.value.code == 2


# --------------------------------------------------------------------------- real runs


@pytest.mark.daemons
def test_up_runs_the_paper_scenario_like_the_in_process_harness(tmp_path: Path) -> None:
    out, trace = tmp_path / "result.json", tmp_path / "trace.csv"
    proc = subprocess.run(
        up_command(tmp_path, "--mode", "rsu", "--seed", "2", "--speed", str(SPEED),
                   "--json", str(out), "--trace", str(trace), "--timeout", "120"),
        cwd=REPO, env=child_env(), capture_output=True, text=True, timeout=180,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    result = json.loads(out.read_text())
    reference = simulate(load_scenario(PAPER), SimOptions(mode=RunMode.RSU, seed=2))
    assert result["harness"] == "daemons" and result["mode"] == "rsu"
    assert result["collisions"] == 0
    assert result["start_times"] == reference.start_times
    for vid, ref in reference.vehicles.items():
        got = result["vehicles"][vid]
        assert got["finished"], vid
        assert got["passing_time_s"] == pytest.approx(ref.passing_time_s, rel=0.10), vid
    # --trace: the per-step CSV of ``sim --trace``, not in the JSON
    assert "trace" not in result and "trace_fields" not in result
    with trace.open() as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == list(TRACE_FIELDS)
    steps = {vid: [r for r in rows if r["vehicle"] == vid] for vid in ("A", "B")}
    for vid, mine in steps.items():
        assert len(mine) >= 0.9 * result["sim_s"] * 20, vid  # every physics step (20 Hz)
        assert max(float(r["speed"]) for r in mine) > 10.0
    assert {r["mode"] for r in rows} >= {"AUTO", "C_FAST"}  # the RSU coordinated
    network = result["network"]
    for stream in ("fp", "ap", "cmd", "beacon"):
        assert stream in network, stream
    for entry in (network[s] for s in ("fp", "ap", "cmd", "beacon")):
        for key in (
            "msgs",
            "bytes",
            "kbps_per_vehicle",
            "latency_ms_p50",
            "latency_ms_p99",
            "delivery_ratio",
        ):
            assert key in entry
    assert network["fp"]["delivery_ratio"] > 0.9
    assert network["fp"]["malformed"] == 0
    assert 0 < network["fp"]["latency_ms_p50"] <= network["fp"]["latency_ms_p99"]
    assert network["total_kbps_per_vehicle"] > network["fp"]["kbps_per_vehicle"] > 0
    assert sorted(result["final_stats"]) == ["A", "B", "rsu1"]
    # the table went to stdout, and no child is left
    assert "passing [s]" in proc.stdout and "kbps/veh" in proc.stdout
    pids = [c["pid"] for c in children(tmp_path).values()]
    assert len(pids) == 4 and all(gone(pid) for pid in pids)


def start_up_and_wait_mid_run(tmp_path: Path) -> tuple[subprocess.Popen[str], dict[str, int]]:
    """``crosspath up`` in the background, 2 s into its run; its children's pids."""
    proc = subprocess.Popen(
        up_command(tmp_path, "--mode", "rsu", "--speed", str(SPEED)),
        cwd=REPO, env=child_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    monitor_log = tmp_path / "run" / "monitor.log"
    deadline = time.monotonic() + 60.0
    while not (monitor_log.exists() and "starting run" in monitor_log.read_text()):
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            raise AssertionError(f"the run did not start: {proc.communicate()}")
        time.sleep(0.1)
    time.sleep(2.0)  # mid-run
    pids = {node: int(c["pid"]) for node, c in children(tmp_path).items()}
    assert sorted(pids) == ["A", "B", "monitor", "rsu1"]
    assert not any(gone(pid) for pid in pids.values())
    return proc, pids


@pytest.mark.daemons
def test_sigterm_to_up_mid_run_leaves_no_process(tmp_path: Path) -> None:
    proc, pids = start_up_and_wait_mid_run(tmp_path)
    try:
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 128 + signal.SIGTERM, out + err
    assert "interrupted by SIGTERM" in err
    assert all(gone(pid) for pid in pids.values())
    # every daemon stopped gracefully (first signal), none was killed
    for node in ("monitor", "rsu1", "A", "B"):
        log = (tmp_path / "run" / f"{node}.log").read_text()
        assert "SIGTERM received: stopping" in log, node
        assert "zenoh session closed" in log, node


@pytest.mark.daemons
def test_a_crashing_car_fails_the_run_clearly_and_leaves_no_process(tmp_path: Path) -> None:
    proc, pids = start_up_and_wait_mid_run(tmp_path)
    try:
        os.kill(pids["B"], signal.SIGKILL)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 1, out + err
    assert "B exited during the run with code -9" in err
    assert "run failed: B lost: its liveliness token disappeared" in err
    assert "--- B (exit -9), last lines of" in err
    result = json.loads((tmp_path / "run" / "result.json").read_text())
    assert result["error"].startswith("B lost")
    assert all(gone(pid) for pid in pids.values())

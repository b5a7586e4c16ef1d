"""The lab's namespaces: plan (pure), connectivity, commands, clean-up and recovery."""

from __future__ import annotations

import ipaddress
import json
import signal
import subprocess
import time
from pathlib import Path

import pytest

from services.supervise.lab.netns import (
    AIR_NET,
    WIRE_NET,
    Lab,
    LabError,
    LabPlan,
    Net,
    Role,
    command,
    down_all,
    list_namespaces,
    tool,
)
from tests.supervise.lab.conftest import PY, new_lab_name, tcp_transfer, udp_transfer

# ----------------------------------------------------------------------------- plan (no root)


def test_plan_names_addresses_and_interfaces() -> None:
    plan = LabPlan.build("demo", cars=["A", "B"], rsus=["rsu1"])
    assert plan.names == ("A", "B", "rsu1", "monitor")
    assert [n.role for n in plan.nodes] == [Role.CAR, Role.CAR, Role.RSU, Role.MONITOR]
    assert plan.hub == "cpl-demo-hub"
    assert plan.namespaces == (
        "cpl-demo-hub",
        "cpl-demo-A",
        "cpl-demo-B",
        "cpl-demo-rsu1",
        "cpl-demo-monitor",
    )
    assert [n.air_addr for n in plan.nodes] == [f"10.231.1.{i}" for i in (1, 2, 3, 4)]
    assert [n.wire_addr for n in plan.nodes] == [f"10.231.2.{i}" for i in (1, 2, 3, 4)]
    assert plan.node("B").hub_air_if == "cpla1"
    assert plan.node("B").hub_wire_if == "cplw1"
    assert plan.air_broadcast == "10.231.1.255"
    assert plan.by_role(Role.RSU) == (plan.node("rsu1"),)
    assert plan.multicast is Net.AIR


def test_plan_of_the_largest_lab_keeps_linux_limits() -> None:
    cars = [f"car{i}" for i in range(249)]
    plan = LabPlan.build("big", cars=cars, rsus=["rsu"], monitor=None)
    ifnames = {n.hub_air_if for n in plan.nodes} | {n.hub_wire_if for n in plan.nodes}
    assert len(ifnames) == 2 * 250
    assert max(len(i) for i in ifnames) <= 15
    assert plan.nodes[-1].air_addr == "10.231.1.250"
    addrs = [n.air_addr for n in plan.nodes] + [n.wire_addr for n in plan.nodes]
    assert len(set(addrs)) == 500
    assert all(ipaddress.IPv4Address(n.air_addr) in AIR_NET for n in plan.nodes)
    assert all(ipaddress.IPv4Address(n.wire_addr) in WIRE_NET for n in plan.nodes)


def test_plan_round_trips_through_json() -> None:
    plan = LabPlan.build("x1", cars=["a"], rsus=["r1", "r2"], monitor="mon", multicast=Net.WIRE)
    data = json.loads(json.dumps(plan.to_json()))
    assert LabPlan.from_json(data) == plan
    data["nodes"][0]["air_addr"] = "10.231.1.99"
    with pytest.raises(ValueError, match="does not match"):
        LabPlan.from_json(data)
    with pytest.raises(ValueError, match="malformed"):
        LabPlan.from_json({"version": 1})


@pytest.mark.parametrize(
    ("lab", "cars", "rsus", "monitor", "match"),
    [
        ("", ["a"], [], None, "bad lab name"),
        ("has-dash", ["a"], [], None, "bad lab name"),
        ("UPPER", ["a"], [], None, "bad lab name"),
        ("waytoolong123", ["a"], [], None, "bad lab name"),
        ("ok", [], [], None, "at least one node"),
        ("ok", ["a", "a"], [], None, "twice"),
        ("ok", ["a"], ["a"], None, "twice"),
        ("ok", ["hub"], [], None, "reserved"),
        ("ok", ["-a"], [], None, "bad node name"),
        ("ok", ["a b"], [], None, "bad node name"),
        ("ok", ["a/b"], [], None, "bad node name"),
        ("ok", [f"c{i}" for i in range(251)], [], None, "at most 250"),
    ],
)
def test_plan_rejects_bad_input(
    lab: str, cars: list[str], rsus: list[str], monitor: str | None, match: str
) -> None:
    with pytest.raises(ValueError, match=match):
        LabPlan.build(lab, cars=cars, rsus=rsus, monitor=monitor)


def test_unknown_node_is_a_key_error_naming_the_nodes() -> None:
    plan = LabPlan.build("k", cars=["a"], monitor=None)
    with pytest.raises(KeyError, match="nodes: a"):
        plan.node("zz")


@pytest.mark.parametrize("prefix", ["", "cpl", "foo-", "cpl-a b", "cpl-*"])
def test_down_all_refuses_foreign_prefixes(prefix: str) -> None:
    with pytest.raises(ValueError, match="prefix"):
        down_all(prefix)


def test_lab_without_state_is_not_up(tmp_path: Path) -> None:
    lab = Lab("nostate", state_dir=tmp_path)
    with pytest.raises(LabError, match="not up"):
        _ = lab.plan
    with pytest.raises(LabError, match="not up"):
        lab.air_addr("a")


# ----------------------------------------------------------------------------- real lab (root)


def _root_links() -> str:
    return command([tool("ip"), "-o", "link"]).stdout


def _root_addrs() -> str:
    return command([tool("ip"), "-o", "addr"]).stdout


def test_lab_is_built_as_planned_and_adds_nothing_to_the_root_namespace(lab3: Lab) -> None:
    plan = lab3.plan
    assert set(plan.namespaces) <= set(list_namespaces(plan.ns_prefix))
    assert lab3.is_up()
    assert json.loads(lab3.state_path.read_text())["lab"] == lab3.name
    assert "cpl" not in _root_links()
    assert "10.231." not in _root_addrs()
    for node in plan.nodes:
        brief = lab3.ip(node.name, ["-br", "-4", "addr"])
        assert f"{node.air_addr}/24" in brief
        assert f"{node.wire_addr}/24" in brief
        assert "127.0.0.1/8" in brief  # loopback up: Zenoh needs it
        routes = lab3.ip(node.name, ["route"])
        assert "224.0.0.0/4 dev air0" in routes
        assert "default" not in routes  # no way out of the lab
    ports = command([tool("ip"), "-n", plan.hub, "-o", "link", "show", "master", "cplair"]).stdout
    assert sorted(n.hub_air_if for n in plan.nodes) == sorted(
        line.split(":")[1].strip().split("@")[0] for line in ports.splitlines()
    )


def test_udp_on_the_air_and_tcp_on_the_wire(lab3: Lab) -> None:
    sent, got = udp_transfer(lab3, "a", ["b"], dst=lab3.air_addr("b"), count=100)
    assert sent == 100
    assert sorted(got["b"].seqs) == list(range(100))
    assert tcp_transfer(lab3, "a", "r", lab3.wire_addr("r"), 200_000, port=40101) == 200_000
    # TCP works on the air too when there are no faults.
    assert tcp_transfer(lab3, "b", "a", lab3.air_addr("a"), 50_000, port=40102) == 50_000


def test_air_broadcast_reaches_every_other_node(lab3: Lab) -> None:
    plan = lab3.plan
    sent, got = udp_transfer(lab3, "a", ["b", "r"], dst=plan.air_broadcast, count=50)
    assert sent == 50
    assert sorted(got["b"].seqs) == list(range(50))
    assert sorted(got["r"].seqs) == list(range(50))


def test_run_reports_failures_and_timeouts(lab3: Lab) -> None:
    done = lab3.run("a", [PY, "-c", "print(42)"], timeout=10)
    assert done.stdout.strip() == b"42"
    with pytest.raises(LabError, match="exit status: 3") as info:
        lab3.run("a", [PY, "-c", "import sys; sys.stderr.write('boom'); sys.exit(3)"], timeout=10)
    assert info.value.returncode == 3
    assert "boom" in info.value.stderr
    assert lab3.run("a", [PY, "-c", "raise SystemExit(4)"], timeout=10, check=False).returncode == 4
    with pytest.raises(LabError, match="timed out"):
        lab3.run("a", ["sleep", "5"], timeout=0.3)
    with pytest.raises(LabError, match="no node"):
        lab3.run("zz", ["true"], timeout=5)
    with pytest.raises(ValueError, match="empty"):
        lab3.exec("a", [])


def test_exec_adds_env_and_runs_in_the_node_namespace(lab3: Lab) -> None:
    proc = lab3.exec(
        "b",
        [PY, "-c", "import os,socket; print(os.environ['CP_X'], os.environ['PATH'] != '')"],
        env={"CP_X": "hello"},
        stdout=subprocess.PIPE,
    )
    out, _ = proc.communicate(timeout=10)
    assert out.split() == [b"hello", b"True"]
    sleeper = lab3.exec("b", ["sleep", "30"])
    try:
        assert sleeper.pid in lab3.pids("b")  # ip netns exec execs: the pid is the command's
        assert sleeper.pid not in lab3.pids("a")
    finally:
        sleeper.kill()
        sleeper.wait(timeout=5)


def _alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def _wait_dead(pid: int, seconds: float = 5.0) -> bool:
    end = time.monotonic() + seconds
    while _alive(pid) and time.monotonic() < end:
        time.sleep(0.02)
    return not _alive(pid)


def test_down_removes_every_namespace_process_and_the_state_file(lab_ready: None) -> None:
    lab = Lab(new_lab_name())
    plan = LabPlan.build(lab.name, cars=["a", "b"], rsus=["r"])
    lab.up(plan)
    # A process that ignores SIGTERM must still go (SIGKILL after the grace period).
    stubborn = lab.exec(
        "r",
        [
            PY,
            "-c",
            "import signal,time; signal.signal(signal.SIGTERM, signal.SIG_IGN); "
            "print('ready', flush=True); time.sleep(60)",
        ],
        stdout=subprocess.PIPE,
    )
    assert stubborn.stdout is not None
    assert stubborn.stdout.readline().strip() == b"ready"
    lab.exec("a", ["sleep", "60"])
    lab.down(grace=0.3)
    assert stubborn.wait(timeout=5) == -signal.SIGKILL
    assert list_namespaces(plan.ns_prefix) == []
    assert not lab.state_path.exists()
    assert "cpl" not in _root_links()
    lab.down()  # idempotent


_CRASHING_CONTROLLER = r"""
import sys
from services.supervise.lab.netns import Lab, LabPlan
lab = Lab(sys.argv[1])
lab.up(LabPlan.build(lab.name, cars=["a", "b"], rsus=["r"]))
p = lab.exec("a", ["sleep", "60"])
print(p.pid, flush=True)
sys.stdin.read()
"""


def test_up_and_down_work_after_the_controller_was_killed(lab_ready: None) -> None:
    name = new_lab_name()
    controller = subprocess.Popen(
        [PY, "-c", _CRASHING_CONTROLLER, name],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        cwd=Path(__file__).resolve().parents[3],
    )
    assert controller.stdout is not None
    orphan = int(controller.stdout.readline())
    controller.kill()
    controller.wait(timeout=5)
    lab = Lab(name)  # a new process knows the lab from its state file
    assert lab.plan.names == ("a", "b", "r", "monitor")
    assert orphan in lab.pids("a")
    plan = LabPlan.build(name, cars=["a", "b"], monitor=None)
    lab.up(plan)  # cleans the leftovers of the same name first
    assert _wait_dead(orphan)
    assert list_namespaces(plan.ns_prefix) == sorted(plan.namespaces)
    sent, got = udp_transfer(lab, "a", ["b"], dst=lab.air_addr("b"), count=10)
    assert sorted(got["b"].seqs) == list(range(sent))
    lab.down()
    assert list_namespaces(plan.ns_prefix) == []


def test_up_works_over_a_half_made_lab_and_a_corrupt_state_file(lab_ready: None) -> None:
    lab = Lab(new_lab_name())
    prefix = f"cpl-{lab.name}-"
    for ns in (f"{prefix}hub", f"{prefix}stale"):
        command([tool("ip"), "netns", "add", ns])
    command([tool("ip"), "-n", f"{prefix}hub", "link", "add", "cplair", "type", "bridge"])
    lab.state_path.parent.mkdir(parents=True, exist_ok=True)
    lab.state_path.write_text("{not json")
    with pytest.raises(LabError, match="cannot read lab state"):
        _ = lab.plan
    plan = LabPlan.build(lab.name, cars=["a", "b"], monitor=None)
    try:
        lab.up(plan)
        assert list_namespaces(prefix) == sorted(plan.namespaces)  # "stale" is gone
        assert Lab(lab.name).plan == plan
        sent, got = udp_transfer(lab, "a", ["b"], dst=lab.air_addr("b"), count=20)
        assert len(got["b"].seqs) == sent == 20
    finally:
        lab.down()
    assert list_namespaces(prefix) == []


def test_failed_up_leaves_nothing(lab_ready: None, monkeypatch: pytest.MonkeyPatch) -> None:
    lab = Lab(new_lab_name())
    plan = LabPlan.build(lab.name, cars=["a"], monitor=None)

    def broken(self: Lab, plan: LabPlan) -> None:
        command([tool("ip"), "netns", "add", plan.hub])
        raise KeyboardInterrupt  # Ctrl-C in the middle of up

    monkeypatch.setattr(Lab, "_build", broken)
    with pytest.raises(KeyboardInterrupt):
        lab.up(plan)
    assert list_namespaces(plan.ns_prefix) == []
    assert not lab.state_path.exists()


def test_down_all_removes_only_the_given_prefix(lab3: Lab, lab_ready: None) -> None:
    other = Lab(new_lab_name())
    other.up(LabPlan.build(other.name, cars=["a"], monitor=None))
    removed = down_all(f"cpl-{other.name}-")
    assert sorted(removed) == [f"cpl-{other.name}-a", f"cpl-{other.name}-hub"]
    assert list_namespaces(f"cpl-{other.name}-") == []
    assert not other.state_path.exists()
    assert lab3.is_up()  # the other lab of this session is untouched

"""The network lab with mutual TLS (issue 13) and with flow scenarios (issue 12).

A TLS lab run (the default) with three intruders in the monitor's namespace while the
run goes: a plain Zenoh peer (UDP and TCP to every node), one with a TLS certificate of
another CA, and, as the control that shows the intruder could see traffic at all, one
with a certificate of the run's own CA. Only the last joins; the run is unharmed. Then a
small flow scenario (12 cars in host processes) runs in the lab.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from services.edge.tls import make_tls, tls_options
from services.model.types import RunMode
from services.supervise.lab.netns import Lab
from services.supervise.lab.runner import QUIC_DATAGRAMS, TCP_PORT, UDP_PORT, run_lab
from tests.daemons.test_daemons import PAPER
from tests.supervise.lab.conftest import new_lab_name
from tests.supervise.lab.test_lab_run import _check_separate_and_routed, _gone

REPO = Path(__file__).resolve().parents[3]
SMALL_FLOWS = REPO / "tests" / "data" / "four-way-flows-small.toml"
FLOWS = ("we", "ew", "sn", "ns")
FLOW_SIM_S = 15.0
"""Run seconds of the flow test."""
LISTEN_S = 4.0
"""How long each intruder listens [wall s]."""

_INTRUDERS = r"""
import json, sys, time
import zenoh
spec, seconds = json.loads(sys.argv[1]), float(sys.argv[2])
live = {}
for label, conf in spec.items():
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("connect/endpoints", json.dumps(conf["connect"]))
    c.insert_json5("listen/endpoints", "[]")  # else a peer listens on tcp/[::]:0
    c.insert_json5("transport/unicast/max_links", "2")
    for k, v in conf["options"].items():
        c.insert_json5(k, json.dumps(v))
    session = zenoh.open(c)
    got = []
    sub = session.declare_subscriber("crosspath/**", lambda s, got=got: got.append(1))
    live[label] = (session, sub, got)
time.sleep(seconds)
out = {}
for label, (session, sub, got) in live.items():
    out[label] = {"peers": len(list(session.info.peers_zid())), "samples": len(got)}
    sub.undeclare()
    session.close()
print(json.dumps(out), flush=True)
"""


class Intruders(threading.Thread):
    """Once the run has started, three Zenoh peers try to join it from the monitor's
    namespace (module docstring); :attr:`found` says what each saw."""

    def __init__(self, name: str, run_dir: Path, foreign: Path) -> None:
        super().__init__(daemon=True)
        self.name_ = name
        self.run_dir = run_dir
        self.foreign = foreign
        self.found: dict[str, dict[str, int]] = {}
        self.error = ""

    def run(self) -> None:
        try:
            self._run()
        except Exception as exc:  # reported by the test
            self.error = repr(exc)

    def _run(self) -> None:
        deadline = time.monotonic() + 60.0
        while not (self.run_dir / "start.json").exists():
            if time.monotonic() > deadline:
                self.error = "the run did not start"
                return
            time.sleep(0.1)
        lab = Lab(self.name_)
        nodes = [n.name for n in lab.plan.nodes if n.name != "monitor"]
        air = [f"{lab.air_addr(n)}:{UDP_PORT}" for n in nodes]
        wire = [f"{lab.wire_addr(n)}:{TCP_PORT}" for n in nodes]
        keys = self.run_dir / "keys"
        make_tls(keys, ["insider"])  # the run's own CA: the control
        make_tls(self.foreign, ["insider"])  # another CA
        secure = [f"quic/{a}{QUIC_DATAGRAMS}" for a in air] + [f"tls/{w}" for w in wire]
        spec: dict[str, dict[str, Any]] = {
            "plain": {
                "connect": [f"udp/{a}" for a in air] + [f"tcp/{w}" for w in wire],
                "options": {},
            },
            "foreign_ca": {"connect": secure, "options": tls_options(self.foreign, "insider")},
            "insider": {"connect": secure, "options": tls_options(keys, "insider")},
        }
        done = lab.run(
            "monitor",
            [sys.executable, "-c", _INTRUDERS, json.dumps(spec), str(LISTEN_S)],
            timeout=LISTEN_S + 30.0,
        )
        self.found = json.loads(done.stdout.decode().strip().splitlines()[-1])


@pytest.mark.timeout(150)
def test_a_tls_lab_run_admits_no_peer_without_a_certificate_of_the_run(
    lab_ready: None, tmp_path: Path
) -> None:
    name = new_lab_name()
    intruders = Intruders(name, tmp_path / "run", tmp_path / "foreign")
    intruders.start()
    result = run_lab(
        PAPER,
        RunMode.RSU,
        seed=0,
        speed=2.0,
        name=name,
        run_dir=tmp_path / "run",
        json_out=tmp_path / "result.json",
    )
    intruders.join(timeout=60)
    assert result.error is None, result.error
    assert result.harness == "daemons" and result.all_finished
    assert result.collisions == 0
    lab: dict[str, Any] = result.lab or {}
    assert lab["tls"] is True
    assert lab["modes"]["B"]["coordinated_s"] > 0  # the RSU coordinated
    assert result.provenance is not None and result.provenance.channel.kind == "lab"
    assert json.loads((tmp_path / "result.json").read_text())["lab"]["name"] == lab["name"]
    _check_separate_and_routed(result)
    for locators in lab["endpoints"].values():
        assert locators[0].startswith("quic/") and locators[0].endswith(QUIC_DATAGRAMS)
        assert locators[1].startswith("tls/")
    # V2X still crosses the air as datagrams (QUIC over UDP), the plumbing the wire (TLS):
    # _check_separate_and_routed
    fp = result.network.stream("fp") if result.network else None
    assert fp is not None and fp.delivery_ratio is not None and fp.delivery_ratio >= 0.95
    assert intruders.error == "", intruders.error
    found = intruders.found
    assert found["plain"] == {"peers": 0, "samples": 0}, found
    assert found["foreign_ca"] == {"peers": 0, "samples": 0}, found
    assert found["insider"]["peers"] >= 3 and found["insider"]["samples"] > 0, found
    _gone(result)


@pytest.mark.timeout(150)
def test_a_flow_scenario_runs_in_the_lab_with_host_processes(
    lab_ready: None, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Short: the first 15 run seconds at real time, 12 cars in 3 host processes of 4 (all
    twelve daemons join and acknowledge; the first car of every flow is inserted). Counts,
    not finishes: on a loaded 2-core machine the daemons run late (``crosspath up`` of the
    same scenario there finished no car within 25 s either). The run directory is relative
    (as ``crosspath lab run`` gives it by default): the daemons, started in the lab's
    namespaces, still find their TLS files."""
    monkeypatch.chdir(tmp_path)
    result = run_lab(
        SMALL_FLOWS,
        RunMode.RSU,
        seed=0,
        speed=1.0,
        name=new_lab_name(),
        run_dir=Path("run"),
        cars_per_process=4,
        max_sim_s=FLOW_SIM_S,
    )
    assert result.error is None, result.error
    assert (tmp_path / "run" / "scenario.toml").is_file()  # the flows expanded for the seed
    assert sorted(result.vehicles) == sorted(f"{f}-{n}" for f in FLOWS for n in range(3))
    assert result.collisions == 0
    summary = result.summary
    assert summary is not None and summary.vehicles_inserted >= len(FLOWS), summary
    acked = result.actors or {}
    assert set(result.vehicles) <= set(acked)  # every car reported as its own node
    lab: dict[str, Any] = result.lab or {}
    hosts = {k: v for k, v in lab["processes"].items() if k.startswith("host.")}
    assert len(hosts) == 3 and set(hosts.values()) <= set(result.vehicles)
    assert len(lab["nodes"]) == 5  # the monitor, rsu1, one namespace per host process
    fp = result.network.stream("fp") if result.network else None
    assert fp is not None and fp.msgs_rx > 0
    _gone(result)


def test_lab_run_cli_has_a_no_tls_flag() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "services.cli.main", "lab", "run", "--help"],
        capture_output=True,
        text=True,
        cwd=REPO,
        check=True,
    ).stdout
    assert "--no-tls" in out and "--cars-per-process" in out

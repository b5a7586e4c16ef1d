"""``crosspath sumo --daemons``: SUMO is the world process, the RSU a real daemon over Zenoh."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.cli.main import main
from services.model.kinematics import TruthState
from services.model.results import RunResult
from services.model.types import RunMode
from services.sumo.cosim import CosimOptions
from services.sumo.daemons import DaemonsCosimulation
from services.sumo.netgen import Control, write_routes
from services.supervise.launcher import processes_carrying

pytestmark = pytest.mark.daemons

# crossing flows at the 4-way: straight from every approach, a left turn from the west, a
# right turn from the south, followers on the west and north approaches (8 cars)
DEPARTURES = {
    "we": [0.0, 2.5],
    "ns": [0.5, 3.0],
    "ew": [1.0],
    "sn": [1.5],
    "wn": [5.0],
    "se": [6.0],
}
CARS = sum(len(ts) for ts in DEPARTURES.values())


class _Watched(DaemonsCosimulation):
    """Records, at every planning step, each connected car's mode and coordinating RSU."""

    owners: dict[str, set[str]]
    modes: set[str]

    def _plan(self, now: float, truths: dict[str, TruthState], reasons: dict[str, str]) -> None:
        super()._plan(now, truths, reasons)
        for cid in truths:
            agent = self.cars[cid].agent
            if agent is not None:
                self.modes.add(agent.mode.name)
                if agent.coordination.rsu is not None:
                    self.owners.setdefault(cid, set()).add(agent.coordination.rsu)


def _no_leftovers(run_id: str | None) -> None:
    assert run_id is not None and run_id.startswith("sumo-")
    assert processes_carrying(run_id) == []


def test_rsu_daemon_coordinates_sumo_cars_over_zenoh(
    short_nets: dict[Control, Path], tmp_path: Path
) -> None:
    routes = tmp_path / "cars.rou.xml"
    assert write_routes(routes, DEPARTURES) == CARS
    run_dir = tmp_path / "run"
    options = CosimOptions(mode=RunMode.RSU, daemons=True, speed=2.0, run_dir=run_dir)
    sim = _Watched(short_nets[Control.PRIORITY], routes, options)
    sim.owners, sim.modes = {}, set()
    r = sim.run()
    assert r.harness == "daemons" and r.mode == "rsu" and r.speed == 2.0
    assert r.sumo is not None and r.summary is not None
    # SUMO's collision check (bodies touching, lanes and junction) and crosspath's
    assert r.sumo.collisions == 0 and r.collisions == 0
    assert r.min_gap_m is not None and r.min_gap_m > 0.0
    assert len(r.vehicles) == CARS and r.all_finished and r.summary.vehicles_finished == CARS
    assert r.sumo.connected == CARS
    # the RSU is a daemon: it ran the run to its end and reported, it saw every car and
    # sent commands that the world process received over Zenoh and handed to the cars
    assert r.provenance is not None and r.provenance.channel.kind == "zenoh"
    assert r.actors is not None and r.final_stats == ["rsu-c"]
    rsu = r.actors["rsu-c"]
    assert rsu["final"] and rsu["v2x"]["msgs_tx"] > 0
    assert {c for _t, cars in rsu["table_log"] for c in cars} == set(r.vehicles)
    assert rsu["auth"]["verified"] > 0  # the cars' paths were signed and verified
    world = r.actors["monitor"]
    assert world["cars_listed"] == CARS and world["rsus_heard"]["rsu-c"] > 0
    assert r.network is not None
    assert r.network.streams["cmd"].msgs_rx > 0 and r.network.streams["ap"].msgs_rx > 0
    # the cars were coordinated by the RSU daemon (a coordinated mode, owner rsu-c)
    assert sim.modes & {"C_SLOW", "C_FAST"}
    assert sim.owners and set().union(*sim.owners.values()) == {"rsu-c"}
    assert len(sim.owners) >= 2
    # the daemon was stopped: its process is gone, it logged its stop, no leftover
    assert sim.launcher is not None
    assert all(c.process.returncode is not None for c in sim.launcher.children.values())
    assert "rsu rsu-c stopped" in (run_dir / "rsu-c.log").read_text()
    assert (run_dir / "scenario.toml").is_file() and (run_dir / "keys" / "we-0.cert").is_file()
    _no_leftovers(r.run_id)


def test_cli_daemons_writes_the_result_and_leaves_no_process(
    short_nets: dict[Control, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    routes = tmp_path / "few.rou.xml"
    write_routes(routes, {"we": [0.0], "ns": [0.5], "ew": [1.0]})
    out = tmp_path / "r.json"
    net = str(short_nets[Control.PRIORITY])
    assert main(["sumo", net, str(routes), "--daemons", "--speed", "3", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "SUMO: 3 of 3 cars connected, 3 arrived, SUMO collisions 0" in printed
    r = RunResult.model_validate_json(out.read_text())
    assert r.harness == "daemons" and r.collisions == 0 and r.all_finished
    assert r.actors is not None and r.actors["rsu-c"]["final"]
    assert (tmp_path / "r-logs" / "rsu-c.log").is_file()  # the run dir beside --json
    _no_leftovers(r.run_id)


def test_bad_input_with_daemons_is_exit_2_before_any_daemon(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "x.net.xml"
    bad.write_text("<routes/>")
    run_dir = tmp_path / "run"
    assert main(["sumo", str(bad), str(bad), "--daemons", "--run-dir", str(run_dir)]) == 2
    assert "not a SUMO network" in capsys.readouterr().err
    assert not (run_dir / "children.json").exists()
    assert main(["sumo", str(bad), str(bad), "--speed", "2"]) == 2
    assert "need --daemons" in capsys.readouterr().err
    with pytest.raises(ValueError, match="speed"):
        CosimOptions(daemons=True, speed=0.0)


class _Interrupted(DaemonsCosimulation):
    """Ctrl-C in the middle of the run (at run time 3 s)."""

    def _plan(self, now: float, truths: dict[str, TruthState], reasons: dict[str, str]) -> None:
        if now >= 3.0:
            raise KeyboardInterrupt
        super()._plan(now, truths, reasons)


def test_interrupted_run_stops_the_rsu_daemon_gracefully(
    short_nets: dict[Control, Path], tmp_path: Path
) -> None:
    routes = tmp_path / "cars.rou.xml"
    write_routes(routes, DEPARTURES)
    run_dir = tmp_path / "run"
    options = CosimOptions(mode=RunMode.RSU, daemons=True, speed=3.0, run_dir=run_dir)
    sim = _Interrupted(short_nets[Control.PRIORITY], routes, options)
    with pytest.raises(KeyboardInterrupt):
        sim.run()
    assert sim.launcher is not None and sim.launcher.children
    assert all(c.process.returncode == 0 for c in sim.launcher.children.values())
    log = (run_dir / "rsu-c.log").read_text()
    assert "stopped by the monitor" in log and "SIGTERM received" in log
    assert sim.loop is None  # the world's Zenoh session is closed
    _no_leftovers(sim.run_id)

"""``crosspath sumo``: SUMO is the world, crosspath's agents and RSU drive the connected cars."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from services.cli.main import main
from services.model.kinematics import TruthState
from services.model.results import RunResult
from services.model.types import RunMode
from services.sumo.cosim import (
    CosimOptions,
    Cosimulation,
    _draw_connected,
    _free_time_to_exit,
)
from services.sumo.netgen import Control, VehicleTypeSpec, build_network, write_routes
from services.sumo.run import cosimulate
from tests.sumo.conftest import require_sumo

# straight from every approach and a left turn from the west, two cars following on
# the west and north approaches: crossing, turning and following at one 4-way
DEPARTURES = {
    "we": [0.0, 2.5],
    "ns": [0.5, 3.0],
    "ew": [1.0],
    "sn": [1.5],
    "wn": [5.0],
}


@pytest.fixture(scope="module")
def four_way(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A 4-way priority junction with 40 m approaches (netconvert) and 7 cars."""
    require_sumo()
    d = tmp_path_factory.mktemp("cosim")
    net = build_network(d, Control.PRIORITY, approach_m=40.0)
    routes = d / "cars.rou.xml"
    write_routes(routes, DEPARTURES)
    return net, routes


def test_rsu_mode_drives_every_car_through_without_a_collision(
    four_way: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    net, routes = four_way
    out = tmp_path / "r.json"
    assert main(["sumo", str(net), str(routes), "--mode", "rsu", "--json", str(out)]) == 0
    assert "SUMO: 7 of 7 cars connected" in capsys.readouterr().out
    r = RunResult.model_validate_json(out.read_text())
    assert r.mode == "rsu" and r.harness == "in-process"
    sumo = r.sumo
    assert sumo is not None and r.summary is not None
    # SUMO's own collision check (lanes and junction, bodies touching) and ours
    assert sumo.collisions == 0
    assert r.collisions == 0
    assert r.min_gap_m is not None and r.min_gap_m > 0.0
    assert len(r.vehicles) == 7 and r.all_finished and r.summary.vehicles_finished == 7
    assert sumo.connected == 7 and all(v.connected for v in sumo.vehicles.values())
    # SUMO's timeLoss beside our delay, for every car
    for vid, v in r.vehicles.items():
        assert v.delay_s is not None and v.insertion_delay_s is not None
        assert sumo.vehicles[vid].time_loss_s is not None
        assert sumo.vehicles[vid].sumo_id == vid
    # the cars were crosspath's: each was coordinated by the RSU of junction "c"
    assert r.provenance is not None and r.provenance.policy_params.keys() == {"rsu-c"}
    assert json.loads(out.read_text())["sumo"]["step_s"] == pytest.approx(0.05)


# the 2-junction corridor (tests/sumo/conftest.py): through traffic both ways, two cars
# following west to east, one car crossing at j0 and one at j1 while they pass
CORRIDOR_ROUTES = {
    "we": "w_j0 j0_j1 j1_e",
    "ew": "e_j1 j1_j0 j0_w",
    "ns0": "n0_j0 j0_s0",
    "sn1": "s1_j1 j1_n1",
}
CORRIDOR_DEPARTURES = {"we": [0.0, 3.0], "ew": [1.0], "ns0": [0.0], "sn1": [3.0]}


class _OwnersWatched(Cosimulation):
    """A co-simulation that records, at every planning step, the RSU coordinating each
    connected car (its agent's owner, ``services.vehicle.coordination``)."""

    owners: dict[str, set[str]]

    def _plan(self, now: float, truths: dict[str, TruthState], reasons: dict[str, str]) -> None:
        super()._plan(now, truths, reasons)
        for cid in truths:
            agent = self.cars[cid].agent
            if agent is not None and agent.coordination.rsu is not None:
                self.owners.setdefault(cid, set()).add(agent.coordination.rsu)


def test_corridor_cars_are_coordinated_by_each_junction_rsu(
    corridors: dict[int, Path], tmp_path: Path
) -> None:
    rows = sorted(
        (t, f"{r}-{n}", r) for r, ts in CORRIDOR_DEPARTURES.items() for n, t in enumerate(ts)
    )
    routes = tmp_path / "corridor.rou.xml"
    routes.write_text(
        "\n".join(
            ["<routes>", VehicleTypeSpec().xml()]
            + [f'  <route id="{r}" edges="{e}"/>' for r, e in CORRIDOR_ROUTES.items()]
            + [
                f'  <vehicle id="{v}" type="car" route="{r}" depart="{t}" departSpeed="0"/>'
                for t, v, r in rows
            ]
            + ["</routes>", ""]
        )
    )
    sim = _OwnersWatched(corridors[2], routes, CosimOptions(mode=RunMode.RSU))
    sim.owners = {}
    r = sim.run()
    assert r.sumo is not None and r.summary is not None
    assert r.collisions == 0 and r.sumo.collisions == 0
    assert r.min_gap_m is not None and r.min_gap_m > 0.0
    assert r.all_finished and r.summary.vehicles_finished == len(rows) == 5
    assert r.sumo.connected == 5
    # one RSU per junction, and each coordinated exactly the cars that cross its junction
    assert r.provenance is not None
    assert r.provenance.policy_params.keys() == {"rsu-j0", "rsu-j1"}
    assert sim.owners == {
        "we-0": {"rsu-j0", "rsu-j1"},
        "we-1": {"rsu-j0", "rsu-j1"},
        "ew-0": {"rsu-j0", "rsu-j1"},
        "ns0-0": {"rsu-j0"},
        "sn1-0": {"rsu-j1"},
    }
    for rsu in sim.rsus.values():
        assert rsu.counters["initiations"] > 0 and rsu.counters["coordinated_paths"] > 0


def test_without_connected_cars_sumo_drives_all(four_way: tuple[Path, Path]) -> None:
    net, routes = four_way
    r = cosimulate(net, routes, CosimOptions(mode=RunMode.RSU, connected_share=0.0))
    assert r.sumo is not None and r.sumo.connected == 0
    assert r.all_finished and r.collisions == 0 and r.sumo.collisions == 0
    # SUMO's priority junction: the minor road (north-south) waits, delays are measured
    assert all(v.delay_s is not None for v in r.vehicles.values())


# each collided or stranded a car before rule 5 (services.vehicle.planner): a connected
# car on the minor road took the way from an unconnected one on the priority road
MIXED = [
    (RunMode.RSU, 0.5, 7),
    (RunMode.STANDALONE, 0.3, 1),
    (RunMode.FP_ONLY, 0.3, 1),
    (RunMode.STANDALONE, 0.3, 2),
]


@pytest.mark.parametrize(("mode", "share", "seed"), MIXED)
def test_mixed_traffic_keeps_the_priority_road(
    four_way: tuple[Path, Path], mode: RunMode, share: float, seed: int
) -> None:
    net, routes = four_way
    r = cosimulate(net, routes, CosimOptions(mode=mode, connected_share=share, seed=seed))
    sumo = r.sumo
    assert sumo is not None and 0 < sumo.connected < 7  # mixed: both kinds of driver
    assert r.collisions == 0 and sumo.collisions == 0
    assert r.all_finished
    assert r.min_gap_m is not None and r.min_gap_m > 0.5


def test_connected_draw_is_per_car_and_seeded() -> None:
    ids = [f"c{k}" for k in range(400)]
    half = [_draw_connected(3, i, 0.5) for i in ids]
    assert half == [_draw_connected(3, i, 0.5) for i in ids]
    assert 150 < sum(half) < 250
    assert all(_draw_connected(0, i, 1.0) for i in ids[:5])
    assert not any(_draw_connected(0, i, 0.0) for i in ids[:5])


def test_free_flow_to_the_exit_does_not_stop_at_the_end() -> None:
    import numpy as np

    from services.model.geometry import Polyline
    from services.model.kinematics import Limits

    line = Polyline(np.array([[0.0, 0.0], [200.0, 0.0]]))
    lim = Limits(v_max=10.0, accel=1.0, decel_comfort=2.0, decel_emergency=5.0, actuator_lag_s=0.0)
    # 50 m to reach 10 m/s in 10 s, then 150 m at 10 m/s: 25 s; no braking at the end
    assert _free_time_to_exit(line, 0.0, 0.0, lim) == pytest.approx(25.0, rel=0.01)
    assert _free_time_to_exit(line, 0.0, 10.0, lim) == pytest.approx(20.0, rel=0.01)
    assert math.isfinite(_free_time_to_exit(line, 199.9, 0.0, lim))


def test_bad_input_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "x.net.xml"
    bad.write_text("<routes/>")
    assert main(["sumo", str(bad), str(bad)]) == 2
    assert "not a SUMO network" in capsys.readouterr().err
    with pytest.raises(ValueError, match="connected_share"):
        CosimOptions(connected_share=1.5)

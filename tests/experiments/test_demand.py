"""``crosspath experiment demand``: the grid's scenarios, SUMO beside crosspath, artefacts."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import pytest

from services.cli.main import main
from services.experiments.demand import (
    MIXES,
    DemandConfig,
    demand_scenario,
    run_demand_experiment,
)
from services.model.catalog import resolve_scenario
from services.model.scenario import load_scenario
from services.model.types import Policy, RunMode
from services.sim.harness import SimOptions, Simulation
from tests.sumo.conftest import require_sumo


def test_demand_scenario_splits_each_approach_by_the_mix() -> None:
    base = load_scenario(resolve_scenario("four-way-flows"))
    sc = demand_scenario(base, 400.0, "turning", 90.0, 150.0)
    flows = {f.id: f for f in sc.spec.flows}
    assert len(flows) == 12 and all(f.route == fid for fid, f in flows.items())
    for side in "wesn":
        assert sum(f.vehicles_per_hour for f in flows.values() if f.route[0] == side) == (
            pytest.approx(400.0)
        )
    assert flows["we"].vehicles_per_hour == pytest.approx(280.0)
    assert flows["wn"].vehicles_per_hour == pytest.approx(60.0)  # left from the west
    assert {f.end_s for f in flows.values()} == {90.0}
    assert sc.params.max_sim_s == 150.0
    straight = demand_scenario(base, 200.0, "straight", 60.0, 60.0)
    assert sorted(f.route for f in straight.spec.flows) == ["ew", "ns", "sn", "we"]
    assert set(MIXES) == {"straight", "turning"}


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"demands": (0.0,)}, "demands"),
        ({"mixes": ("zigzag",)}, "unknown mix"),
        ({"columns": ("rsu-magic",)}, "unknown mode"),
        ({"controls": ("roundabout",)}, "unknown control"),
        ({"seeds": 0}, "seeds"),
    ],
)
def test_bad_grid_is_refused(kwargs: dict[str, Any], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        DemandConfig(**kwargs)


def _check_artefacts(out: Path, n_runs: int) -> dict[str, Any]:
    doc: dict[str, Any] = json.loads((out / "results.json").read_text())
    with (out / "runs.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == len(doc["runs"]) == n_runs
    for key in ("tool", "mode", "demand_vph", "mix", "seed", "arrived", "finished",
                "mean_delay_s", "collisions", "wall_s"):  # fmt: skip
        assert key in rows[0]
    for name in ("delay_vs_demand.png", "delay_vs_demand.pdf", "delay_vs_demand.svg"):
        assert (out / name).stat().st_size > 1000
    table = (out / "table.md").read_text()
    assert "SUMO priority" in table and "SUMO all-way stop" in table and "SUMO actuated TL" in table
    assert "delay_vs_demand.png" in (out / "REPORT.md").read_text()
    # SUMO drove the same arrivals as crosspath, car for car
    by_seed: dict[tuple[str, int], set[int]] = {}
    for r in doc["runs"]:
        by_seed.setdefault((r["mix"], r["seed"]), set()).add(r["arrived"])
    assert all(len(v) == 1 for v in by_seed.values())
    sumo = [r for r in doc["runs"] if r["tool"] == "sumo"]
    assert sumo and all(r["collisions"] == 0 and r["inserted"] == r["arrived"] for r in sumo)
    return doc


@pytest.mark.slow  # 8 SUMO and crosspath runs
def test_small_grid_writes_every_artefact(tmp_path: Path) -> None:
    require_sumo()
    cfg = DemandConfig(
        demands=(300.0,), mixes=("straight",), seeds=2, horizon_s=20.0, clearance_s=40.0,
        columns=("standalone",), jobs=2,
    )  # fmt: skip
    doc = run_demand_experiment(cfg, tmp_path, progress=False)
    _check_artefacts(tmp_path, 2 + 2 * 3)
    (agg,) = [a for a in doc["aggregates"] if a["mode"] == "standalone"]
    assert agg["runs"] == 2 and agg["mean_delay_s"]["n"] + agg["mean_delay_s"]["missing"] == 2
    assert doc["timing"]["crosspath_cpu_s"] > 0


@pytest.mark.slow
def test_quick_command_runs_every_mode_and_control(tmp_path: Path) -> None:
    require_sumo()
    assert main(["experiment", "demand", "--quick", "--out", str(tmp_path), "--jobs", "2"]) == 0
    doc = _check_artefacts(tmp_path, 4 + 3)
    assert {r["mode"] for r in doc["runs"]} == {
        "standalone", "fp-only", "rsu-paper", "rsu-slot",
        "sumo-priority", "sumo-allway_stop", "sumo-traffic_light",
    }  # fmt: skip


def test_bad_option_is_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["experiment", "demand", "--demands", "a,b"])
    assert exc.value.code == 2
    assert "--demands" in capsys.readouterr().err


def test_options_pick_the_grid() -> None:
    from services.cli.main import build_parser
    from services.experiments.demand import config_from_args

    parser = build_parser()
    default = config_from_args(parser.parse_args(["experiment", "demand"]))
    assert default == DemandConfig()
    assert (default.demands, default.mixes, default.seeds) == (
        (200.0, 400.0, 600.0),
        ("straight",),
        2,
    )
    full = config_from_args(parser.parse_args(["experiment", "demand", "--full"]))
    assert full.demands == (200.0, 400.0, 600.0, 800.0) and full.seeds == 5
    assert (full.horizon_s, full.mixes) == (600.0, ("straight", "turning"))
    sumo_only = config_from_args(
        parser.parse_args(
            ["experiment", "demand", "--modes", "none", "--seed", "3", "--seeds", "1"]
        )
    )
    assert sumo_only.columns == () and sumo_only.base_seed == 3 and sumo_only.seeds == 1


@pytest.mark.slow  # 140 s of the turning mix at 600 veh/h in-process (about 40 s)
def test_opposing_left_turners_behind_leaders_do_not_lock_the_box() -> None:
    # Issue 12: sw-2 and ne-2, opposing left turners each following a straight car, had
    # autonomous paths that rested where each could stop behind its leader, so the RSU saw
    # their turns only 1-2 m from the box; both stops ended in it, each in the other's
    # exit, and they stood there from 118 s to the end (27 of 44 cars finished by 180 s).
    # Followed by their leaders' future paths, their paths run through the box early.
    base = load_scenario(resolve_scenario("four-way-flows"))
    sc = demand_scenario(base, 600.0, "turning", 60.0, 140.0)
    sim = Simulation(sc, SimOptions(mode=RunMode.RSU, policy=Policy.PAPER, seed=0, trace=True))
    result = sim.run()
    assert result.collisions == 0
    # no car stands with its centre in the box (grown by half a car) for 20 s or more
    reach = 3.5 + 2.25
    since: dict[str, float] = {}
    longest = 0.0
    for t, vehicle, _s, x, y, speed, *_ in sim.trace_rows:
        if speed <= 0.05 and abs(x) <= reach and abs(y) <= reach:
            since.setdefault(vehicle, t)
            longest = max(longest, t - since[vehicle])
        else:
            since.pop(vehicle, None)
    assert longest < 20.0
    assert result.summary is not None and result.summary.vehicles_finished >= 30

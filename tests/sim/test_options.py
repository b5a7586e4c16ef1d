"""``SimOptions`` coerces names to the enums and refuses what it cannot run; trace conversion."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest

from services.model.scenario import Scenario, load_scenario
from services.model.types import Policy, RunMode
from services.sim.harness import TRACE_FIELDS, SimOptions, harness_trace, simulate

ROOT = Path(__file__).resolve().parents[2]
PAPER = ROOT / "scenarios" / "paper-blind-intersection.toml"


@pytest.fixture(scope="module")
def paper() -> Scenario:
    return load_scenario(PAPER)


def test_names_become_the_enums() -> None:
    o = SimOptions(mode="rsu", policy="slot")  # type: ignore[arg-type]
    assert o.mode is RunMode.RSU and o.policy is Policy.SLOT
    o = SimOptions(mode="fp-only")  # type: ignore[arg-type]
    assert o.mode is RunMode.FP_ONLY


def test_a_mode_given_by_name_runs_that_mode(paper: Scenario) -> None:
    """Before, ``mode="rsu"`` failed the identity checks and ran fp-only labelled rsu."""
    by_name = simulate(paper, SimOptions(mode="rsu", policy="slot", seed=2))  # type: ignore[arg-type]
    by_enum = simulate(paper, SimOptions(mode=RunMode.RSU, policy=Policy.SLOT, seed=2))
    assert by_name.mode is RunMode.RSU and by_name.policy is Policy.SLOT
    assert by_name.vehicles == by_enum.vehicles
    assert by_name.provenance is not None and set(by_name.provenance.policy_params) == {"rsu1"}
    fp_only = simulate(paper, SimOptions(mode=RunMode.FP_ONLY, seed=2))
    assert by_name.vehicles != fp_only.vehicles  # the RSU did coordinate


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"mode": "bogus"}, "unknown mode 'bogus': expected one of standalone, fp-only, rsu"),
        ({"mode": "RSU"}, "unknown mode 'RSU'"),
        ({"mode": 3}, "unknown mode 3"),
        ({"policy": "fast"}, "unknown policy 'fast': expected one of paper, slot"),
        ({"seed": -1}, "seed must be an int >= 0"),
        ({"seed": True}, "seed must be an int >= 0"),
        ({"max_sim_s": 0.0}, "max_sim_s"),
        ({"max_sim_s": math.inf}, "max_sim_s"),
        ({"start_times": {"A": math.nan}}, "start times"),
        ({"start_times": {"A": -1.0}}, "start times"),
    ],
)
def test_what_cannot_run_is_refused(kwargs: dict[str, Any], message: str) -> None:
    with pytest.raises(ValueError) as info:
        SimOptions(**kwargs)
    assert message in str(info.value)


def test_start_times_must_name_every_car(paper: Scenario) -> None:
    with pytest.raises(ValueError, match="lacks the car"):
        simulate(paper, SimOptions(start_times={"A": 0.0}))


def test_harness_trace_converts_the_monitors_rows() -> None:
    fields = ["t", "vehicle", "x", "y", "s", "speed", "mode", "reason"]
    rows = [
        [0.05, "A", 1.0, 2.0, 10.0, 5.1, "AUTO", "cruise"],
        [0.0, "A", 0.0, 2.0, 9.75, 5.0, "AUTO", "cruise"],
        [0.0, "B", 3.0, 4.0, 1.0, 0.0, "C_SLOW", "coordinated"],
    ]
    out = harness_trace(fields, rows)
    assert len(out[0]) == len(TRACE_FIELDS)
    assert out[0] == (0.0, "A", 9.75, 0.0, 2.0, 5.0, 0.0, "cruise", "", "AUTO")
    assert out[1] == (0.0, "B", 1.0, 3.0, 4.0, 0.0, 0.0, "coordinated", "", "C_SLOW")
    assert out[2][6] == pytest.approx(2.0)  # accel from the speed: 0.1 m/s over 0.05 s
    with pytest.raises(ValueError, match="speed"):
        harness_trace(["t", "vehicle", "x", "y", "s"], [])

"""The typed run result: JSON round trip, today's keys, refusals, and the committed schema."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest
from pydantic import ValidationError

from services.model.results import (
    NetworkSection,
    Origin,
    RunResult,
    schema_json,
)
from services.model.types import Policy, RunMode

ROOT = Path(__file__).resolve().parents[2]
SCHEMA = ROOT / "docs" / "run-result.schema.json"

BASE_KEYS = {
    "mode", "policy", "seed", "collisions", "min_gap_m", "min_pet_s", "min_conflict_pet_s",
    "sim_s", "wall_s",
    "mean_passing_time_s", "all_finished", "vehicles", "scenario", "start_times", "harness",
    "speedup_vs_real_time",
}  # fmt: skip


def _stream(**over: Any) -> dict[str, Any]:
    data = {
        "msgs": 10, "bytes": 2920, "msgs_rx": 19, "bytes_rx": 5548, "malformed": 0,
        "dropped_stale": 1, "kbps_per_vehicle": 1.5, "latency_ms_p50": 3.2,
        "latency_ms_p99": 7.1, "latency_ms_mean": None, "delivery_ratio": 1.05,
    }  # fmt: skip
    return {**data, **over}


def _car(passing: float | None = 24.5, first: bool = True) -> dict[str, Any]:
    return {
        "passing_time_s": passing,
        "first_through": first,
        "stops": 0,
        "max_speed_mps": 13.89,
        "finished": passing is not None,
    }


def _base(**over: Any) -> dict[str, Any]:
    data: dict[str, Any] = {
        "mode": "rsu", "policy": "slot", "seed": 4, "collisions": 0, "min_gap_m": None,
        "min_pet_s": 1.35, "min_conflict_pet_s": 1.6, "sim_s": 38.0, "wall_s": 0.9,
        "mean_passing_time_s": 24.5,
        "all_finished": False, "vehicles": {"A": _car(), "B": _car(None, False)},
        "scenario": "paper-blind-intersection", "start_times": {"A": 0.0, "B": 0.5986},
        "harness": "in-process", "speedup_vs_real_time": 42.2,
    }  # fmt: skip
    return {**data, **over}


def _daemon_run() -> dict[str, Any]:
    """Every section a daemon run in the lab can carry."""
    return _base(
        harness="daemons",
        loss=0.3,
        run_id="up-20250101-120000-abc123",
        speed=2.0,
        end_reason="every car stands at its goal",
        truth={"steps": 761, "gaps": 2, "late": 0},
        final_stats=["A", "B", "rsu1"],
        network={
            "fp": _stream(),
            "beacon": _stream(delivery_ratio=None),
            "total_kbps_per_vehicle": 3.0,
        },
        epoch_unix=1735732800.25,
        actors={"rsu1": {"final": True, "v2x": {"msgs_tx": 3}, "table_log": [[0.5, ["A"]]]}},
        expect_crash=["rsu1"],
        crashes=[{"node": "rsu1", "event": "lost", "t_s": 12.5}],
        trace_fields=["t", "vehicle", "x", "y", "s", "speed", "mode", "reason"],
        trace=[[0.0, "A", -200.0, -1.75, 0.0, 0.0, "AUTO", "waiting"]],
        error="B lost",
        lab={"name": "r1234abcd", "faults": {"loss": 0.3, "nodes": ["A", "B", "rsu1"]}},
        provenance={
            "version": "0.1.0",
            "commit": "0" * 40,
            "scenario": "paper-blind-intersection",
            "scenario_file": "/x/paper-blind-intersection.toml",
            "scenario_sha256": "a" * 64,
            "channel": {"kind": "lab", "loss": 0.3, "burst": 2.0, "rate_mbit": 6.0},
            "policy": "slot",
            "policy_params": {"rsu1": {"headway_s": 1.0, "max_points": 171, "policy": "slot"}},
        },
    )


def test_json_round_trip_is_lossless_and_keeps_every_key() -> None:
    data = _daemon_run()
    result = RunResult.model_validate(data)
    again = RunResult.model_validate_json(result.to_json())
    assert again == result
    on_disk = json.loads(result.to_json())
    assert set(on_disk) == set(data)
    assert on_disk["network"]["fp"] == data["network"]["fp"]
    assert on_disk["trace"] == data["trace"]
    assert on_disk["provenance"]["channel"]["burst"] == 2.0
    # attributes, typed
    assert result.mode is RunMode.RSU and result.policy is Policy.SLOT
    assert result.vehicles["B"].passing_time_s is None
    assert result.network is not None and set(result.network.streams) == {"fp", "beacon"}
    fp = result.network.stream("fp")
    assert fp is not None and fp.delivery_ratio == 1.05  # duplicates may exceed 1
    assert result.network.stream("cmd") is None
    assert result.crashes is not None and result.crashes[0].event == "lost"
    assert result.trace_columns()["mode"] == 6
    assert not result.ok


def test_absent_sections_stay_absent_and_nulls_stay_null() -> None:
    result = RunResult.model_validate(_base())
    on_disk = result.to_dict()
    assert set(on_disk) == BASE_KEYS  # no daemon, lab or provenance section appears
    assert on_disk["min_gap_m"] is None and on_disk["vehicles"]["B"]["passing_time_s"] is None
    assert result.ok
    traced = RunResult.model_validate(_daemon_run())
    assert set(traced.without_trace().to_dict()) == set(_daemon_run()) - {"trace", "trace_fields"}


def test_updated_validates_and_failed_builds_an_empty_result() -> None:
    result = RunResult.model_validate(_base())
    assert result.updated(error="stopped").error == "stopped"
    with pytest.raises(ValidationError):
        result.updated(loss=2.0)
    with pytest.raises(ValidationError):
        result.seed = 5  # type: ignore[misc]  # frozen
    failed = RunResult.failed(
        mode="fp-only", policy=None, seed=1, scenario="s", harness="daemons", error="no result"
    )
    assert failed.error == "no result" and failed.vehicles == {} and not failed.all_finished
    assert RunResult.model_validate_json(failed.to_json()) == failed


@pytest.mark.parametrize(
    ("change", "where"),
    [
        ({"min_gap_m": math.nan}, "min_gap_m"),
        ({"min_pet_s": math.inf}, "min_pet_s"),
        ({"min_pet_s": -0.1}, "min_pet_s"),
        ({"collisions": -1}, "collisions"),
        ({"seed": -3}, "seed"),
        ({"loss": 1.5}, "loss"),
        ({"loss": 30.0}, "loss"),  # a percentage is not a probability
        ({"mode": "bogus"}, "mode"),
        ({"policy": "fastest"}, "policy"),
        ({"harness": "lab"}, "harness"),
        ({"passing": 1}, "passing"),  # unknown key
        ({"vehicles": {"A": {**_car(), "stops": 1.5}}}, "stops"),
        ({"vehicles": {"A": {**_car(), "colour": "red"}}}, "colour"),
        ({"network": {"fp": {"msgs": 1}, "total_kbps_per_vehicle": 1.0}}, "bytes"),
        (
            {"network": {"fp": _stream(kbps_per_vehicle=-1.0), "total_kbps_per_vehicle": 0.0}},
            "kbps",
        ),
        ({"network": {"fp": _stream()}}, "total_kbps_per_vehicle"),
        ({"crashes": [{"node": "rsu1", "event": "exploded", "t_s": 1.0}]}, "event"),
        ({"speed": 0.0}, "speed"),
    ],
)
def test_bad_values_are_refused(change: dict[str, Any], where: str) -> None:
    with pytest.raises(ValidationError) as info:
        RunResult.model_validate(_base(**change))
    assert where in str(info.value)


def test_provenance_refuses_bad_digests_and_channels() -> None:
    prov = _daemon_run()["provenance"]
    for bad in (
        {**prov, "scenario_sha256": "ABC"},
        {**prov, "channel": {"kind": "radio"}},
        {**prov, "channel": {"kind": "memory", "jitter_s": math.nan}},
        {**prov, "channel": {"kind": "lab", "loss": 1.2}},
        {**prov, "extra": 1},
    ):
        with pytest.raises(ValidationError):
            RunResult.model_validate(_base(provenance=bad))
    with pytest.raises(ValidationError):
        Origin(scenario_sha256="0" * 63)


def test_network_section_takes_any_stream_name() -> None:
    section = NetworkSection.model_validate(
        {"sim": _stream(), "total_kbps_per_vehicle": 0.5, "fp": _stream()}
    )
    assert sorted(section.streams) == ["fp", "sim"]
    assert section.model_dump(mode="json")["sim"]["msgs"] == 10


def test_the_committed_schema_is_the_models() -> None:
    """docs/run-result.schema.json cannot go stale: regenerate it with
    ``python -c "from services.model.results import schema_json as s; print(s(), end='')"
    > docs/run-result.schema.json``."""
    assert SCHEMA.read_text() == schema_json()
    schema = json.loads(SCHEMA.read_text())
    assert schema == RunResult.model_json_schema()
    assert set(schema["required"]) == BASE_KEYS
    assert schema["additionalProperties"] is False

"""The run result of DESIGN.md (``services.model.results.RunResult``), built from the metrics
of one run (either harness), with its provenance; and its one-screen summary."""

from __future__ import annotations

import dataclasses
import math
from enum import Enum
from typing import Any

import numpy as np
from pydantic import BaseModel

from services.model.results import (
    ChannelParams,
    Knob,
    Origin,
    Provenance,
    RunResult,
    RunSummary,
    VehicleResult,
)
from services.model.scenario import Scenario
from services.model.types import Policy, RunMode
from services.rsu.config import rsu_config
from services.sim.metrics import RunMetrics

__all__ = ["format_summary", "provenance", "rsu_parameters", "run_result", "run_summary"]


def _num(x: float | None) -> float | None:
    """JSON has no infinity: an unmeasured gap or PET is written as null."""
    if x is None or not math.isfinite(x):
        return None
    return round(float(x), 4)


def _knobs(config: object) -> dict[str, Knob]:
    """The scalar fields of a configuration object (dataclass or pydantic model)."""
    if dataclasses.is_dataclass(config) and not isinstance(config, type):
        names = [f.name for f in dataclasses.fields(config)]
    elif isinstance(config, BaseModel):
        names = list(type(config).model_fields)
    else:
        raise TypeError(f"not a configuration object: {config!r}")
    out: dict[str, Knob] = {}
    for name in names:
        value = getattr(config, name)
        if isinstance(value, Enum):
            value = value.value
        if value is None or isinstance(value, bool | int | float | str):
            out[name] = value
    return out


def rsu_parameters(scenario: Scenario, policy: Policy) -> dict[str, dict[str, Knob]]:
    """Every RSU's knobs as its core is configured (``services.rsu.config.rsu_config``, as the
    harness and the RSU daemon build it): its scalar fields, geometry and id left out."""
    out: dict[str, dict[str, Knob]] = {}
    for spec in scenario.rsus:
        knobs = _knobs(rsu_config(scenario, spec.id, policy))
        knobs.pop("rsu_id", None)
        out[spec.id] = knobs
    return out


def provenance(
    scenario: Scenario,
    origin: Origin,
    channel: ChannelParams,
    mode: RunMode,
    policy: Policy,
) -> Provenance:
    """What produced a run of ``scenario`` (the policy and its knobs only in ``rsu`` mode)."""
    rsu = mode is RunMode.RSU
    return Provenance(
        version=origin.version,
        commit=origin.commit,
        scenario=scenario.name,
        scenario_file=origin.scenario_file,
        scenario_sha256=origin.scenario_sha256,
        channel=channel,
        policy=policy if rsu else None,
        policy_params=rsu_parameters(scenario, policy) if rsu else {},
    )


def run_result(
    metrics: RunMetrics,
    *,
    mode: RunMode,
    policy: Policy | None,
    seed: int,
    sim_s: float,
    wall_s: float,
    scenario: str,
    start_times: dict[str, float],
    harness: str,
    provenance: Provenance | None,
    **sections: Any,
) -> RunResult:
    """The run result from one run's metrics; ``sections`` are the optional fields of
    :class:`RunResult` (validated: an unknown name or a bad value raises)."""
    vehicles = {
        vid: VehicleResult(
            passing_time_s=_num(vm.passing_time_s),
            first_through=bool(vm.first_through),
            stops=int(vm.stops),
            max_speed_mps=_num(vm.max_speed_mps),
            finished=bool(vm.finished),
            delay_s=_num(vm.delay_s),
            insertion_delay_s=_num(vm.insertion_delay_s),
        )
        for vid, vm in sorted(metrics.vehicles.items())
    }
    passing = [v.passing_time_s for v in vehicles.values() if v.passing_time_s is not None]
    speedup = round(sim_s / wall_s, 1) if wall_s > 0 else None
    return RunResult.model_validate(
        {
            "mode": mode,
            "policy": policy,
            "seed": seed,
            "collisions": int(metrics.collisions),
            "min_gap_m": _num(metrics.min_gap_m),
            "min_pet_s": _num(metrics.min_pet_s),
            "min_conflict_pet_s": _num(metrics.min_conflict_pet_s),
            "sim_s": round(sim_s, 3),
            "wall_s": round(wall_s, 3),
            "mean_passing_time_s": _num(sum(passing) / len(passing)) if passing else None,
            "all_finished": all(v.finished for v in vehicles.values()),
            "vehicles": vehicles,
            "scenario": scenario,
            "start_times": {vid: round(t, 4) for vid, t in start_times.items()},
            "harness": harness,
            "speedup_vs_real_time": speedup,
            "provenance": provenance,
            **sections,
        }
    )


def run_summary(metrics: RunMetrics, sim_s: float) -> RunSummary:
    """The run's traffic figures (``services.model.results`` defines them) from its metrics."""
    cars = list(metrics.vehicles.values())
    inserted = [vm for vm in cars if vm.inserted_s is not None]
    delays = [vm.delay_s for vm in cars if vm.finished and vm.delay_s is not None]
    finished = sum(1 for vm in cars if vm.finished)
    return RunSummary(
        vehicles_inserted=len(inserted),
        vehicles_finished=finished,
        all_finished=bool(cars) and finished == len(cars),
        mean_delay_s=_num(float(np.mean(delays))) if delays else None,
        p95_delay_s=_num(float(np.percentile(delays, 95.0))) if delays else None,
        throughput_vph=_num(finished * 3600.0 / sim_s) if sim_s > 0 else None,
        stops_per_vehicle=(
            _num(sum(vm.stops for vm in inserted) / len(inserted)) if inserted else None
        ),
    )


def format_summary(result: RunResult) -> str:
    """A short human summary of one run result."""
    loss = result.loss if result.loss is not None else 0
    lines = [
        f"scenario {result.scenario}  mode {result.mode}"
        + (f"  policy {result.policy}" if result.policy else "")
        + f"  seed {result.seed}  loss {loss}",
        f"{'car':<6}{'passing [s]':>12}{'first':>7}{'stops':>7}{'max v [m/s]':>13}",
    ]
    for vid, v in result.vehicles.items():
        pt = "-" if v.passing_time_s is None else f"{v.passing_time_s:.2f}"
        lines.append(
            f"{vid:<6}{pt:>12}{'yes' if v.first_through else 'no':>7}{v.stops:>7}"
            f"{v.max_speed_mps or 0:>13.2f}"
        )
    mean = result.mean_passing_time_s
    gap = result.min_gap_m
    pet = result.min_pet_s
    area = result.min_conflict_pet_s
    lines.append(
        f"mean passing {'-' if mean is None else f'{mean:.2f} s'}"
        f"  collisions {result.collisions}"
        f"  min gap {'-' if gap is None else f'{gap:.2f} m'}"
        f"  min PET {'-' if pet is None else f'{pet:.2f} s'}"
        f" (conflict area {'-' if area is None else f'{area:.2f} s'})"
    )
    speedup = result.speedup_vs_real_time
    lines.append(
        f"simulated {result.sim_s:.1f} s in {result.wall_s:.2f} s wall"
        f" ({'?' if speedup is None else speedup}x real time)"
    )
    return "\n".join(lines)

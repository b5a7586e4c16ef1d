"""The run result of DESIGN.md, built from the metrics of one run (either harness)."""

from __future__ import annotations

import math
from enum import StrEnum
from typing import Any

from services.world.metrics import RunMetrics


class RunMode(StrEnum):
    """The paper's three scenarios."""

    STANDALONE = "standalone"  # no V2X
    FP_ONLY = "fp-only"  # future paths between cars, no RSU
    RSU = "rsu"  # future paths plus the RSU


def _num(x: float | None) -> float | None:
    """JSON has no infinity: an unmeasured gap or PET is written as null."""
    if x is None or not math.isfinite(x):
        return None
    return round(float(x), 4)


def run_result(
    metrics: RunMetrics,
    *,
    mode: RunMode,
    policy: str | None,
    seed: int,
    sim_s: float,
    wall_s: float,
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The JSON-able run result (keys required by DESIGN.md, plus a few more)."""
    vehicles: dict[str, Any] = {}
    for vid, vm in sorted(metrics.vehicles.items()):
        vehicles[vid] = {
            "passing_time_s": _num(vm.passing_time_s),
            "first_through": bool(vm.first_through),
            "stops": int(vm.stops),
            "max_speed_mps": _num(vm.max_speed_mps),
            "finished": bool(vm.finished),
        }
    passing = [v["passing_time_s"] for v in vehicles.values() if v["passing_time_s"] is not None]
    result: dict[str, Any] = {
        "mode": str(mode),
        "policy": policy,
        "seed": seed,
        "collisions": int(metrics.collisions),
        "min_gap_m": _num(metrics.min_gap_m),
        "min_pet_s": _num(metrics.min_pet_s),
        "sim_s": round(sim_s, 3),
        "wall_s": round(wall_s, 3),
        "mean_passing_time_s": _num(sum(passing) / len(passing)) if passing else None,
        "all_finished": all(v["finished"] for v in vehicles.values()),
        "vehicles": vehicles,
    }
    if extra:
        result.update(extra)
    return result

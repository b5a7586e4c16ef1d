"""The run result of DESIGN.md, built from the metrics of one run (either harness)."""

from __future__ import annotations

import math
from typing import Any

from services.model.types import RunMode
from services.sim.metrics import RunMetrics


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


def format_summary(result: dict[str, Any]) -> str:
    """A short human summary of one run result."""
    lines = [
        f"scenario {result.get('scenario', '?')}  mode {result['mode']}"
        + (f"  policy {result['policy']}" if result.get("policy") else "")
        + f"  seed {result['seed']}  loss {result.get('loss', 0)}",
        f"{'car':<6}{'passing [s]':>12}{'first':>7}{'stops':>7}{'max v [m/s]':>13}",
    ]
    for vid, v in result["vehicles"].items():
        pt = "-" if v["passing_time_s"] is None else f"{v['passing_time_s']:.2f}"
        lines.append(
            f"{vid:<6}{pt:>12}{'yes' if v['first_through'] else 'no':>7}{v['stops']:>7}"
            f"{v['max_speed_mps'] or 0:>13.2f}"
        )
    mean = result.get("mean_passing_time_s")
    gap = result["min_gap_m"]
    pet = result["min_pet_s"]
    lines.append(
        f"mean passing {'-' if mean is None else f'{mean:.2f} s'}"
        f"  collisions {result['collisions']}"
        f"  min gap {'-' if gap is None else f'{gap:.2f} m'}"
        f"  min PET {'-' if pet is None else f'{pet:.2f} s'}"
    )
    lines.append(
        f"simulated {result['sim_s']:.1f} s in {result['wall_s']:.2f} s wall"
        f" ({result.get('speedup_vs_real_time', '?')}x real time)"
    )
    return "\n".join(lines)

"""``crosspath bench rsu``: cost of one received future path at the RSU, against brute force.

Scene: a grid of intersections spread over a few kilometres (6 x 6, 500 m
apart), cars on random approach lanes (right-hand traffic, 3.5 m lanes) up to
200 m before an intersection, at random speeds up to ``V_max``, each with a
straight 120-point future path over 10 s through its intersection. One RSU
(coverage stretched over the whole grid, so that every car is in its table)
first receives every car's future path; then, for each measured update, a
future path from a new car on a random lane goes through
``RsuCore.on_message`` (table update, indexed conflict check, mode decision,
and any initiation and coordinated path it causes), and the car is removed
again so that the table keeps its size.

Baseline, in the same run on the same paths: ``ReservationTable.naive_conflicts``
(every point pair of every entry, vectorised per entry), i.e. the conflict
check alone without the index. ``speedup_vs_naive`` is the ratio of medians
(naive check / full update): conservative, the update does more than the check.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from protocol.messages import FuturePath, Header, Mode
from services.edge.args import non_negative_int, output_file, positive_int
from services.edge.progress import Ticker
from services.rsu.config import RsuConfig
from services.rsu.core import RsuCore

V_MAX = 50 / 3.6
GRID = 6
SPACING_M = 500.0
LANE_OFFSET_M = 1.75
ZONE_HALF_M = 3.5
POINTS = 120
HORIZON_S = 10.0
TARGET_SPEEDUP_AT_1000 = 20.0
TARGET_P99_US_AT_100 = 1000.0

# approach directions: heading, lane offset direction (right-hand traffic)
_APPROACHES = (
    (0.0, (0.0, -1.0)),  # eastbound, on the south half
    (math.pi, (0.0, 1.0)),  # westbound, north half
    (math.pi / 2, (1.0, 0.0)),  # northbound, east half
    (-math.pi / 2, (-1.0, 0.0)),  # southbound, west half
)


def _centre(i: int, j: int) -> tuple[float, float]:
    return (i * SPACING_M, j * SPACING_M)


def _config() -> RsuConfig:
    mid = (GRID - 1) / 2 * SPACING_M
    c = _centre(GRID // 2, GRID // 2)
    zone = np.array(
        [
            [c[0] - ZONE_HALF_M, c[1] - ZONE_HALF_M],
            [c[0] + ZONE_HALF_M, c[1] - ZONE_HALF_M],
            [c[0] + ZONE_HALF_M, c[1] + ZONE_HALF_M],
            [c[0] - ZONE_HALF_M, c[1] + ZONE_HALF_M],
        ]
    )
    return RsuConfig("bench-rsu", "bench", (mid, mid), zone, coverage_m=GRID * SPACING_M * 2)


def _random_car(rng: np.random.Generator, vehicle: str, now: float, seq: int) -> FuturePath:
    i, j = int(rng.integers(GRID)), int(rng.integers(GRID))
    heading, (ox, oy) = _APPROACHES[int(rng.integers(4))]
    cx, cy = _centre(i, j)
    back = float(rng.uniform(5.0, 200.0))
    speed = float(rng.uniform(3.0, V_MAX))
    dx, dy = math.cos(heading), math.sin(heading)
    x0 = cx + ox * LANE_OFFSET_M - dx * back
    y0 = cy + oy * LANE_OFFSET_M - dy * back
    t = now + np.linspace(0.0, HORIZON_S, POINTS)
    s = speed * (t - now)
    points = np.column_stack([x0 + dx * s, y0 + dy * s, t])
    header = Header(vehicle, seq, round(now * 1e6))
    return FuturePath(header, x0, y0, speed, heading, 4.5, 1.8, Mode.AUTO, points)


def _percentile(samples: Sequence[float], q: float) -> float:
    return float(np.percentile(np.asarray(samples, dtype=np.float64), q))


def measure_one(cars: int, updates: int, naive_updates: int, seed: int) -> dict[str, Any]:
    """One table size: per-update cost through ``on_message`` and of the naive check [µs]."""
    rng = np.random.default_rng(seed)
    core = RsuCore(_config(), listen_s=0.0)  # decide from the first path: that is measured
    for k in range(cars):
        core.on_message(0.0, _random_car(rng, f"car-{k}", 0.0, 1))
    now = 0.2  # every entry is still live (expiry 0.5 s)
    probes = [_random_car(rng, "probe", now, 1 + k) for k in range(updates)]
    for probe in probes[: min(20, updates)]:  # warm-up
        core.on_message(now, probe)
        core.forget("probe")
    full: list[float] = []
    query: list[float] = []
    naive: list[float] = []
    outgoing = 0
    clock = time.perf_counter_ns
    for probe in probes:
        t0 = clock()
        out = core.on_message(now, probe)
        t1 = clock()
        full.append((t1 - t0) / 1e3)
        outgoing += len(out)
        core.forget("probe")
        t0 = clock()
        core.table.conflicts("probe", probe.points, now, core.config.t_free_s)
        query.append((clock() - t0) / 1e3)
    for probe in probes[:naive_updates]:
        t0 = clock()
        core.table.naive_conflicts("probe", probe.points, now, core.config.t_free_s)
        naive.append((clock() - t0) / 1e3)
    p50 = _percentile(full, 50)
    naive_p50 = _percentile(naive, 50)
    modes = core.modes().values()
    return {
        "cars": cars,
        "table_size": len(core.table),
        "updates": len(full),
        "naive_updates": len(naive),
        "us_per_update_p50": round(p50, 2),
        "us_per_update_p99": round(_percentile(full, 99), 2),
        "us_per_update_mean": round(float(np.mean(full)), 2),
        "query_us_p50": round(_percentile(query, 50), 2),
        "naive_us_per_update_p50": round(naive_p50, 2),
        "naive_us_per_update_p99": round(_percentile(naive, 99), 2),
        "speedup_vs_naive": round(naive_p50 / p50, 2) if p50 > 0 else None,
        "query_speedup_vs_naive": round(naive_p50 / _percentile(query, 50), 2),
        "messages_per_update": round(outgoing / len(full), 3),
        "coordinated_in_table": sum(1 for m in modes if m != Mode.AUTO),
    }


def measure(
    cars: Sequence[int] = (10, 100, 1000),
    updates: int = 500,
    naive_updates: int = 50,
    seed: int = 1,
) -> dict[str, Any]:
    """Run every table size; the JSON document ``bench rsu`` writes."""
    if updates < 1 or naive_updates < 1 or any(n < 0 for n in cars):
        raise ValueError("updates and naive_updates must be >= 1, car counts >= 0")
    results = [measure_one(n, updates, naive_updates, seed + i) for i, n in enumerate(cars)]
    by_cars = {r["cars"]: r for r in results}
    met: dict[str, bool] = {}
    if 1000 in by_cars:
        met["speedup_vs_naive_at_1000"] = (
            by_cars[1000]["speedup_vs_naive"] or 0.0
        ) >= TARGET_SPEEDUP_AT_1000
    if 100 in by_cars:
        met["p99_at_100"] = by_cars[100]["us_per_update_p99"] <= TARGET_P99_US_AT_100
    return {
        "bench": "rsu",
        "scene": {
            "intersections": GRID * GRID,
            "spacing_m": SPACING_M,
            "points_per_path": POINTS,
            "horizon_s": HORIZON_S,
        },
        "targets": {
            "speedup_vs_naive_at_1000": TARGET_SPEEDUP_AT_1000,
            "us_per_update_p99_at_100": TARGET_P99_US_AT_100,
            "met": met,
        },
        "results": results,
    }


def configure(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath bench rsu``; bad values are refused while parsing."""
    parser.add_argument("--json", metavar="OUT", type=output_file, help="write the results as JSON")
    parser.add_argument(
        "--cars",
        metavar="N",
        type=non_negative_int,
        nargs="+",
        default=[10, 100, 1000],
        help="table sizes to measure",
    )
    parser.add_argument(
        "--updates", type=positive_int, default=500, help="measured updates per size"
    )
    parser.add_argument(
        "--naive-updates",
        type=positive_int,
        default=50,
        help="naive checks per size (they are slow)",
    )
    parser.add_argument(
        "--seed", type=non_negative_int, default=1, help="seed of the first table's paths"
    )


def run(args: argparse.Namespace) -> int:
    """Measure and print; a status line on stderr while it runs (on a terminal only)."""
    sizes = " ".join(str(n) for n in args.cars)
    with Ticker("crosspath bench rsu", lambda: f"tables of {sizes} cars"):
        doc = measure(args.cars, args.updates, args.naive_updates, args.seed)
    print(
        f"{'cars':>6} {'p50 µs':>9} {'p99 µs':>9} {'query µs':>9} {'naive µs':>10} {'speedup':>8}"
    )
    for r in doc["results"]:
        print(
            f"{r['cars']:>6} {r['us_per_update_p50']:>9.1f} {r['us_per_update_p99']:>9.1f} "
            f"{r['query_us_p50']:>9.1f} {r['naive_us_per_update_p50']:>10.1f} "
            f"{r['speedup_vs_naive']:>7.1f}x"
        )
    for name, ok in doc["targets"]["met"].items():
        print(f"target {name}: {'met' if ok else 'NOT met'}")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(doc, indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0

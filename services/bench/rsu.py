"""``crosspath bench rsu``: cost of one received future path at the RSU, against brute force.

Two layouts (issue 14), each a list of table sizes:

``one-intersection``
    the case that matters, a jam: every car on a random approach lane (right-hand
    traffic, 3.5 m lanes) of one 4-way intersection, 5-200 m before its turn, at a
    random speed up to ``V_max``, going straight (half of them) or turning left
    (8 m radius) or right (5 m radius), a 120-point future path over 10 s.
``city``
    the same cars spread over a grid of 50 intersections (10 x 5, 500 m apart),
    going straight; one RSU whose coverage is stretched over the whole grid so
    that every car is in its table.

The RSU first receives every car's future path while it still only listens
(``listen_s``: table updates, no decisions; deciding for a jam car by car would
take minutes at 1000 cars); then, after its listening period, for each measured
update (after ``_WARM_UP`` unmeasured ones),
a future path from a new car of the same layout goes through
``RsuCore.on_message`` (table update, indexed conflict check, mode decision, and
any initiation and coordinated path it causes), and the car is removed again so
that the table keeps its size. Times are this process's CPU time per update
(``process_time_ns``: on a shared 2-core machine wall time also counts the other
processes' turns, eight times the CPU time in one run under load): p50 and p99.

Baseline, in the same run on the same paths: ``ReservationTable.naive_conflicts``
(every point pair of every entry, vectorised per entry, one exact check per car; it
derives each entry's headings on the way, which the table no longer stores: about a
tenth of its time), i.e. the conflict check alone without the index.
``speedup_vs_naive`` is the ratio of medians (naive check / full update):
conservative, the update does more than the check. The query alone is timed twice: as
the RSU runs it (``query_us_p50``: with the C kernel ``services/rsu/_scan.c`` when it was
built, ``scene.c_scan``) and on the numpy path it replaces (``query_numpy_us_p50``, on the
naive check's probes), the baseline of the kernel in the same run. ``scene.c_paths`` says
whether the path projections run in C too (``services.rsu.paths.use_kernel``).

``bytes_per_car``: what the RSU keeps per car, by ``tracemalloc``: the memory
still allocated after the second half of the cars was received (the messages
themselves dropped) minus that after the first half, over the second half's
cars, so that the RSU's fixed allocations do not count.

``targets.met`` says where it stands against the issue's targets.
"""

from __future__ import annotations

import argparse
import json
import math
import time
import tracemalloc
from collections.abc import Sequence
from typing import Any

import numpy as np

from protocol.messages import FloatArray, FuturePath, Header, Mode
from services.edge.args import non_negative_int, output_file, positive_int
from services.edge.progress import Ticker
from services.rsu import paths, reservation
from services.rsu.config import RsuConfig
from services.rsu.core import RsuCore

V_MAX = 50 / 3.6
GRID = (10, 5)
SPACING_M = 500.0
LAYOUTS = ("one-intersection", "city")
TURN_RADIUS_M = {"left": 8.0, "right": 5.0}
DEFAULT_CASES: tuple[tuple[str, int], ...] = (
    ("one-intersection", 10),
    ("one-intersection", 100),
    ("one-intersection", 200),
    ("one-intersection", 1000),
    ("city", 1000),
)
LANE_OFFSET_M = 1.75
ZONE_HALF_M = 3.5
POINTS = 120
HORIZON_S = 10.0
_WARM_UP = 5
"""Unmeasured updates before the measured ones (the first decisions after listening)."""

_LISTEN_S = 0.1
"""The RSU only listens this long after its first input [s]: while the table fills."""

TARGETS: dict[str, float] = {
    "us_per_update_p50_at_200": 250.0,
    "us_per_update_p99_at_200": 1000.0,
    "speedup_vs_naive_at_200": 10.0,
    "speedup_vs_naive_at_1000": 20.0,
    "bytes_per_car": 4096.0,
}
"""Issue 14's targets, all for the one-intersection layout."""

# approach directions: heading, lane offset direction (right-hand traffic)
_APPROACHES = (
    (0.0, (0.0, -1.0)),  # eastbound, on the south half
    (math.pi, (0.0, 1.0)),  # westbound, north half
    (math.pi / 2, (1.0, 0.0)),  # northbound, east half
    (-math.pi / 2, (-1.0, 0.0)),  # southbound, west half
)


def _centre(i: int, j: int) -> tuple[float, float]:
    return (i * SPACING_M, j * SPACING_M)


def _zone(c: tuple[float, float]) -> FloatArray:
    return np.array(
        [
            [c[0] - ZONE_HALF_M, c[1] - ZONE_HALF_M],
            [c[0] + ZONE_HALF_M, c[1] - ZONE_HALF_M],
            [c[0] + ZONE_HALF_M, c[1] + ZONE_HALF_M],
            [c[0] - ZONE_HALF_M, c[1] + ZONE_HALF_M],
        ]
    )


def _config(layout: str) -> RsuConfig:
    if layout == "one-intersection":
        return RsuConfig("bench-rsu", "bench", (0.0, 0.0), _zone((0.0, 0.0)), coverage_m=400.0)
    mid = ((GRID[0] - 1) / 2 * SPACING_M, (GRID[1] - 1) / 2 * SPACING_M)
    c = _centre(GRID[0] // 2, GRID[1] // 2)
    span = max(GRID) * SPACING_M * 2
    return RsuConfig("bench-rsu", "bench", mid, _zone(c), coverage_m=span)


def _local_path(s: FloatArray, back: float, turn: str) -> tuple[FloatArray, FloatArray]:
    """x, y [m] at arc lengths ``s`` of an eastbound car on y = -1.75 m turning at (0, 0).

    The car starts ``back`` metres before the start of its turn (before the centre
    when going straight); a left turn ends northbound on x = 1.75 m, a right turn
    southbound on x = -1.75 m (right-hand traffic).
    """
    lane = LANE_OFFSET_M
    if turn == "straight":
        return s - back, np.full_like(s, -lane)
    radius = TURN_RADIUS_M[turn]
    arc = math.pi / 2 * radius
    angle = np.clip(s - back, 0.0, arc) / radius
    after = np.maximum(s - back - arc, 0.0)
    before = np.minimum(s - back, 0.0)
    if turn == "left":
        x0, sign = lane - radius, 1.0
    else:
        x0, sign = -lane - radius, -1.0
    x = x0 + before + radius * np.sin(angle)
    y = -lane + sign * (radius * (1.0 - np.cos(angle)) + after)
    return x, y


def _intersection_car(rng: np.random.Generator, vehicle: str, now: float, seq: int) -> FuturePath:
    """A car of the one-intersection layout (module docstring)."""
    heading = _APPROACHES[int(rng.integers(4))][0]
    turn = ("straight", "straight", "left", "right")[int(rng.integers(4))]
    back = float(rng.uniform(5.0, 200.0))
    speed = float(rng.uniform(3.0, V_MAX))
    t = now + np.linspace(0.0, HORIZON_S, POINTS)
    lx, ly = _local_path(speed * (t - now), back, turn)
    cos, sin = math.cos(heading), math.sin(heading)
    x, y = cos * lx - sin * ly, sin * lx + cos * ly
    points = np.column_stack([x, y, t])
    header = Header(vehicle, seq, round(now * 1e6))
    return FuturePath(header, float(x[0]), float(y[0]), speed, heading, 4.5, 1.8, Mode.AUTO, points)


def _random_car(rng: np.random.Generator, vehicle: str, now: float, seq: int) -> FuturePath:
    """A car of the city layout (module docstring)."""
    i, j = int(rng.integers(GRID[0])), int(rng.integers(GRID[1]))
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


def measure_one(
    cars: int, updates: int, naive_updates: int, seed: int, layout: str = "one-intersection"
) -> dict[str, Any]:
    """One layout and table size: cost per update through ``on_message`` and of the naive
    check [µs], and the RSU's memory per car [bytes]."""
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
    make = _intersection_car if layout == "one-intersection" else _random_car
    rng = np.random.default_rng(seed)
    tracing = tracemalloc.is_tracing()
    if not tracing:
        tracemalloc.start()
    # filled while still listening (table updates only): deciding for a jam car by car
    # would take minutes at 1000 cars; the measured updates come after the listening
    core = RsuCore(_config(layout), listen_s=_LISTEN_S)
    half = cars // 2
    for k in range(half):
        core.on_message(0.0, make(rng, f"car-{k}", 0.0, 1))
    at_half = tracemalloc.get_traced_memory()[0]
    for k in range(half, cars):
        core.on_message(0.0, make(rng, f"car-{k}", 0.0, 1))
    kept = tracemalloc.get_traced_memory()[0] - at_half
    if not tracing:
        tracemalloc.stop()
    now = 0.2  # listening is over; every entry is still live (expiry 0.5 s)
    probes = [make(rng, "probe", now, 1 + k) for k in range(updates)]
    for probe in probes[: min(_WARM_UP, updates)]:
        core.on_message(now, probe)
        core.forget("probe")
    full: list[float] = []
    query: list[float] = []
    naive: list[float] = []
    outgoing = 0
    clock = time.process_time_ns  # CPU time: on a shared machine wall time counts others' turns
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
    numpy_query: list[float] = []  # the same query on the numpy path (no C kernel)
    previous = reservation.use_scan(False)
    try:
        for probe in probes[:naive_updates]:
            t0 = clock()
            core.table.conflicts("probe", probe.points, now, core.config.t_free_s)
            numpy_query.append((clock() - t0) / 1e3)
    finally:
        reservation.use_scan(previous)
    p50 = _percentile(full, 50)
    naive_p50 = _percentile(naive, 50)
    modes = core.modes().values()
    return {
        "layout": layout,
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
        "query_numpy_us_p50": round(_percentile(numpy_query, 50), 2),
        "messages_per_update": round(outgoing / len(full), 3),
        "coordinated_in_table": sum(1 for m in modes if m != Mode.AUTO),
        "bytes_per_car": round(kept / (cars - half)) if cars - half else None,
    }


def measure(
    cases: Sequence[tuple[str, int]] = DEFAULT_CASES,
    updates: int = 200,
    naive_updates: int = 20,
    seed: int = 1,
) -> dict[str, Any]:
    """Run every (layout, cars) case; the JSON document ``bench rsu`` writes.

    Tables of 1000 cars or more get a fifth of ``updates`` (at least 20): one update
    costs up to a tenth of a second there.
    """
    if updates < 1 or naive_updates < 1 or any(n < 0 for _, n in cases):
        raise ValueError("updates and naive_updates must be >= 1, car counts >= 0")
    results = []
    for i, (layout, n) in enumerate(cases):
        k = updates if n < 1000 else max(min(updates, 20), updates // 5)
        results.append(measure_one(n, k, min(naive_updates, k), seed + i, layout))
    at = {r["cars"]: r for r in results if r["layout"] == "one-intersection"}
    met: dict[str, bool] = {}
    if 200 in at:
        met["us_per_update_p50_at_200"] = (
            at[200]["us_per_update_p50"] <= TARGETS["us_per_update_p50_at_200"]
        )
        met["us_per_update_p99_at_200"] = (
            at[200]["us_per_update_p99"] <= TARGETS["us_per_update_p99_at_200"]
        )
        met["speedup_vs_naive_at_200"] = (at[200]["speedup_vs_naive"] or 0.0) >= TARGETS[
            "speedup_vs_naive_at_200"
        ]
    if 1000 in at:
        met["speedup_vs_naive_at_1000"] = (at[1000]["speedup_vs_naive"] or 0.0) >= TARGETS[
            "speedup_vs_naive_at_1000"
        ]
    per_car = [r["bytes_per_car"] for r in at.values() if r["cars"] >= 100]
    if per_car:
        met["bytes_per_car"] = max(per_car) <= TARGETS["bytes_per_car"]
    return {
        "bench": "rsu",
        "scene": {
            "layouts": list(LAYOUTS),
            "city_intersections": GRID[0] * GRID[1],
            "spacing_m": SPACING_M,
            "points_per_path": POINTS,
            "horizon_s": HORIZON_S,
            "c_scan": reservation._SCAN is not None,
            "c_paths": paths.kernel() is not None,
        },
        "targets": {**TARGETS, "met": met},
        "cases": results,
    }


def configure(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath bench rsu``; bad values are refused while parsing."""
    parser.add_argument("--json", metavar="OUT", type=output_file, help="write the results as JSON")
    parser.add_argument(
        "--cars",
        metavar="N",
        type=non_negative_int,
        nargs="*",
        default=[n for layout, n in DEFAULT_CASES if layout == "one-intersection"],
        help="table sizes of the one-intersection layout",
    )
    parser.add_argument(
        "--city-cars",
        metavar="N",
        type=non_negative_int,
        nargs="*",
        default=[n for layout, n in DEFAULT_CASES if layout == "city"],
        help="table sizes of the city layout (50 intersections)",
    )
    parser.add_argument(
        "--updates", type=positive_int, default=200, help="measured updates per size"
    )
    parser.add_argument(
        "--naive-updates",
        type=positive_int,
        default=20,
        help="naive checks per size (they are slow)",
    )
    parser.add_argument(
        "--seed", type=non_negative_int, default=1, help="seed of the first table's paths"
    )


def run(args: argparse.Namespace) -> int:
    """Measure and print; a status line on stderr while it runs (on a terminal only)."""
    cases = [("one-intersection", n) for n in args.cars] + [("city", n) for n in args.city_cars]
    label = ", ".join(f"{layout} {n}" for layout, n in cases)
    with Ticker("crosspath bench rsu", lambda: label):
        doc = measure(cases, args.updates, args.naive_updates, args.seed)
    print(
        f"{'layout':<17} {'cars':>6} {'p50 µs':>9} {'p99 µs':>9} {'query µs':>9} "
        f"{'numpy µs':>9} {'naive µs':>10} {'speedup':>8} {'B/car':>7}"
    )
    for r in doc["cases"]:
        print(
            f"{r['layout']:<17} {r['cars']:>6} {r['us_per_update_p50']:>9.1f} "
            f"{r['us_per_update_p99']:>9.1f} {r['query_us_p50']:>9.1f} "
            f"{r['query_numpy_us_p50']:>9.1f} {r['naive_us_per_update_p50']:>10.1f} "
            f"{r['speedup_vs_naive']:>7.1f}x "
            f"{r['bytes_per_car'] or 0:>7}"
        )
    for name, ok in doc["targets"]["met"].items():
        print(f"target {name}: {'met' if ok else 'NOT met'}")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(doc, indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0

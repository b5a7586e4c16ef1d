"""``crosspath bench rsu``: the JSON it produces (keys and sanity, never timings)."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import pytest

from services.bench import rsu
from services.rsu import reservation

KEYS = {
    "layout",
    "cars",
    "us_per_update_p50",
    "us_per_update_p99",
    "naive_us_per_update_p50",
    "speedup_vs_naive",
    "bytes_per_car",
}


def test_measure_small() -> None:
    cases = (("one-intersection", 5), ("one-intersection", 20), ("city", 20))
    doc = rsu.measure(cases, updates=6, naive_updates=3, seed=4)
    assert doc["bench"] == "rsu"
    results = doc["cases"]
    assert [(r["layout"], r["cars"]) for r in results] == list(cases)
    for r in results:
        assert set(r) >= KEYS
        assert r["table_size"] == r["cars"]  # the probe car was removed again every time
        assert r["updates"] == 6 and r["naive_updates"] == 3
        assert 0 < r["us_per_update_p50"] <= r["us_per_update_p99"]
        assert r["naive_us_per_update_p50"] > 0 and r["speedup_vs_naive"] > 0
        assert r["query_us_p50"] > 0 and r["query_numpy_us_p50"] > 0
        assert r["bytes_per_car"] > 0  # each car's path is kept
    assert set(doc["targets"]["met"]) == set()  # no 100 / 200 / 1000 case in this run
    assert doc["scene"]["city_intersections"] == 50
    assert doc["scene"]["c_scan"] is reservation.scan_available()
    assert doc["scene"]["c_paths"] is reservation.scan_available()  # the same module
    json.dumps(doc)  # plain JSON values only


@pytest.mark.parametrize("turn", ["straight", "left", "right"])
def test_intersection_paths_turn_into_their_lane(turn: str) -> None:
    s = np.linspace(0.0, 80.0, 200)
    x, y = rsu._local_path(s, 20.0, turn)
    steps = np.hypot(np.diff(x), np.diff(y))
    assert np.allclose(steps, s[1] - s[0], rtol=0.02)  # constant speed along the path
    assert y[0] == -rsu.LANE_OFFSET_M  # eastbound, right-hand lane
    end = {"straight": (1.0, 0.0), "left": (0.0, 1.0), "right": (0.0, -1.0)}[turn]
    assert np.allclose([x[-1] - x[-2], y[-1] - y[-2]] / steps[-1], end, atol=1e-6)
    if turn != "straight":
        lane = rsu.LANE_OFFSET_M if turn == "left" else -rsu.LANE_OFFSET_M
        assert x[-1] == pytest.approx(lane)


def test_intersection_cars_all_cross_the_one_intersection() -> None:
    rng = np.random.default_rng(3)
    for k in range(40):
        car = rsu._intersection_car(rng, f"c{k}", 0.0, 1)
        near = np.hypot(car.points[:, 0], car.points[:, 1]).min()
        heading = math.atan2(
            car.points[1, 1] - car.points[0, 1], car.points[1, 0] - car.points[0, 0]
        )
        assert heading == pytest.approx(car.heading, abs=1e-6) or near > 190  # starts straight
        assert car.points.shape == (rsu.POINTS, 3)


def test_run_writes_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    parser = argparse.ArgumentParser()
    rsu.configure(parser)
    out = tmp_path / "bench" / "rsu.json"
    args = parser.parse_args(
        [
            "--json",
            str(out),
            "--cars",
            "3",
            "200",
            "--city-cars",
            "--updates",
            "3",
            "--naive-updates",
            "2",
        ]
    )
    assert rsu.run(args) == 0
    doc = json.loads(out.read_text())
    assert [(r["layout"], r["cars"]) for r in doc["cases"]] == [
        ("one-intersection", 3),
        ("one-intersection", 200),
    ]
    assert set(doc["targets"]["met"]) == {
        "us_per_update_p50_at_200",
        "us_per_update_p99_at_200",
        "speedup_vs_naive_at_200",
        "bytes_per_car",
    }
    assert "speedup" in capsys.readouterr().out


def test_bad_arguments_raise() -> None:
    with pytest.raises(ValueError):
        rsu.measure((("one-intersection", 5),), updates=0)
    with pytest.raises(ValueError):
        rsu.measure_one(5, 3, 1, 0, layout="ring")

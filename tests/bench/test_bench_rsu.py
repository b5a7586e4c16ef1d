"""``crosspath bench rsu``: the JSON it produces (keys and sanity, never timings)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

from services.bench import rsu

KEYS = {
    "cars",
    "us_per_update_p50",
    "us_per_update_p99",
    "naive_us_per_update_p50",
    "speedup_vs_naive",
}


def test_measure_small() -> None:
    doc = rsu.measure(cars=(5, 40), updates=12, naive_updates=3, seed=4)
    assert doc["bench"] == "rsu"
    results = doc["results"]
    assert [r["cars"] for r in results] == [5, 40]
    for r in results:
        assert set(r) >= KEYS
        assert r["table_size"] == r["cars"]  # the probe car was removed again every time
        assert r["updates"] == 12 and r["naive_updates"] == 3
        assert 0 < r["us_per_update_p50"] <= r["us_per_update_p99"]
        assert r["naive_us_per_update_p50"] > 0 and r["speedup_vs_naive"] > 0
        assert r["query_us_p50"] > 0
    assert set(doc["targets"]["met"]) == set()  # no 100 / 1000 case in this run
    json.dumps(doc)  # plain JSON values only


def test_run_writes_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    parser = argparse.ArgumentParser()
    rsu.configure(parser)
    out = tmp_path / "bench" / "rsu.json"
    args = parser.parse_args(
        ["--json", str(out), "--cars", "3", "100", "--updates", "5", "--naive-updates", "2"]
    )
    assert rsu.run(args) == 0
    doc = json.loads(out.read_text())
    assert [r["cars"] for r in doc["results"]] == [3, 100]
    assert set(doc["targets"]["met"]) == {"p99_at_100"}
    assert "speedup" in capsys.readouterr().out


def test_bad_arguments_raise() -> None:
    with pytest.raises(ValueError):
        rsu.measure(cars=(5,), updates=0)

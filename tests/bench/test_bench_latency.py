"""``crosspath bench latency``: two loopback Zenoh sessions, per-stream keys (never timings)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

from services.bench import latency


def test_measure_splits_transport_and_age(tmp_path: Path) -> None:
    parser = argparse.ArgumentParser()
    latency.configure(parser)
    out = tmp_path / "latency.json"
    args = parser.parse_args(["--cars", "4", "--seconds", "1", "--json", str(out)])
    assert latency.run(args) == 0
    doc = json.loads(out.read_text())
    assert doc["sent"] == 4 * 10 * 2
    assert doc["received"] >= doc["sent"] * 0.8  # best effort, loopback
    assert set(doc["streams"]) == {"fp", "cmd"}
    for stream in doc["streams"].values():
        tr, age = stream["transport"], stream["age"]
        assert tr["n"] > 0 and age["n"] == tr["n"]
        assert 0 < tr["p50_ms"] <= tr["p99_ms"] <= tr["max_ms"]
        # the planning instant comes before the publish call: age includes transport
        assert age["p50_ms"] >= tr["p50_ms"]
    assert set(doc["targets"]["met"]) == {"transport_p99"}


def test_bad_arguments_raise() -> None:
    with pytest.raises(ValueError):
        latency.measure(cars=0)
    with pytest.raises(ValueError):
        latency.measure(duration_s=0.0)

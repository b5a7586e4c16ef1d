"""Traffic counters, latency percentiles and the run's network section on crafted numbers."""

from __future__ import annotations

import json
import math

import pytest

from protocol.keys import Stream
from services.edge.stats import (
    LatencyHistogram,
    NodeStats,
    StreamStats,
    merge_snapshots,
    network_section,
)


def test_percentiles_within_bucket_resolution() -> None:
    hist = LatencyHistogram()
    for ms in range(1, 101):  # 1..100 ms
        hist.add(ms / 1000)
    assert hist.count == 100
    assert hist.percentile(0.5) == pytest.approx(0.050, rel=0.025)
    assert hist.percentile(0.99) == pytest.approx(0.099, rel=0.025)
    assert hist.percentile(1.0) == pytest.approx(0.100, rel=0.025)
    assert hist.percentile(0.01) == pytest.approx(0.001, rel=0.025)
    assert hist.mean_s == pytest.approx(0.0505)


def test_single_value_is_exact_and_empty_is_none() -> None:
    hist = LatencyHistogram()
    assert hist.percentile(0.5) is None and hist.mean_s is None
    hist.add(0.0123)
    assert hist.percentile(0.5) == 0.0123  # clamped to the observed min/max
    assert hist.percentile(0.99) == 0.0123


def test_negative_latency_counts_as_zero() -> None:
    hist = LatencyHistogram()
    hist.add(-0.002)
    hist.add(0.004)
    assert hist.negative == 1
    assert hist.percentile(0.5) == 0.0
    with pytest.raises(ValueError):
        hist.add(math.nan)
    with pytest.raises(ValueError):
        hist.percentile(0.0)


def test_node_stats_snapshot_roundtrips_through_json() -> None:
    node = NodeStats("car-a")
    node.on_send(Stream.FP, 700)
    node.on_send(Stream.FP, 720)
    node.on_receive(Stream.FP, 690, 0.003)
    node.on_receive(Stream.CMD, 300)
    node.on_malformed(Stream.FP)
    node.on_stale(Stream.CMD)
    snapshot = json.loads(json.dumps(node.snapshot(now=12.5)))
    assert snapshot["node"] == "car-a" and snapshot["time_s"] == 12.5
    fp = StreamStats.from_json(snapshot["streams"]["fp"])
    assert (fp.msgs_tx, fp.bytes_tx, fp.msgs_rx, fp.bytes_rx, fp.malformed) == (2, 1420, 1, 690, 1)
    assert fp.latency.percentile(0.5) == pytest.approx(0.003)
    cmd = StreamStats.from_json(snapshot["streams"]["cmd"])
    assert (cmd.msgs_rx, cmd.dropped_stale, cmd.latency.count) == (1, 1, 0)


def test_merge_is_exact_over_nodes() -> None:
    a, b = NodeStats("a"), NodeStats("b")
    for i in range(50):
        a.on_receive("fp", 100, 0.001 * (i + 1))  # 1..50 ms
        b.on_receive("fp", 100, 0.001 * (i + 51))  # 51..100 ms
    merged = merge_snapshots([a.snapshot(), b.snapshot()])
    assert merged["fp"].msgs_rx == 100 and merged["fp"].bytes_rx == 10_000
    assert merged["fp"].latency.percentile(0.5) == pytest.approx(0.050, rel=0.025)
    assert merged["fp"].latency.min_s == pytest.approx(0.001)
    assert merged["fp"].latency.max_s == pytest.approx(0.100)


def test_network_section_on_crafted_numbers() -> None:
    # Two cars broadcast 100 future paths each (800 B); one RSU listens.
    # Each fp should reach the other car and the RSU: 2 expected receivers.
    car_a, car_b, rsu = NodeStats("car-a"), NodeStats("car-b"), NodeStats("rsu-1")
    for _ in range(100):
        car_a.on_send("fp", 800)
        car_b.on_send("fp", 800)
    for _ in range(90):  # car-a hears 90 of car-b's
        car_a.on_receive("fp", 800, 0.002)
    for _ in range(100):  # car-b hears all of car-a's
        car_b.on_receive("fp", 800, 0.004)
    for _ in range(190):  # the RSU hears 190 of 200
        rsu.on_receive("fp", 800, 0.003)
    for _ in range(10):  # RSU -> car-a commands, all received
        rsu.on_send("cmd", 200)
        car_a.on_receive("cmd", 200, 0.001)
    snapshots = [car_a.snapshot(), car_b.snapshot(), rsu.snapshot()]

    section = network_section(
        snapshots, n_vehicles=2, duration_s=10.0, expected_receivers={"fp": 2, "cmd": 1}
    )
    fp = section["fp"]
    assert fp["msgs"] == 200 and fp["bytes"] == 160_000
    assert fp["msgs_rx"] == 380
    assert fp["delivery_ratio"] == pytest.approx(380 / 400)
    assert fp["kbps_per_vehicle"] == pytest.approx(160_000 * 8 / 1000 / 10.0 / 2)  # 64 kbit/s
    assert fp["latency_ms_p50"] == pytest.approx(3.0, rel=0.025)
    assert fp["latency_ms_p99"] == pytest.approx(4.0, rel=0.025)
    cmd = section["cmd"]
    assert cmd["delivery_ratio"] == 1.0
    assert cmd["kbps_per_vehicle"] == pytest.approx(2000 * 8 / 1000 / 10.0 / 2)
    required = {"msgs", "bytes", "kbps_per_vehicle", "latency_ms_p50", "latency_ms_p99"}
    assert required | {"delivery_ratio"} <= set(fp)
    json.dumps(section)  # JSON-able

    unknown = network_section(snapshots, n_vehicles=2, duration_s=10.0, expected_receivers={})
    assert unknown["fp"]["delivery_ratio"] is None


def test_network_section_refuses_nonsense() -> None:
    with pytest.raises(ValueError):
        network_section([], n_vehicles=0, duration_s=1.0, expected_receivers={})
    with pytest.raises(ValueError):
        network_section([], n_vehicles=1, duration_s=0.0, expected_receivers={})
    with pytest.raises(ValueError, match="malformed"):
        merge_snapshots([{"node": "x"}])
    with pytest.raises(ValueError, match="malformed"):
        merge_snapshots([{"streams": {"fp": {"msgs_rx": -1}}}])
    with pytest.raises(ValueError, match="malformed"):
        merge_snapshots([{"streams": {"fp": {"latency": {"count": 2, "buckets": {"3": 1}}}}}])

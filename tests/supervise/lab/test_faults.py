"""Fault injection on the air: loss (independent, bursty, ingress/egress), rate, crash."""

from __future__ import annotations

import signal
from collections.abc import Iterator

import pytest

from services.supervise.lab.faults import (
    AirCounters,
    AirFaults,
    Direction,
    Loss,
    Rate,
    air_counters,
    apply,
    clear,
    crash,
    kill,
    loss_ruleset,
    set_loss,
    set_rate,
)
from services.supervise.lab.netns import Lab, LabError
from tests.supervise.lab.conftest import tcp_transfer, udp_transfer

# ----------------------------------------------------------------------------- models (no root)


def test_independent_loss_is_one_probability() -> None:
    loss = Loss(0.3)
    assert loss.p_enter == pytest.approx(0.3)
    assert loss.p_leave == 0.0
    script = loss_ruleset("air0", loss)
    assert 'hook ingress device "air0"' in script
    assert "numgen random mod 1000000 < 300000" in script
    assert "@bad" not in script.split("flush set")[1]


def test_gilbert_parameters_give_the_asked_loss_and_burst() -> None:
    loss = Loss(0.3, burst=5)
    p, r = loss.p_enter, loss.p_leave
    assert r == pytest.approx(0.2)
    assert p / (p + r) == pytest.approx(0.3)  # stationary loss
    script = loss_ruleset("air0", loss)
    assert "ip saddr @bad" in script
    assert "delete @bad { ip saddr }" in script
    assert "add @bad { ip saddr }" in script


def test_egress_loss_matches_the_sender_side() -> None:
    script = loss_ruleset("air0", Loss(0.1, burst=2, direction=Direction.EGRESS))
    assert 'hook egress device "air0"' in script
    assert "ingress" not in script
    assert "ip daddr @bad" in script
    # An ingress chain left from an earlier call is emptied, not left dropping.
    again = loss_ruleset("air0", Loss(0.1, direction=Direction.EGRESS), ["ingress"])
    assert "flush chain netdev crosspath_lab ingress" in again


def test_extreme_losses_need_no_random_draw() -> None:
    assert "numgen" not in loss_ruleset("air0", Loss(1.0, burst=3))
    zero = loss_ruleset("air0", Loss(0.0))
    assert "numgen" not in zero
    assert not any(line.endswith(" drop") for line in zero.splitlines())


@pytest.mark.parametrize(
    ("ratio", "burst", "match"),
    [
        (-0.01, None, "0..1"),
        (1.005, None, "0..1"),
        (30.0, None, "0..1"),  # a percentage is not a fraction
        (float("nan"), None, "0..1"),
        (0.3, 0.5, ">= 1"),
        (0.9, 5.0, "at least 9"),
    ],
)
def test_impossible_loss_models_are_refused(ratio: float, burst: float | None, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        Loss(ratio, burst)


def test_rate_bucket_defaults_and_validation() -> None:
    dsrc = Rate.of(6.0)
    assert dsrc.burst_bytes == 3750  # 5 ms at 6 Mbit/s
    assert Rate.of(0.1).burst_bytes == 3028  # never below two full frames
    assert dsrc.tc_args("air0")[:7] == ["qdisc", "replace", "dev", "air0", "root", "tbf", "rate"]
    assert "6000kbit" in dsrc.tc_args("air0")
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="rate"):
            Rate.of(bad)
    with pytest.raises(ValueError, match="burst"):
        Rate.of(6.0, burst_bytes=100)


# ----------------------------------------------------------------------------- real lab (root)


@pytest.fixture
def lab(lab3: Lab) -> Iterator[Lab]:
    """The module's three-node lab, with every fault cleared after each test."""
    yield lab3
    for node in lab3.plan.names:
        clear(lab3, node)


def _loss_runs(seqs: list[int], sent: int) -> list[int]:
    """Lengths of the runs of consecutive lost sequence numbers."""
    got = set(seqs)
    runs, run = [], 0
    for seq in range(sent):
        if seq in got:
            if run:
                runs.append(run)
            run = 0
        else:
            run += 1
    if run:
        runs.append(run)
    return runs


def test_ingress_loss_is_independent_per_receiver(lab: Lab) -> None:
    before = air_counters(lab, "b")
    set_loss(lab, "b", 0.3)
    sent, got = udp_transfer(lab, "a", ["b", "r"], dst=lab.plan.air_broadcast, count=2000)
    after = air_counters(lab, "b")
    assert sent == 2000
    received = len(set(got["b"].seqs))
    assert 0.6 <= received / sent <= 0.8
    assert sorted(got["r"].seqs) == list(range(sent))  # the other receiver lost nothing
    # Exact accounting: what b's rule dropped plus what b got is what a sent.
    assert after.loss_seen == sent
    assert after.loss_dropped + received == sent
    assert after.rx_packets - before.rx_packets >= sent  # the interface saw all of them
    assert max(_loss_runs(got["b"].seqs, sent)) < 15  # no long bursts without a burst model


def test_full_loss_cuts_the_air_but_not_the_wire(lab: Lab) -> None:
    set_loss(lab, "b", 1.0)
    sent, got = udp_transfer(lab, "a", ["b"], dst=lab.air_addr("b"), count=200)
    assert sent == 200
    assert got["b"].seqs == []
    assert tcp_transfer(lab, "a", "b", lab.wire_addr("b"), 100_000, port=40201) == 100_000
    assert air_counters(lab, "b").loss_dropped == 200


def test_burst_loss_gives_the_asked_loss_in_longer_runs(lab: Lab) -> None:
    loss = set_loss(lab, "b", 0.3, burst=5)
    assert loss.burst == 5
    sent, got = udp_transfer(lab, "a", ["b"], dst=lab.air_addr("b"), count=3000)
    received = len(set(got["b"].seqs))
    assert 0.55 <= received / sent <= 0.85
    runs = _loss_runs(got["b"].seqs, sent)
    mean_run = sum(runs) / len(runs)
    assert 3.0 <= mean_run <= 8.0  # independent 30 % loss would give 1/(1-0.3) = 1.43
    assert air_counters(lab, "b").loss_dropped + received == sent


def test_egress_loss_drops_a_broadcast_for_every_receiver(lab: Lab) -> None:
    set_loss(lab, "a", 0.3, direction=Direction.EGRESS)
    sent, got = udp_transfer(lab, "a", ["b", "r"], dst=lab.plan.air_broadcast, count=2000)
    b, r = set(got["b"].seqs), set(got["r"].seqs)
    assert b == r
    assert 0.6 <= len(b) / sent <= 0.8
    counters = air_counters(lab, "a")
    assert counters.loss_dropped + len(b) == sent
    assert counters.tx_packets >= len(b)


def test_loss_only_on_the_air_interface(lab: Lab) -> None:
    set_loss(lab, "r", 1.0)
    sent, got = udp_transfer(lab, "a", ["r"], dst=lab.air_addr("r"), count=50)
    assert got["r"].seqs == []
    counters = air_counters(lab, "r")
    assert counters.loss_seen == counters.loss_dropped == sent == 50
    # Wire traffic (TCP, and the receivers' stop datagrams) never meets the loss rule.
    assert tcp_transfer(lab, "b", "r", lab.wire_addr("r"), 10_000, port=40202) == 10_000
    assert air_counters(lab, "r").loss_seen == 50
    # ARP on the air is not IPv4: a fresh neighbour lookup still succeeds under full loss.
    for node in ("a", "r"):
        lab.ip(node, ["neigh", "flush", "dev", "air0"])
    _, got = udp_transfer(lab, "a", ["r"], dst=lab.air_addr("r"), count=5)
    assert got["r"].seqs == []
    assert "lladdr" in lab.ip("a", ["neigh", "show", "dev", "air0", lab.air_addr("r")])


def test_rate_limit_cuts_throughput_against_an_unlimited_baseline(lab: Lab) -> None:
    seconds, size, mbit = 0.5, 1000, 6.0
    _, base = udp_transfer(lab, "a", ["b"], dst=lab.air_addr("b"), size=size, seconds=seconds)
    rate = set_rate(lab, "a", mbit)
    before = air_counters(lab, "a")
    _, limited = udp_transfer(lab, "a", ["b"], dst=lab.air_addr("b"), size=size, seconds=seconds)
    after = air_counters(lab, "a")
    assert limited.get("b") is not None
    assert limited["b"].nbytes > 0
    assert limited["b"].nbytes / base["b"].nbytes < 0.25
    # Upper bound only (a slow machine can send less, never more): the rate over the
    # sending window plus the 50 ms queue drain, plus the bucket, plus 10 %.
    window = seconds + rate.latency_ms / 1000
    ceiling = 1.1 * (mbit * 1e6 / 8 * window + rate.burst_bytes)
    assert after.tx_bytes - before.tx_bytes <= ceiling
    assert after.rate_dropped > 0  # the sender was faster than the channel


def test_clear_and_apply_restore_a_clean_air(lab: Lab) -> None:
    set_loss(lab, "b", 1.0)
    set_rate(lab, "a", 1.0)
    clear(lab, "b")
    clear(lab, "a")
    assert "crosspath_lab" not in lab.nft("b", ["list", "tables"])
    assert "tbf" not in lab.tc("a", ["qdisc", "show", "dev", "air0"])
    sent, got = udp_transfer(lab, "a", ["b"], dst=lab.air_addr("b"), count=200)
    assert sorted(got["b"].seqs) == list(range(sent))
    apply(lab, "b", AirFaults(loss=Loss(1.0), rate_mbit=2.0))
    assert "tbf" in lab.tc("b", ["qdisc", "show", "dev", "air0"])
    assert air_counters(lab, "b").loss_dropped == 0
    apply(lab, "b", AirFaults())
    assert "crosspath_lab" not in lab.nft("b", ["list", "tables"])
    assert "tbf" not in lab.tc("b", ["qdisc", "show", "dev", "air0"])
    clear(lab, "b")  # clearing twice is fine


def test_bad_fault_requests_change_nothing(lab: Lab) -> None:
    set_loss(lab, "b", 0.1)
    script_before = lab.nft("b", ["list", "ruleset"])
    with pytest.raises(ValueError):
        set_loss(lab, "b", 1.5)
    with pytest.raises(LabError, match="no node"):
        set_loss(lab, "zz", 0.1)
    with pytest.raises(ValueError):
        set_rate(lab, "b", 0.0)
    assert lab.nft("b", ["list", "ruleset"]) == script_before


def test_counters_measure_on_air_bytes(lab: Lab) -> None:
    before = {n: air_counters(lab, n) for n in ("a", "b")}
    sent, _ = udp_transfer(lab, "a", ["b"], dst=lab.air_addr("b"), count=100, size=500)
    after = {n: air_counters(lab, n) for n in ("a", "b")}
    frame = 500 + 8 + 20 + 14  # UDP payload + UDP + IPv4 + Ethernet headers
    assert after["a"].tx_packets - before["a"].tx_packets >= sent
    assert after["a"].tx_bytes - before["a"].tx_bytes >= sent * frame
    assert after["b"].rx_bytes - before["b"].rx_bytes >= sent * frame
    # Little else is on the air (ARP at most): the counters are the car's V2X traffic.
    assert after["a"].tx_packets - before["a"].tx_packets <= sent + 5
    keys = set(after["a"].as_dict())
    assert {"tx_bytes", "rx_bytes", "loss_dropped", "rate_dropped"} <= keys
    assert isinstance(after["a"], AirCounters)


def test_crash_kills_everything_in_a_node_and_it_can_restart(lab: Lab) -> None:
    proc = lab.exec("r", ["sleep", "30"])
    other = lab.exec("b", ["sleep", "30"])
    try:
        pids = crash(lab, "r")
        assert proc.pid in pids
        assert proc.wait(timeout=5) == -signal.SIGKILL
        assert other.poll() is None  # other nodes untouched
        restarted = lab.exec("r", ["sleep", "30"])
        assert lab.pids("r") == [restarted.pid]
        kill(restarted)
        assert restarted.wait(timeout=5) == -signal.SIGKILL
    finally:
        kill(other)
        other.wait(timeout=5)

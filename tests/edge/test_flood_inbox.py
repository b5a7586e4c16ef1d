"""The bounded receive path (issue 13): latest wins per lane, rate limits, bounded state,
and a loop that keeps its timers while a backlog drains. In process, no wall-clock limits."""

from __future__ import annotations

import asyncio
import tempfile
import threading
from pathlib import Path

import pytest

from protocol import encode
from protocol.auth import seal
from protocol.messages import FORMAT_VERSION
from services.bench.flood import _fake_path
from services.edge.transport import (
    TICK_YIELD_S,
    V2X_QOS,
    Inbox,
    MemoryBus,
    MemoryTransport,
    ReceivePolicy,
)
from services.edge.trust import Authority


class Clock:
    """A hand-set monotonic clock [s]."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def payload(kind: int, tag: int = 0) -> bytes:
    """A datagram-looking payload: magic, version, kind, flags (unsigned), then a tag."""
    return bytes((0xCB, FORMAT_VERSION, kind, 0)) + tag.to_bytes(4, "little")


async def settle(rounds: int = 50) -> None:
    for _ in range(rounds):
        await asyncio.sleep(0)


async def test_latest_wins_per_sender_and_kind() -> None:
    got: list[tuple[str, bytes]] = []
    policy = ReceivePolicy()
    inbox = Inbox(asyncio.get_running_loop(), lambda k, p: got.append((k, p)), policy)
    for tag in range(10):
        inbox.put("cp/v2x/fp/A", payload(1, tag))
    inbox.put("cp/v2x/rsu/r/cmd/A", payload(4, 1))  # a mode command
    inbox.put("cp/v2x/rsu/r/cmd/A", payload(3, 2))  # a coordinated path: another lane
    inbox.put("cp/v2x/fp/B", payload(1, 7))
    await settle()
    assert got == [
        ("cp/v2x/fp/A", payload(1, 9)),
        ("cp/v2x/rsu/r/cmd/A", payload(4, 1)),
        ("cp/v2x/rsu/r/cmd/A", payload(3, 2)),
        ("cp/v2x/fp/B", payload(1, 7)),
    ]
    snap = policy.stats.snapshot()
    assert (snap["offered"], snap["coalesced"], snap["delivered"]) == (13, 9, 4)
    assert snap["latency_ms_p99"] is not None and inbox.lanes == 0 and inbox.queued_bytes == 0


async def test_a_datagram_with_a_certificate_is_not_replaced_by_a_digest_signed_one() -> None:
    """A signer attaches its certificate about once a second; the receiver cannot verify
    the digest-signed ones before it has seen it, so latest-wins must not drop it."""
    got: list[bytes] = []
    inbox = Inbox(asyncio.get_running_loop(), lambda k, p: got.append(p), ReceivePolicy())
    with tempfile.TemporaryDirectory() as tmp:
        authority = Authority.init(Path(tmp))
        cert = authority.issue_vehicle("A")
        key = authority.credentials("A").key
    with_cert = seal(encode(_fake_path("A", 1)), key, 0, cert)
    digests = [seal(encode(_fake_path("A", seq)), key, 0) for seq in (2, 3)]
    for data in (with_cert, *digests):
        inbox.put("cp/v2x/fp/A", data)
    await settle()
    assert got == [with_cert, digests[1]]


async def test_certificates_only_queues_nothing_else() -> None:
    """Between runs a verifying daemon only learns keys: unsigned and digest-signed
    datagrams are refused before they are queued (no decoding), counted ``refused``."""
    got: list[bytes] = []
    policy = ReceivePolicy(certificates_only=True)
    inbox = Inbox(asyncio.get_running_loop(), lambda k, p: got.append(p), policy)
    with tempfile.TemporaryDirectory() as tmp:
        authority = Authority.init(Path(tmp))
        cert = authority.issue_vehicle("A")
        key = authority.credentials("A").key
    with_cert = seal(encode(_fake_path("A", 1)), key, 0, cert)
    others = [encode(_fake_path("A", 2)), seal(encode(_fake_path("A", 3)), key, 0), b"", b"\xcb"]
    for data in (*others, with_cert):
        inbox.put("cp/v2x/fp/A", data)
        await settle()
    assert got == [with_cert]
    assert (policy.stats.counts["refused"], policy.stats.counts["offered"]) == (len(others), 1)
    policy.certificates_only = False  # a run started
    inbox.put("cp/v2x/fp/A", others[0])
    await settle()
    assert got == [with_cert, others[0]]


async def test_a_plumbing_lane_keeps_order_up_to_its_depth() -> None:
    got: list[bytes] = []
    policy = ReceivePolicy(depth=4, by_kind=False)
    inbox = Inbox(asyncio.get_running_loop(), lambda k, p: got.append(p), policy)
    for tag in range(6):
        inbox.put("cp/sim/truth/A", payload(0, tag))
    await settle()
    assert got == [payload(0, t) for t in (2, 3, 4, 5)]  # the oldest two pushed out
    assert policy.stats.counts["coalesced"] == 2


async def test_per_sender_rate_limit_counts_what_it_drops() -> None:
    clock = Clock()
    got: list[bytes] = []
    policy = ReceivePolicy(rate_hz=10.0, burst=5.0)
    inbox = Inbox(asyncio.get_running_loop(), lambda k, p: got.append(p), policy, time_fn=clock)
    for tag in range(100):  # all at the same instant
        inbox.put("cp/v2x/fp/A", payload(1, tag))
        await asyncio.sleep(0)
    assert len(got) == 5 and policy.stats.counts["rate_limited"] == 95
    clock.t = 1.0  # one second later: ten more tokens, capped at the burst
    for tag in range(100, 120):
        inbox.put("cp/v2x/fp/A", payload(1, tag))
        await asyncio.sleep(0)
    assert len(got) == 10
    inbox.put("cp/v2x/fp/B", payload(1, 0))  # another sender has its own bucket
    await settle()
    assert len(got) == 11


@pytest.mark.parametrize(("dedupe", "expect"), [(32, 5), (0, 2)])
async def test_replays_of_a_senders_datagrams_do_not_spend_its_rate(
    dedupe: int, expect: int
) -> None:
    """A replayer repeating a sender's (validly signed) datagrams must not starve it: an
    exact copy of one of the lane's recent datagrams is dropped before the token bucket.
    Without ``dedupe`` the same replays use up the bucket and the sender's next datagrams
    are rate limited (the CI failure of the evil-peer test, issue 13)."""
    clock = Clock()
    got: list[bytes] = []
    policy = ReceivePolicy(rate_hz=10.0, burst=5.0, dedupe=dedupe)
    inbox = Inbox(asyncio.get_running_loop(), lambda k, p: got.append(p), policy, time_fn=clock)
    inbox.put("cp/v2x/rsu/r1/cmd/B", payload(4, 0))
    await settle()
    for _ in range(1000):  # at the same instant: no token comes back
        inbox.put("cp/v2x/rsu/r1/cmd/B", payload(4, 0))
    for tag in range(1, 5):  # the sender's next datagrams
        inbox.put("cp/v2x/rsu/r1/cmd/B", payload(4, tag))
        await asyncio.sleep(0)
    await settle()
    assert len(got) == expect
    counts = policy.stats.counts
    assert counts["duplicate"] == (1000 if dedupe else 0)
    assert counts["rate_limited"] == (0 if dedupe else 1000)


def test_a_negative_dedupe_is_refused() -> None:
    with pytest.raises(ValueError, match="dedupe"):
        ReceivePolicy(dedupe=-1)


async def test_a_lane_forgets_what_is_beyond_its_dedupe_depth() -> None:
    got: list[bytes] = []
    policy = ReceivePolicy(depth=8, dedupe=2)
    inbox = Inbox(asyncio.get_running_loop(), lambda k, p: got.append(p), policy)
    for tag in (0, 1, 1, 2, 0, 2):  # 1 and 2 again within two; 0 after two others
        inbox.put("cp/v2x/fp/A", payload(1, tag))
    await settle()
    assert got == [payload(1, t) for t in (0, 1, 2, 0)]
    assert policy.stats.counts["duplicate"] == 2
    inbox.put("cp/v2x/fp/B", payload(1, 0))  # the same bytes from another sender: its own
    await settle()
    assert len(got) == 5


async def test_a_new_sender_on_every_datagram_keeps_state_bounded() -> None:
    delivered = 0

    def deliver(key: str, data: bytes) -> None:
        nonlocal delivered
        delivered += 1

    policy = ReceivePolicy(rate_hz=50.0, max_lanes=64, max_buckets=128, max_bytes=64 * 8, dedupe=32)
    inbox = Inbox(asyncio.get_running_loop(), deliver, policy)
    n = 20_000
    lanes = buckets = remembered = 0
    for i in range(n):  # no loop turn in between: the worst backlog
        inbox.put(f"cp/v2x/fp/x{i}", payload(1, i))
        lanes = max(lanes, inbox.lanes)
        buckets = max(buckets, inbox.buckets)
        remembered = max(remembered, inbox.remembered)
    assert lanes <= 64 and buckets <= 128 and inbox.queued_bytes <= 64 * 8
    assert remembered == 128
    await settle(2000)
    counts = policy.stats.counts
    assert counts["offered"] == delivered == 64
    assert counts["overflow"] == n - 64
    assert inbox.lanes == 0 and inbox.buckets <= 128


async def test_refused_senders_leave_no_state() -> None:
    policy = ReceivePolicy(rate_hz=50.0, admit=lambda key: key.endswith("/A"))
    got: list[str] = []
    inbox = Inbox(asyncio.get_running_loop(), lambda k, p: got.append(k), policy)
    for i in range(5000):
        key = f"cp/v2x/fp/f{i % 500}"
        if inbox.admits(key):
            inbox.put(key, payload(1, i))
    key = "cp/v2x/fp/A"
    assert inbox.admits(key)
    inbox.put(key, payload(1, 1))
    await settle()
    assert got == [key] and policy.stats.counts["refused"] == 5000
    assert inbox.buckets == 1


async def test_timers_run_while_a_backlog_drains() -> None:
    """A timer due while 2000 datagrams wait runs long before the last is handled: the
    drain takes a few per loop turn (``batch``), never the whole backlog at once."""
    handled = 0
    seen_at_tick: list[int] = []

    def deliver(key: str, data: bytes) -> None:
        nonlocal handled
        handled += 1

    policy = ReceivePolicy(batch=16, max_lanes=4096)
    loop = asyncio.get_running_loop()
    inbox = Inbox(loop, deliver, policy)
    for i in range(2000):
        inbox.put(f"cp/v2x/fp/f{i}", payload(1, i))
    loop.call_later(0.0, lambda: seen_at_tick.append(handled))
    while handled < 2000:
        await asyncio.sleep(0)
    assert seen_at_tick and seen_at_tick[0] <= 4 * 16


async def test_a_due_tick_runs_before_the_datagrams_that_arrived_with_it() -> None:
    """The control tick falls due as datagrams arrive (the cars plan when the RSU ticks):
    its wake-up is queued after the drain, yet it runs first (``tick_due``)."""
    loop = asyncio.get_running_loop()
    order: list[bytes] = []
    due: list[float | None] = [1.0]  # the tick of run time 1.0 is due and has not run
    policy = ReceivePolicy(tick_due=lambda: due[0])
    # wall time stands still (a hand-set clock): only the tick can end the hold
    inbox = Inbox(loop, lambda k, p: order.append(p[-4:]), policy, Clock())
    for i in range(3):
        inbox.put(f"cp/v2x/fp/c{i}", payload(1, i))  # the drain is queued first

    async def tick() -> None:
        wake = loop.create_future()
        loop.call_soon(wake.set_result, None)  # the tick's timer, after the datagrams
        await wake
        order.append(b"tick")
        due[0] = None

    await asyncio.gather(tick(), settle())
    await settle()
    assert order == [b"tick", *(i.to_bytes(4, "little") for i in range(3))]


async def test_an_inbox_holds_its_datagrams_for_a_due_tick_only_so_long() -> None:
    """A due tick that does not run (its task waits for something else) holds the datagrams
    back for ``TICK_YIELD_S`` of wall time, then they flow; the next tick is held for anew."""
    clock = Clock()
    handled: list[bytes] = []
    due: list[float | None] = [1.0]
    policy = ReceivePolicy(tick_due=lambda: due[0])
    inbox = Inbox(asyncio.get_running_loop(), lambda k, p: handled.append(p), policy, clock)
    inbox.put("cp/v2x/fp/a", payload(1, 0))
    await settle()
    assert handled == []  # held while the tick is due
    clock.t += TICK_YIELD_S
    await settle()
    assert len(handled) == 1  # the hold is over: the tick did not come
    due[0] = 1.1
    inbox.put("cp/v2x/fp/a", payload(1, 1))
    await settle()
    assert len(handled) == 1  # held for the next tick
    due[0] = None
    await settle()
    assert len(handled) == 2


async def test_memory_transport_offers_from_another_thread_through_the_inbox() -> None:
    bus = MemoryBus()
    sub = MemoryTransport(bus)
    pub = MemoryTransport(bus)
    sub.open()
    pub.open()
    got: list[bytes] = []
    policy = ReceivePolicy(admit=lambda key: not key.endswith("evil"))
    sub.subscribe("cp/**", lambda k, p: got.append(p), policy)

    def flood() -> None:
        for i in range(3000):
            pub.publish("cp/v2x/fp/evil", payload(1, i), V2X_QOS)
        pub.publish("cp/v2x/fp/A", payload(1, 42), V2X_QOS)

    thread = threading.Thread(target=flood)
    thread.start()
    thread.join()
    await settle()
    assert got == [payload(1, 42)] and policy.stats.counts["refused"] == 3000
    sub.close()
    pub.close()


def test_policy_refuses_nonsense() -> None:
    with pytest.raises(ValueError, match="depth"):
        ReceivePolicy(depth=0)
    with pytest.raises(ValueError, match="rate_hz"):
        ReceivePolicy(rate_hz=float("nan"))

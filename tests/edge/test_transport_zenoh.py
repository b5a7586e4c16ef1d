"""The transports: real Zenoh peers on loopback, the in-memory bus, key expressions, QoS."""

from __future__ import annotations

import asyncio
import json
import os
import socket
import subprocess
import sys
import threading
from collections.abc import AsyncIterator, Callable
from pathlib import Path

import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import keys
from services.edge.settings import ZenohSettings
from services.edge.transport import (
    MAX_TOKEN_GENERATIONS,
    RELIABLE_QOS,
    V2X_QOS,
    EndpointError,
    MemoryBus,
    MemoryTransport,
    Qos,
    TokenGenerations,
    TransportConfigError,
    TransportError,
    ZenohTransport,
    connect_in_turn,
    keyexpr_matches,
    qos_for,
    qos_for_key,
    validate_key,
    zenoh_config,
    zenoh_reason,
)

REPO = Path(__file__).resolve().parents[2]


def free_port(kind: int) -> int:
    """A port the kernel reports free on 127.0.0.1 for ``kind`` (SOCK_STREAM / SOCK_DGRAM)."""
    with socket.socket(socket.AF_INET, kind) as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


def endpoints() -> list[str]:
    return [
        f"udp/127.0.0.1:{free_port(socket.SOCK_DGRAM)}",
        f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}",
    ]


async def wait_for(predicate: Callable[[], bool], timeout: float = 5.0) -> None:
    deadline = asyncio.get_running_loop().time() + timeout
    while not predicate():
        if asyncio.get_running_loop().time() > deadline:
            raise AssertionError("condition not reached in time")
        await asyncio.sleep(0.02)


def snmp(proto: str, counter: str) -> int:
    """A kernel counter of this network namespace (``/proc/net/snmp``)."""
    rows = [line.split() for line in Path("/proc/net/snmp").read_text().splitlines()]
    head, values = (row for row in rows if row[0] == f"{proto}:")
    return int(values[head.index(counter)])


@pytest.fixture
async def peers() -> AsyncIterator[tuple[ZenohTransport, ZenohTransport]]:
    """Two Zenoh peers on loopback, scouting off, B connected to both of A's endpoints."""
    a_eps = endpoints()
    a = ZenohTransport(ZenohSettings(listen=a_eps))
    b = ZenohTransport(ZenohSettings(listen=endpoints(), connect=a_eps))
    a.open()
    await b.open_async()
    await wait_for(lambda: {src.split("/")[0] for src, _ in a.links()} == {"udp", "tcp"})
    yield a, b
    b.close()
    a.close()


# --------------------------------------------------------------------------- Zenoh


async def test_peers_exchange_v2x_and_reliable_on_the_loop_thread(
    peers: tuple[ZenohTransport, ZenohTransport],
) -> None:
    a, b = peers
    loop_thread = threading.get_ident()
    got: list[tuple[str, bytes, int]] = []

    def handler(key: str, data: bytes) -> None:
        got.append((key, data, threading.get_ident()))

    a.subscribe(keys.all_future_paths(), handler)
    a.subscribe(keys.all_sim(), handler)
    fp_key = keys.future_path("car-b")
    sim_key = keys.sim("truth", "car-b")
    fp_payload = bytes(range(256)) * 5  # 1280 bytes, one datagram
    sim_payload = b"\x00ground truth\xff"

    # Declarations propagate asynchronously: repeat until both arrive.
    async def exchange() -> None:
        while not ({k for k, _, _ in got} >= {fp_key, sim_key}):
            b.publish(fp_key, fp_payload, qos_for(keys.Stream.FP))
            b.publish(sim_key, sim_payload, qos_for_key(sim_key))
            await asyncio.sleep(0.05)

    await asyncio.wait_for(exchange(), 5.0)
    by_key = {k: (data, ident) for k, data, ident in got}
    assert by_key[fp_key][0] == fp_payload
    assert by_key[sim_key][0] == sim_payload
    assert {ident for _, _, ident in got} == {loop_thread}
    assert a.dropped == 0


async def test_best_effort_takes_udp_and_reliable_takes_tcp(
    peers: tuple[ZenohTransport, ZenohTransport],
) -> None:
    """Lower bounds on the kernel's counters: other traffic can only add to them."""
    a, b = peers
    counts = {"be": 0, "rel": 0}

    def count(key: str, data: bytes) -> None:
        counts[key.rsplit("/", 1)[1]] += 1

    a.subscribe("crosspath/v2x/test/*", count)
    a.subscribe("crosspath/sim/test/*", count)
    warm = 0
    while counts["be"] == 0 or counts["rel"] == 0:  # wait for the declarations to arrive
        b.publish("crosspath/v2x/test/be", b"w", V2X_QOS)
        b.publish("crosspath/sim/test/rel", b"w", RELIABLE_QOS)
        await asyncio.sleep(0.05)
        warm += 1
        assert warm < 100
    await asyncio.sleep(0.1)
    n = 200
    reliable_express = Qos(reliable=True, express=True, drop=False)  # one segment each
    for key, qos, proto, counter in (
        ("crosspath/v2x/test/be", V2X_QOS, "Udp", "OutDatagrams"),
        ("crosspath/sim/test/rel", reliable_express, "Tcp", "OutSegs"),
    ):
        name = key.rsplit("/", 1)[1]
        counts[name] = 0
        before = snmp(proto, counter)
        for _ in range(n):
            b.publish(key, b"x" * 600, qos)
            await asyncio.sleep(0.001)
        arrived = await _settled(counts, name, n)
        # reliable: every one; best effort may lose some on a loaded machine (the drop
        # congestion control sheds what the transmit queue cannot take: a CI run on
        # 3 Dec, with the parallel test pass on both cores, got under 95 %)
        floor = n if qos.reliable else n // 2
        assert arrived >= floor, (key, arrived, n)
        assert snmp(proto, counter) - before >= arrived, (key, proto)


async def _settled(counts: dict[str, int], name: str, n: int, timeout: float = 10.0) -> int:
    """How many of ``n`` arrived: wait until all have, or none more came for 0.5 s."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    last, quiet_since = -1, loop.time()
    while counts[name] < n and loop.time() < deadline:
        if counts[name] != last:
            last, quiet_since = counts[name], loop.time()
        elif loop.time() - quiet_since >= 0.5:
            break
        await asyncio.sleep(0.02)
    await asyncio.sleep(0.1)
    return counts[name]


async def test_liveliness_token_appears_and_goes(
    peers: tuple[ZenohTransport, ZenohTransport],
) -> None:
    a, b = peers
    changes: list[tuple[str, bool]] = []
    early = b.declare_liveliness("crosspath/alive/early")
    a.watch_liveliness("crosspath/alive/*", lambda key, alive: changes.append((key, alive)))
    await wait_for(lambda: ("crosspath/alive/early", True) in changes)  # history
    late = b.declare_liveliness("crosspath/alive/late")
    await wait_for(lambda: ("crosspath/alive/late", True) in changes)
    late.close()
    await wait_for(lambda: ("crosspath/alive/late", False) in changes)
    b.close()  # the session's tokens vanish with it
    await wait_for(lambda: ("crosspath/alive/early", False) in changes)
    early.close()  # no-op once the transport is closed


async def test_a_token_is_declared_again_unnoticed_by_a_watcher() -> None:
    """TOKEN_REFRESH_S: the token gets its new generations on schedule, then no more (a
    declaration lost while many peers join is repaired), and a watcher that saw it
    sees neither a second PUT nor a DELETE until the token really goes."""
    a_eps = endpoints()
    a = ZenohTransport(ZenohSettings(listen=a_eps))
    b = ZenohTransport(ZenohSettings(connect=a_eps), token_refresh_s=(0.05,) * 5)
    a.open()
    await b.open_async()
    try:
        changes: list[tuple[str, bool]] = []
        a.watch_liveliness("crosspath/alive/*", lambda key, alive: changes.append((key, alive)))
        token = b.declare_liveliness("crosspath/alive/b")
        await wait_for(lambda: b.tokens_refreshed >= 5)
        await asyncio.sleep(0.3)
        assert b.tokens_refreshed == 5  # five generations after the first, then none
        assert changes == [("crosspath/alive/b", True)]
        token.close()
        await wait_for(lambda: ("crosspath/alive/b", False) in changes)
        done = b.tokens_refreshed
        await asyncio.sleep(0.3)
        assert b.tokens_refreshed == done  # a closed token is not declared again
        assert changes == [("crosspath/alive/b", True), ("crosspath/alive/b", False)]
    finally:
        b.close()
        a.close()
    with pytest.raises(ValueError, match="refresh"):
        ZenohTransport(ZenohSettings(), token_refresh_s=(1.0, 0.0))


async def test_a_restarted_node_stays_alive_when_its_predecessor_goes() -> None:
    """Two transports declare the same key (a node and its restart, whose predecessor's
    token lingers until its lease ends): the key stays alive until both are gone, even
    where their generations coincide (Zenoh counts a key alive while any session holds
    a token on it)."""
    a_eps = endpoints()
    watcher = ZenohTransport(ZenohSettings(listen=a_eps))
    old = ZenohTransport(ZenohSettings(connect=a_eps))
    new = ZenohTransport(ZenohSettings(connect=a_eps))
    watcher.open()
    await old.open_async()
    await new.open_async()
    try:
        changes: list[tuple[str, bool]] = []
        watcher.watch_liveliness("crosspath/alive/*", lambda k, alive: changes.append((k, alive)))
        old.declare_liveliness("crosspath/alive/rsu1")
        await wait_for(lambda: changes == [("crosspath/alive/rsu1", True)])
        new.declare_liveliness("crosspath/alive/rsu1")
        await asyncio.sleep(0.3)
        old.close()
        await asyncio.sleep(1.0)
        assert changes == [("crosspath/alive/rsu1", True)]
        new.close()
        await wait_for(lambda: changes[-1] == ("crosspath/alive/rsu1", False))
    finally:
        new.close()
        old.close()
        watcher.close()


def test_token_generations_report_a_key_while_any_generation_lives() -> None:
    g = TokenGenerations("p/alive/*")
    assert g.update("p/alive/a/0", True) == "p/alive/a"
    assert g.update("p/alive/a/1", True) is None  # the next generation: no change
    assert g.update("p/alive/a/0", False) is None
    assert g.update("p/alive/a/1", False) == "p/alive/a"
    assert g.update("p/alive/7", True) == "p/alive/7"  # a bare token counts, digits too
    assert g.update("p/alive/7", False) == "p/alive/7"
    assert g.update("p/other/a/0", True) is None and g.ignored == 1
    assert g.update("p/alive/a/x/0", True) is None and g.ignored == 2
    assert g.update("p/alive/a/9", False) is None  # never seen: nothing to end
    deep = TokenGenerations("p/**")
    assert deep.update("p/alive/a/3", True) == "p/alive/a"


@settings(max_examples=300, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.sampled_from(["a", "b", "12"]),
            st.sampled_from(["", "0", "1", "2", "3", "4", "5"]),
            st.booleans(),
        ),
        max_size=60,
    )
)
def test_token_generations_follow_a_model(events: list[tuple[str, str, bool]]) -> None:
    """Any sequence of token events: a key is reported alive exactly while one of its
    tracked generations lives, transitions alternate, and per-key state stays bounded."""
    g = TokenGenerations("p/alive/*")
    model: dict[str, set[str]] = {}
    reported: dict[str, bool] = {}
    for node, gen, alive in events:
        key = f"p/alive/{node}"
        live = model.setdefault(key, set())
        if alive and gen not in live and len(live) < MAX_TOKEN_GENERATIONS:
            live.add(gen)
        elif not alive:
            live.discard(gen)
        changed = g.update(f"{key}/{gen}" if gen else key, alive)
        if changed is not None:
            assert changed == key and reported.get(key, False) != alive
            reported[key] = alive
        assert reported.get(key, False) == bool(live)


async def test_close_undeclares_everything_and_is_idempotent() -> None:
    t = ZenohTransport(ZenohSettings(listen=[f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"]))
    t.open()
    sub = t.subscribe("crosspath/v2x/**", lambda key, data: None)
    t.declare_liveliness("crosspath/alive/x")
    t.watch_liveliness("crosspath/alive/*", lambda key, alive: None)
    t.publish("crosspath/v2x/fp/x", b"1", V2X_QOS)
    t.publish("crosspath/stats/x", b"2", RELIABLE_QOS)
    assert len(t._handles) == 3 and len(t._publishers) == 2
    t.close()
    assert t._handles == [] and t._publishers == {} and not t.is_open
    t.close()
    sub.close()
    with pytest.raises(TransportError, match="closed"):
        t.publish("crosspath/v2x/fp/x", b"1", V2X_QOS)
    with pytest.raises(TransportError, match="closed"):
        t.open()


async def test_subscription_close_stops_delivery(
    peers: tuple[ZenohTransport, ZenohTransport],
) -> None:
    a, b = peers
    got: list[str] = []
    sub = a.subscribe("crosspath/v2x/fp/*", lambda key, data: got.append(key))
    await asyncio.wait_for(_publish_until(b, "crosspath/v2x/fp/q", got), 5.0)
    sub.close()
    sub.close()
    assert sub not in a._handles
    got.clear()
    for _ in range(5):
        b.publish("crosspath/v2x/fp/q", b"late", V2X_QOS)
    await asyncio.sleep(0.2)
    assert got == []


async def _publish_until(t: ZenohTransport, key: str, got: list[str]) -> None:
    while not got:
        t.publish(key, b"p", V2X_QOS)
        await asyncio.sleep(0.05)


async def test_a_failing_handler_is_logged_not_fatal(
    peers: tuple[ZenohTransport, ZenohTransport], caplog: pytest.LogCaptureFixture
) -> None:
    a, b = peers
    ok: list[str] = []

    def bad(key: str, data: bytes) -> None:
        raise RuntimeError("boom")

    a.subscribe("crosspath/v2x/fp/*", bad)
    a.subscribe("crosspath/v2x/fp/*", lambda key, data: ok.append(key))
    await asyncio.wait_for(_publish_until(b, "crosspath/v2x/fp/z", ok), 5.0)
    assert "handler for crosspath/v2x/fp/* failed" in caplog.text


def test_open_needs_a_loop_and_bad_keys_are_refused() -> None:
    t = ZenohTransport(ZenohSettings())
    with pytest.raises(TransportError, match="event loop"):
        t.open()
    with pytest.raises(TransportError, match="not open"):
        t.publish("crosspath/v2x/fp/a", b"", V2X_QOS)
    loop = asyncio.new_event_loop()
    try:
        t = ZenohTransport(ZenohSettings(listen=["tcp/127.0.0.1:0"]), loop=loop)
        t.open()
        with pytest.raises(ValueError, match="wildcards"):
            t.publish("crosspath/v2x/fp/*", b"", V2X_QOS)
        with pytest.raises(ValueError, match="empty chunk"):
            t.subscribe("crosspath//fp", lambda key, data: None)
        t.close()
    finally:
        loop.close()


def test_zenoh_reason_is_one_short_line() -> None:
    nested = zenoh.ZError(
        "Can not create a new TCP listener bound to tcp/127.0.0.1:7447: [127.0.0.1:7447: "
        "Address already in use (os error 98) at /root/.cargo/x/src/tcp.rs:61.] at "
        "/root/.cargo/y/src/unicast.rs:338."
    )
    assert zenoh_reason(nested) == "Address already in use (os error 98)"
    plain = zenoh.ZError("Unicast not supported for foo protocol at /a/b/lib.rs:183.")
    assert zenoh_reason(plain) == "Unicast not supported for foo protocol"


async def test_an_endpoint_that_cannot_be_opened_is_named() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        in_use = f"tcp/127.0.0.1:{busy.getsockname()[1]}"
        fine = f"udp/127.0.0.1:{free_port(socket.SOCK_DGRAM)}"
        cases = [
            ({"listen": [fine, in_use]}, "listen", in_use, "in use"),
            ({"listen": ["foo/1.2.3.4:1"]}, "listen", "foo/1.2.3.4:1", "foo protocol"),
            ({"listen": ["tcp/127.0.0.1:abc"]}, "listen", "tcp/127.0.0.1:abc", "port"),
            ({"connect": ["foo/1.2.3.4:1"]}, "connect", "foo/1.2.3.4:1", "foo protocol"),
        ]
        for fields, role, endpoint, reason in cases:
            transport = ZenohTransport(ZenohSettings(**fields))
            with pytest.raises(EndpointError) as info:
                transport.open()
            assert (info.value.role, info.value.endpoint) == (role, endpoint)
            assert reason in info.value.reason and "\n" not in str(info.value)
            assert ".rs:" not in str(info.value)
    with pytest.raises(TransportConfigError, match="invalid Zenoh configuration"):
        ZenohTransport(ZenohSettings(options={"mode": 5})).open()
    # a client that reaches no router: not a configuration error (the router may come up)
    nobody = f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"
    with pytest.raises(TransportError) as failed:
        ZenohTransport(ZenohSettings(mode="client", connect=[nobody])).open()
    assert not isinstance(failed.value, TransportConfigError)
    assert nobody in str(failed.value)


async def test_a_peer_records_its_connect_endpoints() -> None:
    nobody = f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"
    transport = ZenohTransport(ZenohSettings(connect=[nobody]))
    transport.open()  # a peer opens without a link and keeps trying
    try:
        assert transport.connect_endpoints == [nobody] and transport.links() == []
    finally:
        transport.close()


def test_connect_in_turn_awaits_reliable_endpoints_then_the_others() -> None:
    given_order = [
        "udp/10.0.0.1:7447",
        "tcp/10.0.0.1:7447",
        "quic/10.0.0.2:7447?rel=0#retry_period_init_ms=100",
        "tls/10.0.0.2:7447",
        "udp/10.0.0.3:7447#exit_on_failure=true",
    ]
    assert connect_in_turn(given_order) == [
        "tcp/10.0.0.1:7447",
        "tls/10.0.0.2:7447",
        "udp/10.0.0.1:7447#exit_on_failure=false",
        "quic/10.0.0.2:7447?rel=0#retry_period_init_ms=100;exit_on_failure=false",
        "udp/10.0.0.3:7447#exit_on_failure=true",  # said explicitly: kept
    ]
    assert connect_in_turn([]) == []


endpoint_st = st.builds(
    "{}/10.0.0.{}:{}{}".format,
    st.sampled_from(["udp", "tcp", "tls", "quic", "ws"]),
    st.integers(0, 255),
    st.integers(1, 65535),
    st.sampled_from(["", "#dscp=0x08", "?rel=0"]),
)


@given(st.lists(endpoint_st, max_size=12))
def test_connect_in_turn_keeps_every_endpoint_and_the_reliable_order(eps: list[str]) -> None:
    out = connect_in_turn(eps)
    reliable = [e for e in eps if e.split("/")[0] in ("tcp", "tls")]
    assert out[: len(reliable)] == reliable
    rest = out[len(reliable) :]
    assert all(e.endswith("exit_on_failure=false") for e in rest)
    assert [e.removesuffix("exit_on_failure=false")[:-1] for e in rest] == [
        e for e in eps if e not in reliable
    ]


async def test_a_peer_connecting_in_turn_holds_both_links_to_each_earlier_peer() -> None:
    """Three peers started in order, each connecting in turn to the ones before it."""
    listens = [endpoints() for _ in range(3)]
    nodes = [
        ZenohTransport(
            ZenohSettings(
                listen=listens[i],
                connect=[e for earlier in listens[:i] for e in earlier],
                connect_in_turn=True,
            )
        )
        for i in range(3)
    ]
    try:
        for node in nodes:
            await node.open_async()
        for i, node in enumerate(nodes[1:], start=1):
            wanted = {e for earlier in listens[:i] for e in earlier}
            await wait_for(lambda n=node, w=wanted: {dst for _, dst in n.links()} >= w)  # type: ignore[misc]
        # data crosses: the last node's subscriber was declared to the first
        got: list[str] = []
        nodes[2].subscribe(keys.all_sim(), lambda key, _data: got.append(key))

        async def exchange() -> None:
            while not got:
                nodes[0].publish(keys.sim("truth", "a"), b"x", RELIABLE_QOS)
                await asyncio.sleep(0.05)

        await asyncio.wait_for(exchange(), 5.0)
    finally:
        for node in reversed(nodes):
            node.close()


async def test_a_peer_connecting_in_turn_fails_when_a_reliable_endpoint_never_answers() -> None:
    nobody_tcp = f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"
    late = ZenohTransport(
        ZenohSettings(connect=[nobody_tcp], connect_in_turn=True, connect_timeout_s=0.5)
    )
    with pytest.raises(TransportError, match="connect_in_turn") as failed:
        await late.open_async()
    assert not isinstance(failed.value, TransportConfigError) and nobody_tcp in str(failed.value)
    # a best-effort endpoint that never answers does not hold the open up
    a_eps = endpoints()
    a = ZenohTransport(ZenohSettings(listen=a_eps))
    a.open()
    nobody_udp = f"udp/127.0.0.1:{free_port(socket.SOCK_DGRAM)}"
    b = ZenohTransport(
        ZenohSettings(connect=[*a_eps, nobody_udp], connect_in_turn=True, connect_timeout_s=5.0)
    )
    try:
        await b.open_async()
        assert [dst for _, dst in b.links() if dst.startswith("tcp/")] == [a_eps[1]]
    finally:
        b.close()
        a.close()


def test_zenoh_config_from_settings_and_file(tmp_path: Path) -> None:
    config = zenoh_config(
        ZenohSettings(
            mode="client",
            connect=["tcp/127.0.0.1:7447"],
            options={"transport/unicast/lowlatency": False},
        )
    )
    assert '"client"' in config.get_json("mode")
    assert "tcp/127.0.0.1:7447" in config.get_json("connect/endpoints")
    assert config.get_json("scouting/multicast/enabled") == "false"
    assert config.get_json("transport/unicast/max_links") == "2"

    file = tmp_path / "z.json5"
    file.write_text('{ mode: "peer", listen: { endpoints: ["udp/127.0.0.1:7000"] } }')
    only_file = zenoh_config(ZenohSettings(config_file=file))
    assert "udp/127.0.0.1:7000" in only_file.get_json("listen/endpoints")
    overridden = zenoh_config(ZenohSettings(config_file=file, listen=["tcp/127.0.0.1:7001"]))
    assert "tcp/127.0.0.1:7001" in overridden.get_json("listen/endpoints")
    assert "udp/127.0.0.1:7000" not in overridden.get_json("listen/endpoints")

    in_turn = zenoh_config(
        ZenohSettings(
            config_file=file,
            connect=["udp/127.0.0.1:7000", "tcp/127.0.0.1:7000"],
            connect_in_turn=True,
            connect_timeout_s=2.5,
        )
    )
    assert json.loads(in_turn.get_json("connect/endpoints")) == [
        "tcp/127.0.0.1:7000",
        "udp/127.0.0.1:7000#exit_on_failure=false",
    ]
    assert in_turn.get_json("connect/exit_on_failure") == "true"
    assert in_turn.get_json("connect/timeout_ms") == "2500"
    assert "exit_on_failure" not in only_file.get_json("connect/endpoints")
    per_mode = tmp_path / "per-mode.json5"
    per_mode.write_text('{ connect: { endpoints: { peer: ["tcp/127.0.0.1:7002"] } } }')
    kept = zenoh_config(ZenohSettings(config_file=per_mode, connect_in_turn=True))
    assert "tcp/127.0.0.1:7002" in kept.get_json("connect/endpoints")  # not wiped

    file.write_text("{ mode: ")
    with pytest.raises(TransportError, match="invalid Zenoh configuration"):
        zenoh_config(ZenohSettings(config_file=file))


@pytest.mark.parametrize("name", sorted(p.name for p in (REPO / "deploy/zenoh").glob("*.json5")))
def test_deploy_examples_are_valid_zenoh_configs(name: str) -> None:
    config = zenoh.Config.from_file(REPO / "deploy/zenoh" / name)
    assert config.get_json("mode").strip('"') in ("peer", "client", "router")


def test_deploy_has_the_four_examples() -> None:
    names = {p.name for p in (REPO / "deploy/zenoh").glob("*.json5")}
    assert {"car-peer.json5", "rsu-peer.json5", "router.json5", "client-to-router.json5"} <= names


@pytest.mark.daemons
async def test_router_command_forwards_between_clients() -> None:
    udp, tcp = endpoints()
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.daemons.router", "--listen", udp, "--listen", tcp],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    try:
        assert proc.stdout is not None
        line = await asyncio.wait_for(asyncio.to_thread(proc.stdout.readline), 20.0)
        assert "crosspath router: ready" in line, line
        a = ZenohTransport(ZenohSettings(mode="client", connect=[tcp]))
        b = ZenohTransport(ZenohSettings(mode="client", connect=[tcp]))
        a.open()
        b.open()
        got: list[str] = []
        a.subscribe("crosspath/v2x/fp/*", lambda key, data: got.append(key))
        await asyncio.wait_for(_publish_until(b, "crosspath/v2x/fp/r", got), 5.0)
        assert got[0] == "crosspath/v2x/fp/r"
        a.close()
        b.close()
        proc.terminate()
        code = await asyncio.wait_for(asyncio.to_thread(proc.wait), 10.0)
        assert code == 0, proc.stderr.read() if proc.stderr else ""
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


# --------------------------------------------------------------------------- memory


@pytest.mark.parametrize(
    ("pattern", "key", "expected"),
    [
        ("a/b/c", "a/b/c", True),
        ("a/b/c", "a/b", False),
        ("a/*/c", "a/b/c", True),
        ("a/*/c", "a/b/x/c", False),
        ("a/*", "a", False),
        ("a/**", "a", True),
        ("a/**", "a/b/c", True),
        ("a/**/c", "a/c", True),
        ("a/**/c", "a/b/x/c", True),
        ("a/**/c", "a/b/x/d", False),
        ("**", "a/b", True),
        ("**/c", "a/b/c", True),
        ("crosspath/v2x/rsu/*/cmd/car-a", "crosspath/v2x/rsu/r1/cmd/car-a", True),
        ("crosspath/v2x/rsu/*/cmd/car-a", "crosspath/v2x/rsu/r1/cmd/car-b", False),
        ("crosspath/v2x/**", "crosspath/sim/x", False),
    ],
)
def test_keyexpr_matches(pattern: str, key: str, expected: bool) -> None:
    assert keyexpr_matches(pattern, key) is expected


@pytest.mark.parametrize("bad", ["", "a//b", "/a", "a/", "a/b*", "a/#", "a/?x", "a/**/**"])
def test_validate_key_refuses(bad: str) -> None:
    with pytest.raises(ValueError):
        validate_key(bad, wildcards=True)


async def test_memory_transport_delivers_by_wildcards_on_the_loop() -> None:
    bus = MemoryBus()
    car = MemoryTransport(bus)
    rsu = MemoryTransport(bus)
    car.open()
    rsu.open()
    got: list[tuple[str, str, bytes]] = []
    rsu.subscribe("crosspath/v2x/fp/*", lambda k, d: got.append(("fp", k, d)))
    rsu.subscribe("crosspath/v2x/**", lambda k, d: got.append(("all", k, d)))
    car.subscribe("crosspath/v2x/rsu/*/cmd/car-a", lambda k, d: got.append(("cmd", k, d)))
    car.publish("crosspath/v2x/fp/car-a", b"path", V2X_QOS)
    rsu.publish("crosspath/v2x/rsu/r1/cmd/car-a", b"go", V2X_QOS)
    rsu.publish("crosspath/v2x/rsu/r1/cmd/car-b", b"other", V2X_QOS)
    assert got == []  # asynchronous, like Zenoh
    await asyncio.sleep(0)
    assert sorted(got) == sorted(
        [
            ("fp", "crosspath/v2x/fp/car-a", b"path"),
            ("all", "crosspath/v2x/fp/car-a", b"path"),
            ("all", "crosspath/v2x/rsu/r1/cmd/car-a", b"go"),
            ("all", "crosspath/v2x/rsu/r1/cmd/car-b", b"other"),
            ("cmd", "crosspath/v2x/rsu/r1/cmd/car-a", b"go"),
        ]
    )
    assert bus.published == 3
    car.close()
    rsu.close()


async def test_memory_transport_close_and_liveliness() -> None:
    bus = MemoryBus()
    a = MemoryTransport(bus)
    b = MemoryTransport(bus)
    a.open()
    b.open()
    changes: list[tuple[str, bool]] = []
    b.declare_liveliness("crosspath/alive/b1")
    a.watch_liveliness("crosspath/alive/*", lambda k, alive: changes.append((k, alive)))
    token = b.declare_liveliness("crosspath/alive/b2")
    await asyncio.sleep(0)
    assert changes == [("crosspath/alive/b1", True), ("crosspath/alive/b2", True)]
    token.close()
    b.close()
    await asyncio.sleep(0)
    assert changes[2:] == [("crosspath/alive/b2", False), ("crosspath/alive/b1", False)]

    got: list[bytes] = []
    sub = a.subscribe("crosspath/v2x/**", lambda k, d: got.append(d))
    c = MemoryTransport(bus)
    c.open()
    c.publish("crosspath/v2x/fp/c", b"1", V2X_QOS)
    sub.close()  # closes before the queued delivery runs: nothing is delivered
    await asyncio.sleep(0)
    assert got == []
    a.close()
    a.close()
    with pytest.raises(TransportError, match="closed"):
        a.publish("crosspath/v2x/fp/a", b"", V2X_QOS)
    c.close()


async def test_memory_transport_delivers_from_another_thread() -> None:
    bus = MemoryBus()
    a = MemoryTransport(bus)
    b = MemoryTransport(bus)
    a.open()
    b.open()
    idents: list[int] = []
    a.subscribe("crosspath/v2x/**", lambda k, d: idents.append(threading.get_ident()))
    worker = threading.Thread(target=b.publish, args=("crosspath/v2x/fp/x", b"1", V2X_QOS))
    worker.start()
    worker.join()
    await wait_for(lambda: bool(idents))
    assert idents == [threading.get_ident()]
    a.close()
    b.close()


# --------------------------------------------------------------------------- QoS


def test_qos_per_stream() -> None:
    assert qos_for(keys.Stream.FP) == V2X_QOS
    assert qos_for("beacon").reliable is False
    assert qos_for("stats") == RELIABLE_QOS
    assert qos_for_key("lab1/crosspath/sim/truth", prefix="lab1/crosspath").reliable
    with pytest.raises(ValueError, match="unknown stream"):
        qos_for("radio")
    with pytest.raises(keys.BadKey):
        qos_for_key("other/v2x/fp/a")

"""The daemon shell with credentials (over the memory bus): it signs what it sends,
refuses and counts what is unsigned, forged, replayed or from another run, and hands
the verified certificate to the handler."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import pytest

from protocol import Message, decode, encode
from protocol import keys as keyexpr
from protocol.auth import Role, decode_signed
from protocol.keys import ParsedKey, Stream
from services.daemons.vehicle import VehicleDaemonConfig
from services.edge.settings import ConfigError, load_config
from services.edge.shell import DaemonShell
from services.edge.transport import V2X_QOS, MemoryBus, MemoryTransport
from services.edge.trust import Authority, Signer, run_tag
from tests.daemons.test_daemons import future_path

PAPER = Path(__file__).resolve().parents[2] / "scenarios" / "paper-blind-intersection.toml"


def shell_config(keys: Path, node: str) -> VehicleDaemonConfig:
    fields = {
        "node_id": node,
        "scenario": str(PAPER),
        "security.key": str(keys / "{node}.key"),
        "security.certificate": str(keys / "{node}.cert"),
        "security.root": str(keys / "root.pub"),
        "security.revocation": str(keys / "revoked.txt"),
    }
    return load_config(VehicleDaemonConfig, None, fields, env={})


async def car_b_shell(tmp_path: Path) -> tuple[Authority, MemoryBus, DaemonShell]:
    """An authority for cars A and B, and car B's shell with its credentials, open."""
    keys = tmp_path / "keys"
    auth = Authority.init(keys)
    auth.provision(["A", "B"], [], [])
    bus = MemoryBus()
    shell = DaemonShell(shell_config(keys, "B"), "test", MemoryTransport(bus))
    await shell.open()
    return auth, bus, shell


async def test_shell_signs_verifies_and_counts(tmp_path: Path) -> None:
    auth, bus, shell = await car_b_shell(tmp_path)
    got: list[tuple[str, Role | None]] = []

    def handler(parsed: ParsedKey, message: Message, now: float) -> None:
        cert = shell.verified
        got.append((message.header.sender, None if cert is None else cert.role))

    shell.subscribe_v2x(keyexpr.all_future_paths(), Stream.FP, handler, ignore_vehicle="B")
    peer = MemoryTransport(bus)
    peer.open()
    sent: list[bytes] = []
    peer.subscribe(keyexpr.future_path("B"), lambda k, p: sent.append(p), None)

    async def send(payload: bytes) -> None:
        peer.publish(keyexpr.future_path("A"), payload, V2X_QOS)
        await asyncio.sleep(0.01)

    clock = shell.begin_run("run-1", time.time() - 10.0, 1.0)
    a = Signer(auth.credentials("A"))
    a.begin_run(run_tag("run-1"))
    now = clock.now()
    genuine = a.seal(encode(future_path("A", now - 0.01, seq=1)))
    await send(genuine)
    await send(genuine)  # an exact copy: dropped by the inbox (``duplicate``)
    # the same sequence again, older, signed by A: a replay only the window can tell
    await send(a.seal(encode(future_path("A", now - 0.02, seq=1))))
    await send(encode(future_path("A", now - 0.01, seq=2)))  # unsigned
    other_run = Signer(auth.credentials("A"))
    other_run.begin_run(run_tag("run-0"))
    await send(other_run.seal(encode(future_path("A", now - 0.01, seq=3))))
    evil = Authority.init(tmp_path / "evil")
    evil.provision(["A"], [], [])
    await send(Signer(evil.credentials("A")).seal(encode(future_path("A", now - 0.01, seq=4))))
    await asyncio.sleep(0.05)
    assert got == [("A", Role.VEHICLE)]
    counters = shell.stats_report(final=False).snapshot["auth"]
    assert counters == {
        "verified": 1,
        "replay": 1,
        "unsigned": 1,
        "other_run": 1,
        "bad_certificate": 1,
    }
    assert shell.stats_report(final=False).snapshot["receive"]["fp"]["duplicate"] == 1
    assert shell.publish_v2x(keyexpr.future_path("B"), future_path("B", now, seq=9))
    await asyncio.sleep(0.02)
    message, trailer = decode_signed(sent[-1])
    assert message.header.sender == "B" and trailer.run == run_tag("run-1")
    assert trailer.certificate is not None and trailer.certificate.subject == "B"
    assert decode(sent[-1]).header.seq == 9
    await shell.close()
    peer.close()


async def test_between_runs_only_certificates_are_queued_and_learned(tmp_path: Path) -> None:
    """Before a run a verifying shell queues only datagrams that carry a certificate
    (the rest refused on the network thread: a flood then costs no decoding), rate
    limited per lane as at speed 1, and learns the certificates' keys, so a
    digest-signed datagram verifies as soon as the run starts."""
    auth, bus, shell = await car_b_shell(tmp_path)
    got: list[str] = []
    shell.subscribe_v2x(
        keyexpr.all_future_paths(),
        Stream.FP,
        lambda parsed, message, now: got.append(message.header.sender),
        ignore_vehicle="B",
    )
    peer = MemoryTransport(bus)
    peer.open()
    a = Signer(auth.credentials("A"))
    a.begin_run(run_tag("run-1"))
    unsigned = [encode(future_path("A", 1.0, seq=s)) for s in range(1, 41)]
    with_cert = [a.seal(encode(future_path("A", 1.0, seq=s))) for s in range(41, 141)]
    for payload in (*unsigned, *with_cert):
        peer.publish(keyexpr.future_path("A"), payload, V2X_QOS)
    await asyncio.sleep(0.05)
    receive = shell.stats_report(final=False).snapshot["receive"]["fp"]
    assert receive["refused"] == len(unsigned)
    assert receive["rate_limited"] >= len(with_cert) - 40  # a burst of 25, then 50/s
    assert got == []  # nothing is handled outside a run
    clock = shell.begin_run("run-1", time.time() - 10.0, 1.0)
    a._burst_until, a._cert_due = float("-inf"), float("inf")  # the key id only from now
    digest = a.seal(encode(future_path("A", clock.now() - 0.01, seq=500)))
    assert decode_signed(digest)[1].certificate is None
    fresh = encode(future_path("A", clock.now() - 0.01, seq=501))
    for payload in (digest, fresh):  # in a run an unsigned one is decoded and refused
        peer.publish(keyexpr.future_path("A"), payload, V2X_QOS)
        await asyncio.sleep(0.05)
    assert got == ["A"]
    auth_counts = shell.stats_report(final=False).snapshot["auth"]
    assert auth_counts == {"verified": 1, "unsigned": 1}
    await shell.close()
    peer.close()


def test_missing_or_mismatched_files_are_a_config_error(tmp_path: Path) -> None:
    keys = tmp_path / "keys"
    Authority.init(keys).provision(["A"], [], [])
    with pytest.raises(ConfigError, match="security"):
        DaemonShell(shell_config(keys, "B"), "test", MemoryTransport(MemoryBus()))

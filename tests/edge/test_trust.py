"""Key store, certificate cache, replay window and revocation reload (services.edge.trust)."""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import Command, Header, Message, Mode, ModeCommand, encode
from protocol.auth import Coverage, Role, seal
from services.bench.security import forged_certificate
from services.edge.trust import (
    CERT_CHECK_BURST,
    CERT_CHECKS_PER_S,
    REPLAY_WINDOW,
    Authority,
    Credentials,
    Refused,
    Signer,
    TrustStore,
    run_tag,
)

COVER = Coverage(0.0, 0.0, 150.0)


class Ticker:
    """A settable clock."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def authority(tmp_path: Path) -> Authority:
    auth = Authority.init(tmp_path / "pki")
    auth.issue_vehicle("car-a")
    auth.issue_vehicle("car-b")
    auth.issue_rsu("rsu1", ["x0"], COVER)
    return auth


def command(sender: str, seq: int, time_us: int = 1_000_000) -> ModeCommand:
    return ModeCommand(Header(sender, seq, time_us), "car-a", Command.INITIATE, Mode.C_FAST)


def signed(signer: Signer, message: Message) -> tuple[bytes, Message]:
    from protocol import decode

    data = signer.seal(encode(message))
    return data, decode(data)


def store_for(authority: Authority, run: str = "run-1") -> TrustStore:
    mono = Ticker()
    store = TrustStore(authority.root_public, revocation=authority.revocation_path, monotonic=mono)
    store.begin_run(run)
    return store


def test_files_and_credentials(authority: Authority) -> None:
    d = authority.directory
    assert {p.name for p in d.iterdir()} >= {"root.key", "root.pub", "revoked.txt", "rsu1.cert"}
    assert (d / "root.key").stat().st_mode & 0o077 == 0
    creds = authority.credentials("rsu1")
    assert creds.subject == "rsu1" and creds.certificate.role is Role.RSU
    assert creds.certificate.covers("x0", 10.0, 10.0)
    with pytest.raises(FileExistsError):
        Authority.init(d)
    other = Authority.init(d.parent / "other")
    other.issue_vehicle("car-a")
    with pytest.raises(ValueError, match="not signed by the root"):
        Credentials.load(
            d.parent / "other" / "car-a.key", d.parent / "other/car-a.cert", d / "root.pub"
        )
    with pytest.raises(ValueError, match="does not certify"):
        Credentials.load(d / "car-b.key", d / "car-a.cert", d / "root.pub")


def test_valid_message_is_verified_then_its_replay_refused(authority: Authority) -> None:
    store = store_for(authority)
    signer = Signer(authority.credentials("rsu1"), run=run_tag("run-1"))
    data, message = signed(signer, command("rsu1", 1))
    assert store.verify_datagram(data, message).subject == "rsu1"
    with pytest.raises(Refused, match="replay"):
        store.verify_datagram(data, message)
    data2, message2 = signed(signer, command("rsu1", 2))  # digest form: certificate cached
    assert store.verify_datagram(data2, message2).subject == "rsu1"
    assert store.counters == {"verified": 2, "replay": 1}


def test_reordering_within_the_window_is_accepted_once(authority: Authority) -> None:
    store = store_for(authority)
    signer = Signer(authority.credentials("car-a"), run=run_tag("run-1"), cert_every_s=0.0)
    msgs = [signed(signer, command_fp(seq)) for seq in range(1, 6)]
    for i in (0, 4, 2, 1, 3):
        store.verify_datagram(*msgs[i])
    for i in range(5):
        with pytest.raises(Refused, match="replay"):
            store.verify_datagram(*msgs[i])
    assert store.counters["replay"] == 5


def command_fp(seq: int, time_us: int = 1_000_000, sender: str = "car-a") -> Message:
    from tests.protocol.vectors import VECTORS

    fp = VECTORS["fp-basic"][0]
    return dataclasses.replace(fp, header=Header(sender, seq, time_us))


def test_restarted_sender_is_accepted_old_replay_is_not(authority: Authority) -> None:
    store = store_for(authority)
    signer = Signer(authority.credentials("car-a"), run=run_tag("run-1"), cert_every_s=0.0)
    old = signed(signer, command_fp(500, 1_000_000))
    store.verify_datagram(*old)
    store.verify_datagram(*signed(signer, command_fp(600, 2_000_000)))
    restarted = signed(signer, command_fp(1, 3_000_000))  # newer: a restarted counter
    store.verify_datagram(*restarted)
    with pytest.raises(Refused, match="replay"):
        store.verify_datagram(*old)
    with pytest.raises(Refused, match="replay"):
        store.verify_datagram(*signed(signer, command_fp(600 - REPLAY_WINDOW, 1_500_000)))


def test_message_of_another_run_is_refused(authority: Authority) -> None:
    store = store_for(authority, "run-2")
    signer = Signer(authority.credentials("rsu1"), run=run_tag("run-1"))
    with pytest.raises(Refused, match="other_run"):
        store.verify_datagram(*signed(signer, command("rsu1", 1)))
    assert store.counters == {"other_run": 1}


def test_forged_and_misused_keys_are_refused(authority: Authority, tmp_path: Path) -> None:
    store = store_for(authority)
    run = run_tag("run-1")
    evil = Authority.init(tmp_path / "evil")
    evil.issue_rsu("rsu1", ["x0"], COVER)  # same id, wrong root
    forged = Signer(evil.credentials("rsu1"), run=run)
    with pytest.raises(Refused, match="bad_certificate"):
        store.verify_datagram(*signed(forged, command("rsu1", 1)))
    car = Signer(authority.credentials("car-a"), run=run)
    with pytest.raises(Refused, match="wrong_role"):  # a car key cannot command
        store.verify_datagram(*signed(car, command("car-a", 1)))
    with pytest.raises(Refused, match="wrong_sender"):  # car-a's key speaking for car-b
        store.verify_datagram(*signed(car, command_fp(2, sender="car-b")))
    fresh = Signer(authority.credentials("car-b"), run=run)
    fresh.seal(encode(command_fp(1, sender="car-b")))  # its certificate went elsewhere
    with pytest.raises(Refused, match="unknown_key"):
        store.verify_datagram(*signed(fresh, command_fp(2, sender="car-b")))
    data, message = signed(Signer(authority.credentials("rsu1"), run=run), command("rsu1", 9))
    tampered = bytearray(data)
    tampered[-70] ^= 1  # inside the signed part (certificate signature bytes)
    from protocol import decode

    with pytest.raises(Refused, match="bad_"):
        store.verify_datagram(bytes(tampered), decode(bytes(tampered)))
    with pytest.raises(Refused, match="unsigned"):
        message = command("rsu1", 10)
        store.verify_datagram(encode(message), message)
    assert store.refused == 6


def test_revocation_list_is_reloaded(authority: Authority) -> None:
    mono = Ticker()
    store = TrustStore(authority.root_public, revocation=authority.revocation_path, monotonic=mono)
    store.begin_run("r")
    signer = Signer(authority.credentials("rsu1"), run=run_tag("r"), cert_every_s=0.0)
    store.verify_datagram(*signed(signer, command("rsu1", 1)))
    authority.revoke("rsu1")
    mono.t = 5.0
    with pytest.raises(Refused, match="revoked"):
        store.verify_datagram(*signed(signer, command("rsu1", 2)))


def test_replay_and_certificate_state_is_bounded(authority: Authority) -> None:
    store = TrustStore(authority.root_public, max_keys=3)
    for i in range(10):
        authority.issue_vehicle(f"car{i}")
        s = Signer(authority.credentials(f"car{i}"))
        store.verify_datagram(*signed(s, command_fp(1, sender=f"car{i}")))
    assert len(store._certs) == 3 and len(store._windows) == 3


def test_blob_verification(authority: Authority) -> None:
    store = store_for(authority)
    signer = Signer(authority.credentials("rsu1"), run=run_tag("run-1"))
    blob = signer.seal_blob(b"stop")
    payload, cert = store.verify_blob(blob)
    assert (payload, cert.subject) == (b"stop", "rsu1")
    with pytest.raises(Refused, match="replay"):
        store.verify_blob(blob)
    with pytest.raises(Refused, match="bad_trailer"):
        store.verify_blob(b"junk")
    other = Signer(authority.credentials("rsu1"), run=run_tag("run-0"))
    with pytest.raises(Refused, match="other_run"):
        store.verify_blob(other.seal_blob(b"x"))
    assert store.verify_blob(other.seal_blob(b"y"), any_run=True)[0] == b"y"


@settings(max_examples=100, deadline=None)
@given(
    st.lists(
        st.tuples(st.integers(0, 300), st.integers(0, 50)),  # (seq, time in 0.1 s)
        min_size=1,
        max_size=80,
    )
)
def test_window_never_accepts_the_same_message_twice(arrivals: list[tuple[int, int]]) -> None:
    """Whatever order and duplicates arrive in, a (seq, time) pair passes at most once."""
    from services.edge.trust import _Window

    win: _Window | None = None
    accepted: set[tuple[int, int]] = set()
    for seq, tenth in arrivals:
        time_us = tenth * 100_000
        if win is not None and win.seen(seq, time_us):
            continue
        assert (seq, time_us) not in accepted
        accepted.add((seq, time_us))
        if win is None:
            win = _Window(seq, time_us)
        else:
            win.add(seq, time_us)


_FUZZ_AUTH = Authority.init(Path(__import__("tempfile").mkdtemp()) / "pki")
_FUZZ_AUTH.issue_rsu("rsu1", ["x0"], COVER)
_FUZZ_SEALED = Signer(_FUZZ_AUTH.credentials("rsu1")).seal(encode(command("rsu1", 5)))


@settings(max_examples=200, deadline=None)
@given(st.integers(0, len(_FUZZ_SEALED) - 1), st.integers(1, 255), st.integers(0, 40))
def test_hostile_signed_datagrams_only_ever_refuse(pos: int, flip: int, cut: int) -> None:
    """Any corruption of a signed datagram either fails to decode or is refused (a
    ``Refused``, counted); verification raises nothing else."""
    from protocol import DecodeError, decode

    data = bytearray(_FUZZ_SEALED)
    data[pos] ^= flip
    data = data[: len(data) - cut] if cut else data
    try:
        message = decode(bytes(data))
    except DecodeError:
        return
    store = TrustStore(_FUZZ_AUTH.root_public)
    with pytest.raises(Refused):
        store.verify_datagram(bytes(data), message)
    assert store.refused == 1


def test_stores_of_one_root_share_their_checked_certificates(
    authority: Authority, tmp_path: Path
) -> None:
    """A host's cars share one certificate cache: a digest-signed datagram verifies at
    once in a store that never saw the signer's certificate itself."""
    first, second = store_for(authority), store_for(authority)
    second.share_certificates(first)
    signer = Signer(authority.credentials("rsu1"), run=run_tag("run-1"))
    first.verify_datagram(*signed(signer, command("rsu1", 1)))  # carries the certificate
    data, message = signed(signer, command("rsu1", 2))  # digest form
    assert second.verify_datagram(data, message).subject == "rsu1"
    alone = store_for(authority)
    with pytest.raises(Refused, match="unknown_key"):
        alone.verify_datagram(data, message)
    other = Authority.init(tmp_path / "other-pki")
    with pytest.raises(ValueError, match="one root"):
        TrustStore(other.root_public).share_certificates(first)


# ------------------------------------------------------- forged certificates (issue 13)


def forged_datagram(
    creds: Credentials, root_id: bytes, variant: int, seq: int
) -> tuple[bytes, Message]:
    from protocol import decode

    cert = forged_certificate(creds, root_id, variant)
    data = seal(encode(command_fp(seq, sender=creds.subject)), creds.key, run_tag("run-1"), cert)
    return data, decode(data)


@contextlib.contextmanager
def root_checks() -> Iterator[list[int]]:
    """Count the Ed25519 verifications of certificates against a root (``issued_by``);
    message signatures are checked through ``services.edge.trust``'s own import."""
    import protocol.auth

    calls = [0]
    real = protocol.auth.signature_ok

    def counting(public_key: bytes, signature: bytes, data: bytes) -> bool:
        calls[0] += 1
        return real(public_key, signature, data)

    protocol.auth.signature_ok = counting
    try:
        yield calls
    finally:
        protocol.auth.signature_ok = real


def test_forged_certificates_are_verified_once_each_and_paced(
    authority: Authority, tmp_path: Path
) -> None:
    mono = Ticker()
    store = TrustStore(authority.root_public, monotonic=mono)
    store.begin_run("run-1")
    evil = Authority.init(tmp_path / "evil")
    evil.issue_vehicle("car-a")
    creds = evil.credentials("car-a")
    genuine = Signer(authority.credentials("car-b"), run=run_tag("run-1"), cert_every_s=0.0)
    with root_checks() as calls:
        for seq in range(1, 51):  # one forged certificate, again and again
            with pytest.raises(Refused, match="bad_certificate"):
                store.verify_datagram(*forged_datagram(creds, store.root_id, 0, seq))
        assert calls[0] == 1
        other = Signer(creds, run=run_tag("run-1"), cert_every_s=0.0)  # another root, named
        for seq in range(51, 101):
            with pytest.raises(Refused, match="bad_certificate"):
                store.verify_datagram(*signed(other, command_fp(seq)))
        assert calls[0] == 1  # refused by the issuer's key id alone
        extra = 50
        budget = int(CERT_CHECK_BURST) - 1
        for variant in range(1, budget + extra + 1):  # a new forgery in every datagram
            with pytest.raises(Refused, match=r"bad_certificate|certificate_budget"):
                store.verify_datagram(
                    *forged_datagram(creds, store.root_id, variant, 200 + variant)
                )
        assert calls[0] == 1 + budget
        assert store.counters["certificate_budget"] == extra
        with pytest.raises(Refused, match="certificate_budget"):  # its turn comes later
            store.verify_datagram(*signed(genuine, command_fp(1, sender="car-b")))
        mono.t += 1.5 / CERT_CHECKS_PER_S
        assert (
            store.verify_datagram(*signed(genuine, command_fp(2, sender="car-b"))).subject
            == "car-b"
        )
        assert len(store._bad_certs) <= store.max_keys


_PACE_AUTH = Authority.init(Path(__import__("tempfile").mkdtemp()) / "pki")
_PACE_EVIL = Authority.init(Path(__import__("tempfile").mkdtemp()) / "evil")
for _car in ("car-a", "car-b", "car-c"):
    _PACE_AUTH.issue_vehicle(_car)
    _PACE_EVIL.issue_vehicle(_car)


@settings(max_examples=40, deadline=None)
@given(
    st.lists(
        st.one_of(
            st.tuples(st.just("forged"), st.integers(0, 30), st.integers(0, 2)),
            st.tuples(st.just("genuine"), st.integers(0, 2), st.integers(0, 2)),
            st.tuples(st.just("wait"), st.integers(1, 200), st.just(0)),  # ms
        ),
        min_size=1,
        max_size=120,
    ),
    st.integers(1, 6),
    st.integers(1, 8),
)
def test_certificate_checks_never_outrun_their_pace(
    events: list[tuple[str, int, int]], max_keys: int, burst: int
) -> None:
    """Whatever mix of forged and genuine certificates arrives: no forged one is ever
    accepted, a genuine one is refused only for the pace (never as forged), the
    verifications against the root never exceed the burst plus the rate over the time
    elapsed, the memory of forgeries stays within ``max_keys``, and once the pace
    allows a genuine certificate is accepted. (A pace of 20/s and small bursts, so
    that it binds within a hundred datagrams.)"""
    cars = ("car-a", "car-b", "car-c")
    mono = Ticker()
    rate = 20.0
    store = TrustStore(
        _PACE_AUTH.root_public,
        monotonic=mono,
        max_keys=max_keys,
        cert_checks_per_s=rate,
        cert_check_burst=burst,
    )
    store.begin_run("run-1")
    evil = [_PACE_EVIL.credentials(c) for c in cars]
    good = [Signer(_PACE_AUTH.credentials(c), run=run_tag("run-1"), cert_every_s=0.0) for c in cars]
    with root_checks() as calls:
        for seq, (what, a, b) in enumerate(events, start=1):
            if what == "wait":
                mono.t += a / 1000
            elif what == "forged":
                with pytest.raises(Refused, match=r"bad_certificate|certificate_budget"):
                    store.verify_datagram(*forged_datagram(evil[b], store.root_id, a, seq))
            else:
                try:
                    cert = store.verify_datagram(*signed(good[a], command_fp(seq, sender=cars[a])))
                except Refused as exc:
                    assert exc.reason == "certificate_budget"
                else:
                    assert cert.subject == cars[a]
            assert calls[0] <= burst + rate * mono.t + 1e-9
            assert len(store._bad_certs) <= max_keys
        mono.t += 1.5 / rate
        last = len(events) + 1
        assert store.verify_datagram(*signed(good[0], command_fp(last, sender="car-a")))

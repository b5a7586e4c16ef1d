"""Keys, certificates, signing and verification for the daemons (issue 13, SPEC.md 2.9).

The byte layouts and the Ed25519 calls are ``protocol.auth``; this module adds
what needs files and clocks:

- :class:`Authority`: the deployment's root and the files ``crosspath keys``
  writes (``root.key``, ``root.pub``, ``<id>.key``, ``<id>.cert``,
  ``revoked.txt``);
- :class:`Credentials`: a daemon's own key, its certificate, the root public key
  and the revocation list path (what the daemon config names);
- :class:`Signer`: signs outgoing V2X datagrams (:meth:`Signer.seal`) and
  plumbing payloads (:meth:`Signer.seal_blob`), with the certificate attached
  about once a second (:data:`CERT_EVERY_S`), the key id otherwise;
- :class:`TrustStore`: verifies received datagrams and payloads. It caches the
  certificates it has seen and checked (bounded, LRU, by key id), remembers the
  forged ones that named its root (bounded, LRU, refused again without a
  verification), paces its checks against the root (:data:`CERT_CHECKS_PER_S`:
  a forgery that names the root costs a whole verification and can change in
  every datagram at no cost to the forger), keeps a
  replay window per key (highest sequence + a 64-bit bitmap, bounded, LRU),
  reloads the revocation list when its file changes, and counts every refusal
  by reason in :attr:`TrustStore.counters`.

API for other daemons' plumbing (stable)::

    creds = Credentials.load(key, certificate, root, revocation)
    signer = Signer(creds); signer.run = run_tag(run_id)
    blob = signer.seal_blob(payload)                 # plumbing, sender side
    store = TrustStore(creds.root, revocation=creds.revocation)
    payload, cert = store.verify_blob(blob)          # raises Refused(reason)
    cert = store.verify_datagram(datagram, message)  # V2X, raises Refused(reason)
    cert.role, cert.subject, cert.covers(intersection, x, y)

Decisions: replay state is per key id (a key belongs to one subject), keyed on
the header's ``seq`` and ``time_us`` (both signed): a sequence already seen, or
older than the 64 below the highest, is a replay unless the message is newer
than every one accepted from that key (a restarted sender). State is bounded
(:data:`MAX_KEYS`, LRU); after eviction only the shell's freshness window
(1 s) protects that key, so an old replay is refused as stale. Messages of
another run (run tag) are refused; ``run = 0`` on both sides means no run
binding (outside runs).
"""

from __future__ import annotations

import logging
import os
import time
from collections import OrderedDict
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from protocol import Message
from protocol.auth import (
    Certificate,
    Coverage,
    Role,
    decode_certificate,
    issue_certificate,
    key_id,
    open_blob,
    parse_trailer,
    public_bytes,
    run_tag,
    seal,
    seal_blob,
    signature_ok,
)
from protocol.codec import DecodeError
from protocol.messages import CoordinatedPath, ModeCommand, RsuBeacon
from services.edge.settings import ConfigError, SecuritySettings
from services.model.scenario import Scenario

__all__ = [
    "CERT_EVERY_S",
    "REPLAY_WINDOW",
    "Authority",
    "Credentials",
    "Refused",
    "Signer",
    "TrustStore",
    "load_private_key",
    "load_public_key",
    "load_security",
    "role_for",
    "rsu_grants",
    "run_tag",
]

log = logging.getLogger("crosspath.trust")

CERT_EVERY_S: Final = 1.0
"""How often a signer attaches its whole certificate [s, monotonic] (ETSI: about 1/s)."""

CERT_BURST_S: Final = 1.0
"""After a run starts, a signer attaches its certificate to every message this long [s]."""

SIGNATURE_MEMO: Final = 4096
"""Good signatures remembered per process (:func:`_signature_ok`): the cars of a
multi-car host receive the very same datagram once per car; it is verified once."""

_GOOD: OrderedDict[bytes, bytes] = OrderedDict()
"""(public key + signature) -> the bytes it was verified over, oldest first."""


def _signature_ok(public_key: bytes, signature: bytes, data: bytes) -> bool:
    """``signature_ok`` with a bounded per-process memo of good signatures (issue 12: CPU
    per car). A hit needs the same key, signature and signed bytes, so it proves exactly
    what a fresh verification would; replay and the other checks stay per trust store."""
    memo = public_key + signature
    if _GOOD.get(memo) == data:
        return True
    if not signature_ok(public_key, signature, data):
        return False
    _GOOD[memo] = data
    if len(_GOOD) > SIGNATURE_MEMO:
        _GOOD.popitem(last=False)
    return True


REPLAY_WINDOW: Final = 64
"""Sequence numbers below a key's highest one that may still arrive once (reordering)."""

MAX_KEYS: Final = 1024
"""Keys whose certificate and replay state a :class:`TrustStore` keeps (LRU)."""

CERT_CHECKS_PER_S: Final = 200.0
"""Certificates a :class:`TrustStore` checks against the root per second [monotonic s],
beyond :data:`CERT_CHECK_BURST` at once. A certificate is checked once per key (then
cached), so a deployment needs one check per new peer; a forged certificate that names
our root as its issuer costs a whole Ed25519 verification (≈ 0.2 ms) and differs in
every datagram at no cost to the forger, so without this bound a flood of them takes
every core it reaches. Over budget a certificate is refused ``certificate_budget``
(not cached: its signer sends it again within a second)."""

CERT_CHECK_BURST: Final = 400.0
"""Certificate checks a :class:`TrustStore` may do back to back (a run's start, where
every peer's certificate arrives within a second)."""

REVOCATION_CHECK_S: Final = 1.0
"""How often the revocation file's mtime is looked at [s, monotonic]."""

DEFAULT_VALIDITY_S: Final = 7 * 24 * 3600
"""Validity of certificates ``crosspath keys`` issues unless told otherwise [s]."""


class Refused(Exception):
    """A message that failed verification; ``reason`` is its counter name."""

    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason


# ----------------------------------------------------------------- key files


def load_private_key(path: Path) -> Ed25519PrivateKey:
    """The Ed25519 private key in a PEM (PKCS#8, unencrypted) file."""
    key = serialization.load_pem_private_key(path.read_bytes(), password=None)
    if not isinstance(key, Ed25519PrivateKey):
        raise ValueError(f"{path}: not an Ed25519 private key")
    return key


def load_public_key(path: Path) -> bytes:
    """The raw 32-byte Ed25519 public key in a PEM (SubjectPublicKeyInfo) file."""
    key = serialization.load_pem_public_key(path.read_bytes())
    if not isinstance(key, Ed25519PublicKey):
        raise ValueError(f"{path}: not an Ed25519 public key")
    return key.public_bytes_raw()


def _write(path: Path, data: bytes, private: bool = False) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600 if private else 0o644)
    with os.fdopen(fd, "wb") as fh:
        fh.write(data)
    os.replace(tmp, path)


def _private_pem(key: Ed25519PrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )


def _public_pem(key: Ed25519PrivateKey) -> bytes:
    return key.public_key().public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
    )


def read_revocations(path: Path | None) -> frozenset[bytes]:
    """Key ids listed in a revocation file: hex, one per line, ``#`` comments; a missing
    file is an empty list."""
    if path is None or not path.exists():
        return frozenset()
    ids = set()
    for line in path.read_text().splitlines():
        text = line.split("#", 1)[0].strip()
        if text:
            ids.add(bytes.fromhex(text))
    return frozenset(ids)


@dataclass
class Authority:
    """The deployment's root key and the directory ``crosspath keys`` writes into."""

    directory: Path
    root: Ed25519PrivateKey

    @property
    def root_public(self) -> bytes:
        """Raw public key of the root."""
        return public_bytes(self.root)

    @property
    def revocation_path(self) -> Path:
        """The revocation list daemons reload (``revoked.txt``)."""
        return self.directory / "revoked.txt"

    @property
    def root_pub_path(self) -> Path:
        """The root public key every daemon trusts (``root.pub``)."""
        return self.directory / "root.pub"

    @classmethod
    def init(cls, directory: Path, *, exist_ok: bool = False) -> Authority:
        """A new root in ``directory`` (``root.key`` 0600, ``root.pub``, empty ``revoked.txt``)."""
        key_path = directory / "root.key"
        if key_path.exists() and not exist_ok:
            raise FileExistsError(f"{key_path} exists: an authority is already there")
        if key_path.exists():
            return cls.open(directory)
        root = Ed25519PrivateKey.generate()
        _write(key_path, _private_pem(root), private=True)
        _write(directory / "root.pub", _public_pem(root))
        auth = cls(directory, root)
        if not auth.revocation_path.exists():
            _write(auth.revocation_path, b"# revoked key ids (hex), one per line\n")
        return auth

    @classmethod
    def open(cls, directory: Path) -> Authority:
        """The authority already in ``directory``."""
        return cls(directory, load_private_key(directory / "root.key"))

    def _issue(
        self,
        subject: str,
        role: Role,
        validity_s: int,
        now_unix: float | None,
        intersections: tuple[str, ...] = (),
        coverage: Coverage | None = None,
    ) -> Certificate:
        key = Ed25519PrivateKey.generate()
        start = int(time.time() if now_unix is None else now_unix) - 60  # clock skew
        cert = issue_certificate(
            self.root,
            subject,
            role,
            public_bytes(key),
            max(start, 0),
            max(start, 0) + 60 + validity_s,
            intersections=intersections,
            coverage=coverage,
        )
        _write(self.directory / f"{subject}.key", _private_pem(key), private=True)
        _write(self.directory / f"{subject}.cert", cert.raw)
        return cert

    def issue_vehicle(
        self, vehicle: str, validity_s: int = DEFAULT_VALIDITY_S, now_unix: float | None = None
    ) -> Certificate:
        """A new key and certificate for ``vehicle`` (``<vehicle>.key``, ``<vehicle>.cert``)."""
        return self._issue(vehicle, Role.VEHICLE, validity_s, now_unix)

    def issue_rsu(
        self,
        rsu: str,
        intersections: Iterable[str],
        coverage: Coverage,
        validity_s: int = DEFAULT_VALIDITY_S,
        now_unix: float | None = None,
    ) -> Certificate:
        """A new key and certificate for ``rsu`` coordinating ``intersections`` in ``coverage``."""
        return self._issue(rsu, Role.RSU, validity_s, now_unix, tuple(intersections), coverage)

    def issue_monitor(
        self, node: str, validity_s: int = DEFAULT_VALIDITY_S, now_unix: float | None = None
    ) -> Certificate:
        """A new key and certificate for the monitor ``node`` (run control, plumbing)."""
        return self._issue(node, Role.MONITOR, validity_s, now_unix)

    def provision(
        self,
        vehicles: Iterable[str],
        rsus: Iterable[tuple[str, str, Coverage]],
        monitors: Iterable[str] = (),
        validity_s: int = DEFAULT_VALIDITY_S,
    ) -> None:
        """Keys and certificates for a whole run: cars, RSUs as (id, intersection,
        coverage), monitors."""
        for v in vehicles:
            self.issue_vehicle(v, validity_s)
        for rsu, intersection, coverage in rsus:
            self.issue_rsu(rsu, (intersection,), coverage, validity_s)
        for m in monitors:
            self.issue_monitor(m, validity_s)

    def security_settings(self, subject: str) -> dict[str, str]:
        """The daemon config table ``[security]`` for ``subject`` (paths as text)."""
        d = self.directory
        return {
            "key": str(d / f"{subject}.key"),
            "certificate": str(d / f"{subject}.cert"),
            "root": str(self.root_pub_path),
            "revocation": str(self.revocation_path),
        }

    def revoke(self, who: str) -> bytes:
        """Add a key id (hex) or the key of subject ``who`` to ``revoked.txt``; the key id."""
        cert_path = self.directory / f"{who}.cert"
        if cert_path.exists():
            kid = decode_certificate(cert_path.read_bytes()).key_id
        else:
            try:
                kid = bytes.fromhex(who)
            except ValueError:
                raise ValueError(
                    f"{who!r} is neither a subject with a certificate here nor hex"
                ) from None
        with self.revocation_path.open("a") as fh:
            fh.write(f"{kid.hex()}  # {who}\n")
        return kid

    def credentials(self, subject: str) -> Credentials:
        """The credentials of ``subject`` issued in this directory."""
        return Credentials.load(
            self.directory / f"{subject}.key",
            self.directory / f"{subject}.cert",
            self.root_pub_path,
            self.revocation_path,
        )


@dataclass
class Credentials:
    """One daemon's identity: private key, its certificate, the root it trusts, revocations."""

    key: Ed25519PrivateKey
    certificate: Certificate
    root: bytes
    revocation: Path | None = None

    @classmethod
    def load(
        cls, key: Path, certificate: Path, root: Path, revocation: Path | None = None
    ) -> Credentials:
        """Read the files; ``ValueError`` if they do not belong together."""
        private = load_private_key(key)
        cert = decode_certificate(certificate.read_bytes())
        root_key = load_public_key(root)
        if cert.public_key != public_bytes(private):
            raise ValueError(f"{certificate} does not certify the key in {key}")
        if not cert.issued_by(root_key):
            raise ValueError(f"{certificate} is not signed by the root in {root}")
        return cls(private, cert, root_key, revocation)

    @property
    def key_id(self) -> bytes:
        """Key id of the own key."""
        return self.certificate.key_id

    @property
    def subject(self) -> str:
        """The id the certificate binds the key to."""
        return self.certificate.subject

    def sign(self, data: bytes) -> bytes:
        """The 64-byte Ed25519 signature of ``data`` with the own key."""
        return self.key.sign(data)


@dataclass
class Signer:
    """Signs what one daemon sends; ``run`` is the current run tag (:func:`run_tag`)."""

    credentials: Credentials
    run: int = 0
    cert_every_s: float = CERT_EVERY_S
    clock: Callable[[], float] = time.monotonic
    _cert_due: float = field(default=float("-inf"), init=False)
    _burst_until: float = field(default=float("-inf"), init=False)
    _counter: int = field(default=0, init=False)

    def begin_run(self, run: int, speed: float = 1.0) -> None:
        """Sign for run tag ``run`` at ``speed`` run seconds per wall second: the
        certificate goes out every :data:`CERT_EVERY_S` *run* seconds, and with everything
        sent in the first :data:`CERT_BURST_S` run seconds, so receivers that start the
        run a little later know it."""
        self.run = run
        self.cert_every_s = CERT_EVERY_S / speed
        self._burst_until = self.clock() + CERT_BURST_S / speed
        self._cert_due = float("-inf")

    def _cert(self) -> Certificate | None:
        now = self.clock()
        if now >= self._cert_due or now < self._burst_until:
            self._cert_due = now + self.cert_every_s
            return self.credentials.certificate
        return None

    def seal(self, datagram: bytes) -> bytes:
        """``datagram`` (from ``protocol.encode``) signed, with the certificate if due."""
        return seal(datagram, self.credentials.key, self.run, self._cert())

    def seal_blob(self, payload: bytes) -> bytes:
        """A plumbing payload signed (always with the certificate: plumbing is rare)."""
        self._counter = (self._counter + 1) & 0xFFFFFFFF
        cert = self.credentials.certificate
        return seal_blob(payload, self.credentials.key, self.run, self._counter, cert)


def role_for(message: Message) -> Role:
    """The role whose certificate may sign ``message`` (SPEC.md 2.9)."""
    if isinstance(message, CoordinatedPath | ModeCommand | RsuBeacon):
        return Role.RSU
    return Role.VEHICLE


class _Window:
    """Anti-replay window of one key: highest sequence seen, a bitmap below it, and the
    newest generation time accepted [µs]. A message newer than every one accepted is
    never a replay, even with a lower sequence (the sender restarted its counter: the
    window restarts at its sequence)."""

    __slots__ = ("bits", "floor", "newest", "top")

    def __init__(self, top: int, time_us: int) -> None:
        self.top = top
        self.bits = 1
        self.newest = time_us
        self.floor = time_us
        """Messages older than the window's (re)start are refused: their record is gone."""

    def seen(self, seq: int, time_us: int) -> bool:
        if time_us > self.newest:
            return False
        if time_us < self.floor:
            return True
        if seq > self.top:  # a higher sequence but older than accepted: from before a restart
            return time_us < self.newest
        back = self.top - seq
        return back >= REPLAY_WINDOW or bool(self.bits >> back & 1)

    def add(self, seq: int, time_us: int) -> None:
        if seq > self.top:
            shift = seq - self.top
            self.bits = ((self.bits << shift) | 1) & ((1 << REPLAY_WINDOW) - 1)
            self.top = seq
        elif time_us > self.newest and self.top - seq >= REPLAY_WINDOW:
            self.top, self.bits, self.floor = seq, 1, time_us
        else:
            self.bits |= 1 << min(self.top - seq, REPLAY_WINDOW - 1)
        self.newest = max(self.newest, time_us)


class TrustStore:
    """Verifies what a daemon receives; thread-compatible, not thread-safe (one loop).

    ``run`` is the run tag expected (set it at the start of every run);
    ``now_unix`` dates certificate validity; ``monotonic`` paces revocation reloads and
    the checks of certificates against the root (``cert_checks_per_s`` per second,
    ``cert_check_burst`` at once; ``math.inf`` for no pace, a benchmark's baseline).
    """

    def __init__(
        self,
        root: bytes,
        *,
        revocation: Path | None = None,
        run: int = 0,
        max_keys: int = MAX_KEYS,
        now_unix: Callable[[], float] = time.time,
        monotonic: Callable[[], float] = time.monotonic,
        cert_checks_per_s: float = CERT_CHECKS_PER_S,
        cert_check_burst: float = CERT_CHECK_BURST,
    ) -> None:
        self.root = root
        self.root_id = key_id(root)
        self.revocation = revocation
        self.run = run
        self.max_keys = max_keys
        self.now_unix = now_unix
        self.monotonic = monotonic
        self.counters: dict[str, int] = {}
        self._certs: OrderedDict[bytes, Certificate] = OrderedDict()
        self._windows: OrderedDict[bytes, _Window] = OrderedDict()
        self._blob_windows: OrderedDict[bytes, _Window] = OrderedDict()
        if not (cert_checks_per_s > 0 and cert_check_burst >= 1):
            raise ValueError("certificate checks need a rate > 0 and a burst >= 1")
        self._bad_certs: OrderedDict[bytes, None] = OrderedDict()
        self.cert_checks_per_s = cert_checks_per_s
        self.cert_check_burst = cert_check_burst
        self._check_tokens = cert_check_burst
        self._check_stamp = monotonic()
        self._revoked: frozenset[bytes] = frozenset()
        self._rev_mtime: float | None = None
        self._rev_checked = float("-inf")
        self.reload_revocations()

    # -- state

    def share_certificates(self, other: TrustStore) -> None:
        """Use ``other``'s cache of checked certificates from now on (stores of one
        process under the same root: a certificate checked by one is known to all).
        ``ValueError`` for another root: its certificates prove nothing here."""
        if other.root != self.root:
            raise ValueError("certificates are shared only between stores of one root")
        self._certs = other._certs

    def begin_run(self, run_id: str | None) -> None:
        """Expect messages of run ``run_id`` from now on; forget the replay windows."""
        self.run = run_tag(run_id)
        self._windows.clear()
        self._blob_windows.clear()

    def reload_revocations(self) -> None:
        """Re-read the revocation file if it changed (checked at most every second)."""
        now = self.monotonic()
        if now - self._rev_checked < REVOCATION_CHECK_S:
            return
        self._rev_checked = now
        path = self.revocation
        try:
            mtime = path.stat().st_mtime if path is not None else None
        except OSError:
            mtime = None
        if mtime == self._rev_mtime:
            return
        try:
            revoked = read_revocations(path if mtime is not None else None)
        except (OSError, ValueError) as exc:
            log.error("cannot read revocation list %s: %s (keeping the old one)", path, exc)
            return
        self._rev_mtime = mtime
        if revoked != self._revoked:
            log.info("revocation list %s: %d key(s)", path, len(revoked))
        self._revoked = revoked
        for kid in revoked:
            self._certs.pop(kid, None)

    def _refuse(self, reason: str, detail: str = "") -> Refused:
        self.counters[reason] = self.counters.get(reason, 0) + 1
        return Refused(reason, detail)

    def _check(self, cert: Certificate) -> str | None:
        """Check a certificate not in the cache against the root: None if the root issued
        it (then cached), else the refusal reason. Certificates found forged are
        remembered (bounded, LRU) and refused again without a verification; the
        verifications themselves are paced (:data:`CERT_CHECKS_PER_S`)."""
        if cert.issuer != self.root_id:  # another authority's: refused without a verification
            return "bad_certificate"
        if cert.raw in self._bad_certs:
            self._bad_certs.move_to_end(cert.raw)
            return "bad_certificate"
        now = self.monotonic()
        if now > self._check_stamp:
            self._check_tokens = min(
                self.cert_check_burst,
                self._check_tokens + (now - self._check_stamp) * self.cert_checks_per_s,
            )
            self._check_stamp = now
        if self._check_tokens < 1.0:
            return "certificate_budget"
        self._check_tokens -= 1.0
        if not cert.issued_by(self.root):
            self._bad_certs[cert.raw] = None
            if len(self._bad_certs) > self.max_keys:
                self._bad_certs.popitem(last=False)
            return "bad_certificate"
        self._certs[cert.key_id] = cert
        if len(self._certs) > self.max_keys:
            self._certs.popitem(last=False)
        return None

    def _certificate(self, kid: bytes, cert: Certificate | None) -> Certificate:
        """The checked certificate of key ``kid`` (from the message or the cache)."""
        self.reload_revocations()
        if kid in self._revoked:
            raise self._refuse("revoked", kid.hex())
        cached = self._certs.get(kid)
        if cached is not None and (cert is None or cert.raw == cached.raw):
            self._certs.move_to_end(kid)
            cert = cached
        elif cert is None:
            raise self._refuse("unknown_key", kid.hex())
        elif (failed := self._check(cert)) is not None:
            why = "not issued by our root" if failed == "bad_certificate" else "checks paced"
            raise self._refuse(failed, f"{cert.subject}: {why}")
        if not cert.valid_at(self.now_unix()):
            raise self._refuse("expired", cert.subject)
        return cert

    def _window(
        self, table: OrderedDict[bytes, _Window], kid: bytes, seq: int, time_us: int
    ) -> None:
        win = table.get(kid)
        if win is None:
            table[kid] = _Window(seq, time_us)
            if len(table) > self.max_keys:
                table.popitem(last=False)
        else:
            win.add(seq, time_us)
            table.move_to_end(kid)

    def learn(self, datagram: bytes, message: Message) -> None:
        """Cache the certificate a datagram carries, if the root issued it; nothing else
        (for datagrams heard outside a run, which are not verified)."""
        try:
            trailer = parse_trailer(datagram, message)
        except DecodeError:
            return
        cert = trailer.certificate
        if cert is None or trailer.key_id in self._certs or trailer.key_id in self._revoked:
            return
        self._check(cert)

    # -- verification

    def verify_datagram(self, datagram: bytes, message: Message) -> Certificate:
        """The certificate that vouches for ``message`` (decoded from ``datagram``).

        Refuses (:class:`Refused`, counted by reason): ``unsigned``, ``bad_trailer``,
        ``other_run``, ``revoked``, ``unknown_key`` (digest of a key whose certificate
        has not been seen yet), ``bad_certificate``, ``expired``, ``wrong_role``,
        ``wrong_sender`` (certificate subject is not the header's sender),
        ``replay`` (sequence already seen or below the window), ``bad_signature``.
        Freshness of ``time_us`` is the caller's check (the shell's stale window).
        """
        try:
            trailer = parse_trailer(datagram, message)
        except DecodeError as exc:
            raise self._refuse(
                "unsigned" if not message.header.auth else "bad_trailer", str(exc)
            ) from None
        cert = self._certificate(trailer.key_id, trailer.certificate)
        if trailer.run != self.run:
            raise self._refuse("other_run", f"run tag {trailer.run:#x}")
        if cert.role is not role_for(message):
            raise self._refuse("wrong_role", f"{cert.subject} ({cert.role.name})")
        if cert.subject != message.header.sender:
            raise self._refuse("wrong_sender", f"{message.header.sender} signed by {cert.subject}")
        seq, time_us = message.header.seq, message.header.time_us
        win = self._windows.get(trailer.key_id)
        if win is not None and win.seen(seq, time_us):
            raise self._refuse("replay", f"{cert.subject} seq {seq}")
        if not _signature_ok(cert.public_key, trailer.signature, trailer.signed):
            raise self._refuse("bad_signature", cert.subject)
        self._window(self._windows, trailer.key_id, seq, time_us)
        self.counters["verified"] = self.counters.get("verified", 0) + 1
        return cert

    def verify_blob(self, blob: bytes, *, any_run: bool = False) -> tuple[bytes, Certificate]:
        """The payload of a :meth:`Signer.seal_blob` result and its signer's certificate.

        Refuses like :meth:`verify_datagram` (``bad_trailer`` for a malformed
        envelope); with ``any_run`` the run tag is not checked (a start message
        names the run that does not exist yet)."""
        try:
            opened = open_blob(blob)
        except DecodeError as exc:
            raise self._refuse("bad_trailer", str(exc)) from None
        if not any_run and opened.run != self.run:
            raise self._refuse("other_run", f"run tag {opened.run:#x}")
        cert = self._certificate(opened.key_id, opened.certificate)
        win = self._blob_windows.get(opened.key_id)
        if win is not None and win.seen(opened.counter, -1):
            raise self._refuse("replay", f"{cert.subject} counter {opened.counter}")
        if not _signature_ok(cert.public_key, opened.signature, opened.signed):
            raise self._refuse("bad_signature", cert.subject)
        self._window(self._blob_windows, opened.key_id, opened.counter, -1)
        return opened.payload, cert

    @property
    def refused(self) -> int:
        """All refusals so far."""
        return sum(n for k, n in self.counters.items() if k != "verified")


def rsu_grants(scenario: Scenario) -> list[tuple[str, str, Coverage]]:
    """What each RSU of ``scenario`` may coordinate: (RSU id, intersection, coverage), the
    coverage centred on the intersection as the RSU core's (``services.rsu.config``)."""
    out = []
    for r in scenario.rsus:
        cx, cy = scenario.intersection(r.intersection).center
        out.append((r.id, r.intersection, Coverage(float(cx), float(cy), r.coverage_m)))
    return out


def load_security(settings: SecuritySettings, node: str) -> tuple[Signer, TrustStore] | None:
    """The signer and trust store a daemon's ``security`` settings name; None without
    credentials (unsigned). ``{node}`` in a path is replaced by ``node`` (the daemon's
    id: one setting serves every car of a multi-car host). Raises ``ConfigError``
    naming the field for unreadable or mismatched files."""
    if settings.key is None or settings.certificate is None or settings.root is None:
        return None

    def path(p: Path) -> Path:
        return Path(str(p).replace("{node}", node))

    try:
        creds = Credentials.load(
            path(settings.key),
            path(settings.certificate),
            settings.root,
            settings.revocation,
        )
    except (OSError, ValueError, DecodeError) as exc:
        raise ConfigError([("security", str(exc))]) from None
    return Signer(creds), TrustStore(creds.root, revocation=settings.revocation)

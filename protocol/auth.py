"""Authentication scheme 1 (Ed25519) and the crosspath certificate format (SPEC.md 2.9, 2.10).

Pure functions, no I/O and no clock reads (callers pass ``now_unix``). The
cryptography is the ``cryptography`` package's Ed25519; nothing here is
hand-written crypto, only byte layouts.

A signed datagram is an ordinary datagram (format version 3) with ``flags.AUTH`` and a
scheme-1 trailer whose data is::

    u8  form        0: the signer's key id follows, 1: its whole certificate follows
    u32 run         run tag (:func:`run_tag` of the run id; 0 outside runs)
    8 B key id      (form 0)   |   certificate (form 1, :data:`MAX_CERT_LEN` bytes at most)
    64 B signature  Ed25519 over every byte of the datagram before the signature

so the signature covers the header (with its ``AUTH`` flag and ``seq``), the
body, the trailer's scheme and length bytes and the signed extension (form,
run tag, key id or certificate). The header's ``seq`` is the per-sender
monotonic sequence and its ``time_us`` the freshness stamp: both are signed.

Decisions (SPEC.md 2.9): the key id is the first 8 bytes of SHA-256 of the raw
32-byte public key; the signer sends its certificate about once a second and
only when the datagram still fits :data:`MAX_DATAGRAM` (a worst-case path is
sent with the 79-byte digest-form trailer, which :func:`protocol.max_points`
reserves room for); the certificate is at most :data:`MAX_CERT_LEN` bytes so
that it fits the one-byte trailer length.
"""

from __future__ import annotations

import hashlib
import struct
from dataclasses import dataclass
from enum import IntEnum
from typing import Final

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from protocol.codec import DecodeError, EncodeError, decode
from protocol.keys import is_valid_id
from protocol.messages import MAX_DATAGRAM, Flags, Message

__all__ = [
    "BLOB_MAX_PAYLOAD",
    "CERT_VERSION",
    "DIGEST_TRAILER_LEN",
    "KEY_ID_LEN",
    "MAX_CERT_LEN",
    "MAX_INTERSECTIONS",
    "SCHEME_ED25519",
    "SIG_LEN",
    "Certificate",
    "Coverage",
    "Form",
    "Role",
    "SignedBlob",
    "Trailer",
    "decode_certificate",
    "issue_certificate",
    "key_id",
    "open_blob",
    "parse_trailer",
    "run_tag",
    "seal",
    "seal_blob",
    "signature_ok",
]

SCHEME_ED25519: Final = 1
"""Trailer scheme 1: Ed25519 signature with a key id or certificate (this module)."""

KEY_ID_LEN: Final = 8
"""Bytes of a key id: SHA-256 of the raw public key, truncated."""

SIG_LEN: Final = 64
"""Bytes of an Ed25519 signature."""

PUBLIC_KEY_LEN: Final = 32
"""Bytes of a raw Ed25519 public key."""

CERT_VERSION: Final = 1
"""Certificate format version."""

MAX_INTERSECTIONS: Final = 8
"""Most intersections one RSU certificate may name."""

_TRAILER_EXT: Final = struct.Struct("<BI")  # form, run tag
_TRAILER_MAX_DATA: Final = 255
MAX_CERT_LEN: Final = _TRAILER_MAX_DATA - _TRAILER_EXT.size - SIG_LEN
"""Longest encoded certificate (186 bytes): it must fit a trailer with the extension
and the signature in 255 bytes of trailer data."""

DIGEST_TRAILER_LEN: Final = 2 + _TRAILER_EXT.size + KEY_ID_LEN + SIG_LEN
"""Bytes a digest-form scheme-1 trailer adds to a datagram (79): scheme, length, form,
run tag, key id, signature. ``protocol.max_points`` keeps room for it."""

_CERT_HEAD: Final = struct.Struct("<BB")  # version, role
_CERT_TAIL: Final = struct.Struct("<II8s")  # not_before, not_after [unix s], issuer key id
_COVERAGE: Final = struct.Struct("<iiIB")  # x [cm], y [cm], radius [cm], intersection count
_MAX_COORD_CM: Final = 10**9
_MAX_RADIUS_CM: Final = 10**6
_U32_MAX: Final = 2**32 - 1


class Role(IntEnum):
    """What a certificate lets its key say."""

    VEHICLE = 1
    RSU = 2
    MONITOR = 3
    """Run control (start, stop, the result): the plumbing's authority, no V2X."""


class Form(IntEnum):
    """How a scheme-1 trailer names its signer."""

    DIGEST = 0
    CERTIFICATE = 1


def key_id(public_key: bytes) -> bytes:
    """Short name of a raw 32-byte Ed25519 public key (8 bytes of its SHA-256)."""
    if len(public_key) != PUBLIC_KEY_LEN:
        raise ValueError(f"an Ed25519 public key is {PUBLIC_KEY_LEN} bytes, not {len(public_key)}")
    return hashlib.sha256(public_key).digest()[:KEY_ID_LEN]


def public_bytes(key: Ed25519PrivateKey | Ed25519PublicKey) -> bytes:
    """The raw 32-byte public key of ``key``."""
    pub = key.public_key() if isinstance(key, Ed25519PrivateKey) else key
    return pub.public_bytes_raw()


def run_tag(run_id: str | None) -> int:
    """The u32 a signed message carries to bind it to one run (0: no run)."""
    if not run_id:
        return 0
    return int.from_bytes(hashlib.sha256(run_id.encode()).digest()[:4], "little") or 1


@dataclass(frozen=True, slots=True)
class Coverage:
    """The disc an RSU may coordinate in: centre (x, y) [m] and radius [m]."""

    x: float
    y: float
    radius: float

    def contains(self, x: float, y: float) -> bool:
        """Whether the point (x, y) [m] lies in the disc."""
        return (x - self.x) ** 2 + (y - self.y) ** 2 <= self.radius**2


@dataclass(frozen=True, slots=True)
class Certificate:
    """A key bound by the root to one subject id and role (SPEC.md 2.10).

    ``raw`` is the encoded certificate including the issuer's signature; RSU
    certificates also name the intersections and the coverage disc."""

    subject: str
    role: Role
    public_key: bytes
    not_before: int
    not_after: int
    issuer: bytes
    intersections: tuple[str, ...]
    coverage: Coverage | None
    signature: bytes
    raw: bytes

    @property
    def key_id(self) -> bytes:
        """Key id of the certified key."""
        return key_id(self.public_key)

    @property
    def tbs(self) -> bytes:
        """The bytes the issuer signed (everything but the signature)."""
        return self.raw[:-SIG_LEN]

    def issued_by(self, issuer_public_key: bytes) -> bool:
        """Whether the issuer's Ed25519 signature over the certificate is valid."""
        if key_id(issuer_public_key) != self.issuer:
            return False
        return signature_ok(issuer_public_key, self.signature, self.tbs)

    def valid_at(self, now_unix: float) -> bool:
        """Whether ``now_unix`` [s since 1970] lies in the validity period."""
        return self.not_before <= now_unix <= self.not_after

    def covers(self, intersection: str, x: float, y: float) -> bool:
        """Whether an RSU with this certificate may coordinate ``intersection`` for a car
        at (x, y) [m]: the intersection is listed and the car is inside the coverage."""
        return (
            self.role is Role.RSU
            and intersection in self.intersections
            and self.coverage is not None
            and self.coverage.contains(x, y)
        )


def _id(value: str, what: str) -> bytes:
    if not is_valid_id(value):
        raise EncodeError(f"invalid {what} {value!r}")
    raw = value.encode("ascii")
    return bytes((len(raw),)) + raw


def _cm(value: float, bound: int, what: str, lo: int) -> int:
    if value != value or value in (float("inf"), float("-inf")):
        raise EncodeError(f"{what} is not finite")
    cm = round(value * 100)
    if not lo <= cm <= bound:
        raise EncodeError(f"{what} {value} m out of range")
    return cm


def issue_certificate(
    issuer: Ed25519PrivateKey,
    subject: str,
    role: Role,
    public_key: bytes,
    not_before: int,
    not_after: int,
    *,
    intersections: tuple[str, ...] = (),
    coverage: Coverage | None = None,
) -> Certificate:
    """A certificate for ``public_key`` signed by ``issuer``; ``EncodeError`` if invalid.

    Vehicle certificates take no intersections or coverage; RSU certificates need
    1..:data:`MAX_INTERSECTIONS` intersections and a coverage disc. Validity is in
    whole unix seconds."""
    if len(public_key) != PUBLIC_KEY_LEN:
        raise EncodeError("the subject key must be a raw 32-byte Ed25519 public key")
    if not 0 <= not_before <= not_after <= _U32_MAX:
        raise EncodeError("validity must satisfy 0 <= not_before <= not_after < 2**32")
    role = Role(role)
    parts = [_CERT_HEAD.pack(CERT_VERSION, role), _id(subject, "subject id"), public_key]
    parts.append(_CERT_TAIL.pack(not_before, not_after, key_id(public_bytes(issuer))))
    if role is Role.RSU:
        if coverage is None or not 1 <= len(intersections) <= MAX_INTERSECTIONS:
            raise EncodeError(
                f"an RSU certificate needs a coverage and 1..{MAX_INTERSECTIONS} intersections"
            )
        x = _cm(coverage.x, _MAX_COORD_CM, "coverage x", -_MAX_COORD_CM)
        y = _cm(coverage.y, _MAX_COORD_CM, "coverage y", -_MAX_COORD_CM)
        r = _cm(coverage.radius, _MAX_RADIUS_CM, "coverage radius", 1)
        parts.append(_COVERAGE.pack(x, y, r, len(intersections)))
        parts.extend(_id(i, "intersection id") for i in intersections)
    elif intersections or coverage is not None:
        raise EncodeError(f"a {role.name.lower()} certificate names no intersections or coverage")
    tbs = b"".join(parts)
    if len(tbs) + SIG_LEN > MAX_CERT_LEN:
        raise EncodeError(
            f"certificate of {len(tbs) + SIG_LEN} bytes; at most {MAX_CERT_LEN} "
            "(shorten the ids or name fewer intersections)"
        )
    return decode_certificate(tbs + issuer.sign(tbs))


def _read_id(buf: bytes, off: int, what: str) -> tuple[str, int]:
    if off >= len(buf):
        raise DecodeError(f"truncated certificate: no {what}")
    n = buf[off]
    raw = buf[off + 1 : off + 1 + n]
    if len(raw) != n:
        raise DecodeError(f"truncated certificate: {what}")
    try:
        value = raw.decode("ascii")
    except UnicodeDecodeError:
        raise DecodeError(f"invalid {what}") from None
    if not is_valid_id(value):
        raise DecodeError(f"invalid {what} {value!r}")
    return value, off + 1 + n


def decode_certificate(data: bytes | bytearray | memoryview) -> Certificate:
    """The certificate in ``data`` (exactly); ``DecodeError`` and nothing else if malformed.

    Checks the layout only: whether the root signed it is :meth:`Certificate.issued_by`."""
    buf = bytes(data)
    if len(buf) > MAX_CERT_LEN:
        raise DecodeError(f"certificate of {len(buf)} bytes; at most {MAX_CERT_LEN}")
    if len(buf) < _CERT_HEAD.size:
        raise DecodeError("truncated certificate")
    version, role_value = _CERT_HEAD.unpack_from(buf, 0)
    if version != CERT_VERSION:
        raise DecodeError(f"unsupported certificate version {version}")
    if role_value not in (Role.VEHICLE, Role.RSU, Role.MONITOR):
        raise DecodeError(f"invalid certificate role {role_value}")
    role = Role(role_value)
    subject, off = _read_id(buf, _CERT_HEAD.size, "subject id")
    public_key = buf[off : off + PUBLIC_KEY_LEN]
    off += PUBLIC_KEY_LEN
    if off + _CERT_TAIL.size > len(buf):
        raise DecodeError("truncated certificate")
    not_before, not_after, issuer = _CERT_TAIL.unpack_from(buf, off)
    off += _CERT_TAIL.size
    if not_before > not_after:
        raise DecodeError("certificate validity ends before it starts")
    intersections: tuple[str, ...] = ()
    coverage: Coverage | None = None
    if role is Role.RSU:
        if off + _COVERAGE.size > len(buf):
            raise DecodeError("truncated certificate coverage")
        x, y, r, count = _COVERAGE.unpack_from(buf, off)
        off += _COVERAGE.size
        if abs(x) > _MAX_COORD_CM or abs(y) > _MAX_COORD_CM or not 1 <= r <= _MAX_RADIUS_CM:
            raise DecodeError("certificate coverage out of range")
        if not 1 <= count <= MAX_INTERSECTIONS:
            raise DecodeError(f"certificate names {count} intersections")
        names = []
        for _ in range(count):
            name, off = _read_id(buf, off, "intersection id")
            names.append(name)
        intersections = tuple(names)
        coverage = Coverage(x / 100, y / 100, r / 100)
    if len(buf) - off != SIG_LEN:
        raise DecodeError(f"certificate signature of {len(buf) - off} bytes, not {SIG_LEN}")
    return Certificate(
        subject=subject,
        role=role,
        public_key=public_key,
        not_before=not_before,
        not_after=not_after,
        issuer=issuer,
        intersections=intersections,
        coverage=coverage,
        signature=buf[off:],
        raw=buf,
    )


def signature_ok(public_key: bytes, signature: bytes, data: bytes) -> bool:
    """Whether ``signature`` is ``public_key``'s valid Ed25519 signature of ``data``."""
    try:
        Ed25519PublicKey.from_public_bytes(public_key).verify(signature, data)
    except (InvalidSignature, ValueError):
        return False
    return True


# ----------------------------------------------------------------- V2X datagrams


@dataclass(frozen=True, slots=True)
class Trailer:
    """A parsed scheme-1 trailer: who claims to have signed, and what to check."""

    form: Form
    run: int
    key_id: bytes
    certificate: Certificate | None
    signature: bytes
    signed: bytes
    """Every byte of the datagram before the signature: what the signature covers."""


def _ext(form: Form, run: int, who: bytes) -> bytes:
    if not 0 <= run <= _U32_MAX:
        raise EncodeError(f"run tag {run} outside u32")
    return _TRAILER_EXT.pack(form, run) + who


def seal(
    datagram: bytes,
    key: Ed25519PrivateKey,
    run: int,
    certificate: Certificate | None = None,
) -> bytes:
    """``datagram`` (unsigned, from ``protocol.encode``) signed with scheme 1.

    With ``certificate`` the trailer carries it when the result still fits
    :data:`MAX_DATAGRAM`, else (and without it) the key id. ``EncodeError`` if the
    datagram already has a trailer or the digest form does not fit either."""
    if len(datagram) < 4 or datagram[3] & Flags.AUTH:
        raise EncodeError("seal needs an encoded datagram without an authentication trailer")
    kid = key_id(public_bytes(key))
    head = datagram[:3] + bytes((datagram[3] | Flags.AUTH,)) + datagram[4:]
    who = _ext(Form.DIGEST, run, kid)
    if certificate is not None:
        if certificate.key_id != kid:
            raise EncodeError("the certificate is not for this key")
        full = _ext(Form.CERTIFICATE, run, certificate.raw)
        if len(head) + 2 + len(full) + SIG_LEN <= MAX_DATAGRAM:
            who = full
    if len(head) + 2 + len(who) + SIG_LEN > MAX_DATAGRAM:
        raise EncodeError(f"a signed datagram of {len(head) + DIGEST_TRAILER_LEN} bytes")
    signed = head + bytes((SCHEME_ED25519, len(who) + SIG_LEN)) + who
    return signed + key.sign(signed)


def _parse_data(data: bytes) -> tuple[Form, int, bytes, Certificate | None, bytes]:
    if len(data) < _TRAILER_EXT.size + SIG_LEN:
        raise DecodeError("scheme-1 trailer too short")
    form_value, run = _TRAILER_EXT.unpack_from(data, 0)
    who = data[_TRAILER_EXT.size : -SIG_LEN]
    if form_value == Form.DIGEST:
        if len(who) != KEY_ID_LEN:
            raise DecodeError(f"key id of {len(who)} bytes, not {KEY_ID_LEN}")
        return Form.DIGEST, run, who, None, data[-SIG_LEN:]
    if form_value == Form.CERTIFICATE:
        cert = decode_certificate(who)
        return Form.CERTIFICATE, run, cert.key_id, cert, data[-SIG_LEN:]
    raise DecodeError(f"invalid scheme-1 form {form_value}")


def parse_trailer(datagram: bytes, message: Message) -> Trailer:
    """The scheme-1 trailer of ``datagram``, which decoded to ``message``.

    ``DecodeError`` if the datagram is unsigned, of another scheme or malformed."""
    auth = message.header.auth
    if not auth:
        raise DecodeError("unsigned datagram")
    if auth[0] != SCHEME_ED25519:
        raise DecodeError(f"authentication scheme {auth[0]}, not {SCHEME_ED25519}")
    form, run, kid, cert, signature = _parse_data(auth[1:])
    return Trailer(form, run, kid, cert, signature, bytes(datagram[:-SIG_LEN]))


def decode_signed(datagram: bytes) -> tuple[Message, Trailer]:
    """``decode`` plus :func:`parse_trailer`; ``DecodeError`` and nothing else."""
    message = decode(datagram)
    return message, parse_trailer(bytes(datagram), message)


# ----------------------------------------------------------------- plumbing blobs

_BLOB_EXT: Final = struct.Struct("<BII")  # form, run tag, counter
BLOB_MAX_PAYLOAD: Final = 1 << 20
"""Largest payload :func:`open_blob` accepts [bytes]."""


@dataclass(frozen=True, slots=True)
class SignedBlob:
    """A plumbing payload opened by :func:`open_blob` (signature not yet checked)."""

    payload: bytes
    form: Form
    run: int
    counter: int
    key_id: bytes
    certificate: Certificate | None
    signature: bytes
    signed: bytes


def seal_blob(
    payload: bytes,
    key: Ed25519PrivateKey,
    run: int,
    counter: int,
    certificate: Certificate | None = None,
) -> bytes:
    """``payload`` (any bytes, e.g. a plumbing message) signed for transport.

    Layout: ``payload || form u8 || run u32 || counter u32 || key id or certificate
    || signature(64) || u8 K`` where K counts the bytes from ``form`` to the
    signature; the signature covers everything before it. ``counter`` is the
    sender's monotonic counter (replay protection)."""
    if not 0 <= counter <= _U32_MAX or not 0 <= run <= _U32_MAX:
        raise EncodeError("run tag and counter must be u32")
    if len(payload) > BLOB_MAX_PAYLOAD:
        raise EncodeError(f"payload of {len(payload)} bytes")
    kid = key_id(public_bytes(key))
    if certificate is not None and certificate.key_id != kid:
        raise EncodeError("the certificate is not for this key")
    form = Form.DIGEST if certificate is None else Form.CERTIFICATE
    who = kid if certificate is None else certificate.raw
    signed = payload + _BLOB_EXT.pack(form, run, counter) + who
    return signed + key.sign(signed) + bytes((_BLOB_EXT.size + len(who) + SIG_LEN,))


def open_blob(blob: bytes | bytearray | memoryview) -> SignedBlob:
    """The parts of a :func:`seal_blob` result; ``DecodeError`` and nothing else."""
    buf = bytes(blob)
    if not buf:
        raise DecodeError("empty signed payload")
    k = buf[-1]
    if k < _BLOB_EXT.size + SIG_LEN or k + 1 > len(buf):
        raise DecodeError("truncated signed payload")
    start = len(buf) - 1 - k
    if start > BLOB_MAX_PAYLOAD:
        raise DecodeError("signed payload too large")
    form_value, run, counter = _BLOB_EXT.unpack_from(buf, start)
    who = buf[start + _BLOB_EXT.size : -1 - SIG_LEN]
    cert: Certificate | None = None
    if form_value == Form.DIGEST:
        if len(who) != KEY_ID_LEN:
            raise DecodeError(f"key id of {len(who)} bytes, not {KEY_ID_LEN}")
        kid = who
    elif form_value == Form.CERTIFICATE:
        cert = decode_certificate(who)
        kid = cert.key_id
    else:
        raise DecodeError(f"invalid signed-payload form {form_value}")
    return SignedBlob(
        payload=buf[:start],
        form=Form(form_value),
        run=run,
        counter=counter,
        key_id=kid,
        certificate=cert,
        signature=buf[-1 - SIG_LEN : -1],
        signed=buf[: -1 - SIG_LEN],
    )

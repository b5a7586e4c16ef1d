"""Scheme 1 (Ed25519) and certificates: golden vectors (SPEC.md 7.2), tampering, capacity,
and any bytes either decode or raise ``DecodeError``."""

from __future__ import annotations

import pytest
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import MAX_DATAGRAM, DecodeError, EncodeError, Flags, Kind, decode, encode, max_points
from protocol.auth import (
    DIGEST_TRAILER_LEN,
    MAX_CERT_LEN,
    SIG_LEN,
    Coverage,
    Form,
    Role,
    decode_certificate,
    decode_signed,
    issue_certificate,
    key_id,
    open_blob,
    public_bytes,
    run_tag,
    seal,
    seal_blob,
    signature_ok,
)
from tests.protocol.test_codec import LONG_ID, path_message
from tests.protocol.vectors import VECTORS, assert_same

ROOT = Ed25519PrivateKey.from_private_bytes(bytes([1] * 32))
CAR = Ed25519PrivateKey.from_private_bytes(bytes([2] * 32))
RSU = Ed25519PrivateKey.from_private_bytes(bytes([3] * 32))
NOT_BEFORE, NOT_AFTER = 1767225600, 1798761600  # 2026-01-01 .. 2027-01-01 UTC
RUN = run_tag("run-1")

VEHICLE_CERT = (
    "0101056361722d618139770ea87d175f56a35466c34c7ecccb8d8a91b4ee37a2"
    "5df60f5b8fc9b39400b9556980ec366b34750f98bd59fcfc16bf046f29c127ed"
    "672aff21412da9eca4b9bbe09a51da8a38ef5417d66ec324728b614f1e60dfa1"
    "62571a10919f468ce0961288a26070afae33d77c8a619c0a"
)
RSU_CERT = (
    "0102057273752d31ed4928c628d1c2c6eae90338905995612959273a5c63f936"
    "36c14614ac8737d100b9556980ec366b34750f98bd59fcfcf40100000cfeffff"
    "983a00000103782d302b314bd2794783540d8354ef8d9d4c8c9ef8fabbe6721c"
    "a3f8a2f1c9dbdf5883e03409c318071457320f5bdac732cbed08a55cab66c5f7"
    "1878db80eae8240e0e"
)
FP_SIGNED = (
    "cb03010101000000a85ebc0000000000056361722d61fef7ffff51ffffff7e04"
    "0000c201b4006d050f141400040011fef7ffff51ffffff000000007373736464"
    "6401bd014e65d3fb"
    + VEHICLE_CERT
    + "5cced84a9f3f1da122d977e17b781642ea784fb7f5b16cb8a29aa13518baf397"
    "23d3775906393af0b1fec20b8f9c8a5778d3d9baf55706c8685cbba22a9e4602"
)
MC_SIGNED = (
    "cb0304012b00000050a4f60500000000057273752d31056361722d610102014d"
    "004e65d3fbb62e867fa2f33afedddba9814126df705c28a3177706c24e58afe0"
    "43ed7b2c4a7984253367d3ae502571414f1e7faa4e896560be55fcba0dba7042"
    "b312ef36677ebad696dd4e2708"
)


def vehicle_cert() -> bytes:
    cert = issue_certificate(ROOT, "car-a", Role.VEHICLE, public_bytes(CAR), NOT_BEFORE, NOT_AFTER)
    return cert.raw


def rsu_cert() -> bytes:
    cert = issue_certificate(
        ROOT,
        "rsu-1",
        Role.RSU,
        public_bytes(RSU),
        NOT_BEFORE,
        NOT_AFTER,
        intersections=("x-0",),
        coverage=Coverage(5.0, -5.0, 150.0),
    )
    return cert.raw


def test_key_ids_and_run_tag() -> None:
    assert key_id(public_bytes(ROOT)).hex() == "34750f98bd59fcfc"
    assert key_id(public_bytes(CAR)).hex() == "6a3803d5f059902a"
    assert key_id(public_bytes(RSU)).hex() == "b62e867fa2f33afe"
    assert RUN == 0xFBD3654E
    assert run_tag(None) == 0
    with pytest.raises(ValueError, match="32 bytes"):
        key_id(b"short")


def test_certificate_vectors() -> None:
    assert vehicle_cert().hex() == VEHICLE_CERT
    assert rsu_cert().hex() == RSU_CERT
    v = decode_certificate(bytes.fromhex(VEHICLE_CERT))
    assert (v.subject, v.role, v.intersections, v.coverage) == ("car-a", Role.VEHICLE, (), None)
    assert v.issued_by(public_bytes(ROOT)) and not v.issued_by(public_bytes(CAR))
    r = decode_certificate(bytes.fromhex(RSU_CERT))
    assert (r.subject, r.role, r.intersections) == ("rsu-1", Role.RSU, ("x-0",))
    assert r.coverage == Coverage(5.0, -5.0, 150.0)
    assert r.covers("x-0", 100.0, -5.0) and not r.covers("x-0", 200.0, 0.0)
    assert not r.covers("x-9", 5.0, -5.0) and not v.covers("x-0", 5.0, -5.0)
    assert r.valid_at(NOT_BEFORE) and not r.valid_at(NOT_AFTER + 1)


def test_signed_datagram_vectors() -> None:
    fp_message, _ = VECTORS["fp-basic"]
    cert = decode_certificate(bytes.fromhex(VEHICLE_CERT))
    assert seal(encode(fp_message), CAR, RUN, cert).hex() == FP_SIGNED
    mc_message, _ = VECTORS["mc-initiate"]
    assert seal(encode(mc_message), RSU, RUN).hex() == MC_SIGNED
    for hexed, key, form in ((FP_SIGNED, CAR, Form.CERTIFICATE), (MC_SIGNED, RSU, Form.DIGEST)):
        message, trailer = decode_signed(bytes.fromhex(hexed))
        assert message.header.flags == Flags.AUTH
        assert (trailer.form, trailer.run) == (form, RUN)
        assert trailer.key_id == key_id(public_bytes(key))
        assert signature_ok(public_bytes(key), trailer.signature, trailer.signed)
    message, _ = decode_signed(bytes.fromhex(MC_SIGNED))
    unsigned = decode(bytes.fromhex(VECTORS["mc-initiate"][1]))
    assert message.header.seq == unsigned.header.seq
    assert len(bytes.fromhex(MC_SIGNED)) - len(bytes.fromhex(VECTORS["mc-initiate"][1])) == (
        DIGEST_TRAILER_LEN
    )


def test_every_flipped_byte_breaks_the_signature() -> None:
    data = bytes.fromhex(MC_SIGNED)
    pub = public_bytes(RSU)
    for i in range(len(data)):
        forged = bytearray(data)
        forged[i] ^= 0x01
        try:
            _, trailer = decode_signed(bytes(forged))
        except DecodeError:
            continue
        assert not signature_ok(pub, trailer.signature, trailer.signed), f"byte {i}"


def test_seal_refuses_a_signed_or_foreign_input() -> None:
    signed = bytes.fromhex(MC_SIGNED)
    with pytest.raises(EncodeError, match="without an authentication trailer"):
        seal(signed, RSU, RUN)
    cert = decode_certificate(bytes.fromhex(VEHICLE_CERT))
    with pytest.raises(EncodeError, match="not for this key"):
        seal(encode(VECTORS["mc-initiate"][0]), RSU, RUN, cert)


@pytest.mark.parametrize("kind", [Kind.FUTURE_PATH, Kind.AUTONOMOUS_PATH, Kind.COORDINATED_PATH])
def test_signed_worst_case_message_fits_a_datagram(kind: Kind) -> None:
    assert max_points(Kind.FUTURE_PATH) >= 200
    data = encode(path_message(kind, max_points(kind)))
    key = Ed25519PrivateKey.generate()
    cert = issue_certificate(ROOT, LONG_ID, Role.VEHICLE, public_bytes(key), 0, 2**32 - 1)
    signed = seal(data, key, 2**32 - 1, cert)  # no room for the certificate: digest form
    assert MAX_DATAGRAM - 8 < len(signed) <= MAX_DATAGRAM
    message, trailer = decode_signed(signed)
    assert trailer.form is Form.DIGEST
    assert message.points.shape[0] == max_points(kind)  # type: ignore[union-attr]


def test_small_message_carries_the_certificate() -> None:
    data = encode(path_message(Kind.FUTURE_PATH, 120))
    cert = decode_certificate(bytes.fromhex(VEHICLE_CERT))
    _, trailer = decode_signed(seal(data, CAR, 0, cert))
    assert trailer.form is Form.CERTIFICATE and trailer.certificate == cert


def test_certificate_limits() -> None:
    pub = public_bytes(CAR)
    with pytest.raises(EncodeError, match="at most"):
        issue_certificate(
            ROOT,
            LONG_ID,
            Role.RSU,
            pub,
            0,
            1,
            intersections=("i" * 32, "j" * 32),
            coverage=Coverage(0, 0, 10),
        )
    with pytest.raises(EncodeError, match="coverage"):
        issue_certificate(ROOT, "rsu", Role.RSU, pub, 0, 1)
    with pytest.raises(EncodeError, match="vehicle certificate"):
        issue_certificate(ROOT, "car", Role.VEHICLE, pub, 0, 1, intersections=("x",))
    with pytest.raises(EncodeError, match="validity"):
        issue_certificate(ROOT, "car", Role.VEHICLE, pub, 2, 1)
    with pytest.raises(EncodeError, match="invalid subject"):
        issue_certificate(ROOT, "bad id!", Role.VEHICLE, pub, 0, 1)
    longest = issue_certificate(ROOT, LONG_ID, Role.VEHICLE, pub, 0, 1)
    assert len(longest.raw) <= MAX_CERT_LEN


def test_blob_round_trip_and_tamper() -> None:
    cert = decode_certificate(bytes.fromhex(VEHICLE_CERT))
    for c in (cert, None):
        blob = seal_blob(b"payload", CAR, RUN, 7, c)
        opened = open_blob(blob)
        assert (opened.payload, opened.run, opened.counter) == (b"payload", RUN, 7)
        assert opened.key_id == cert.key_id
        assert signature_ok(cert.public_key, opened.signature, opened.signed)
        forged = bytearray(blob)
        forged[0] ^= 1
        bad = open_blob(bytes(forged))
        assert not signature_ok(cert.public_key, bad.signature, bad.signed)
    assert len(seal_blob(b"", CAR, 0, 0)) == 9 + 8 + SIG_LEN + 1


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_any_bytes_decode_as_certificate_or_raise(data: bytes) -> None:
    try:
        cert = decode_certificate(data)
    except DecodeError:
        return
    assert cert.raw == data


def _mutations(base: bytes) -> st.SearchStrategy[bytes]:
    return st.builds(
        lambda cut, pos, val: (
            (base[:cut] if cut else base)[:pos]
            + bytes((val,))
            + (base[:cut] if cut else base)[pos + 1 :]
        ),
        st.integers(0, len(base)),
        st.integers(0, len(base)),
        st.integers(0, 255),
    )


@settings(max_examples=300, deadline=None)
@given(
    st.one_of(
        st.binary(max_size=400),
        _mutations(bytes.fromhex(FP_SIGNED)),
        _mutations(bytes.fromhex(MC_SIGNED)),
    )
)
def test_any_bytes_decode_signed_or_raise(data: bytes) -> None:
    try:
        message, trailer = decode_signed(data)
    except DecodeError:
        return
    assert message.header.flags & Flags.AUTH
    assert trailer.signed == data[:-SIG_LEN]


@settings(max_examples=300, deadline=None)
@given(st.one_of(st.binary(max_size=300), _mutations(seal_blob(b"x" * 20, CAR, 1, 2))))
def test_any_bytes_open_as_blob_or_raise(data: bytes) -> None:
    try:
        opened = open_blob(data)
    except DecodeError:
        return
    assert opened.signed + opened.signature == data[:-1]


def test_unsigned_vector_has_no_scheme_1_trailer() -> None:
    message = decode(bytes.fromhex(VECTORS["fp-auth"][1]))
    with pytest.raises(DecodeError, match="too short"):
        decode_signed(bytes.fromhex(VECTORS["fp-auth"][1]))
    assert_same(message, VECTORS["fp-auth"][0])


def test_spec_lists_the_signed_vectors() -> None:
    import re
    from pathlib import Path

    import protocol

    text = Path(protocol.__file__).with_name("SPEC.md").read_text(encoding="utf-8")
    pattern = re.compile(r"#### Signed vector `([a-z0-9-]+)`.*?```hex\n(.*?)```", re.DOTALL)
    found = {name: "".join(body.split()) for name, body in pattern.findall(text)}
    assert found == {
        "cert-vehicle": VEHICLE_CERT,
        "cert-rsu": RSU_CERT,
        "fp-signed-cert": FP_SIGNED,
        "mc-signed-digest": MC_SIGNED,
    }

"""Mutual-TLS certificates and access-control rules for the Zenoh transport (issue 13).

Independent of the V2X signatures (``services.edge.trust``): TLS authenticates
the *links* between daemons and routers (and hides the plumbing from
eavesdroppers on TCP); the Ed25519 signatures authenticate every *message*, also
over UDP and through any router. Both come from ``crosspath keys``.

- :func:`make_tls`: an X.509 CA (ECDSA P-256, the ``cryptography`` package) and
  one certificate per node whose common name is the node id, with both
  ``serverAuth`` and ``clientAuth`` (a peer listens and connects), SANs for
  ``localhost``, ``127.0.0.1`` and any hosts given;
- :func:`tls_options`: the Zenoh settings (``ZenohSettings.options``) that make a
  daemon use them with ``enable_mtls``;
- :func:`acl_config`: a Zenoh ``access_control`` block for routers: deny by
  default; each node, identified by its TLS certificate's common name, may
  publish only on its own key expressions (SPEC.md 6).
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import json
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any, Final

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

__all__ = ["CA_CERT", "acl_config", "make_tls", "tls_options"]

CA_CERT: Final = "tls-ca.pem"
"""The TLS root every daemon and router trusts (in the keys directory)."""

_CA_KEY: Final = "tls-ca.key"
_VALIDITY: Final = dt.timedelta(days=30)
_DATA: Final = ("put", "delete")
_ALL: Final = (
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "declare_queryable",
    "reply",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
)


def _write(path: Path, data: bytes, private: bool) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600 if private else 0o644)
    with os.fdopen(fd, "wb") as fh:
        fh.write(data)


def _name(cn: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )


def _ca(directory: Path) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    key_path, cert_path = directory / _CA_KEY, directory / CA_CERT
    if key_path.exists() and cert_path.exists():
        key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
        if not isinstance(key, ec.EllipticCurvePrivateKey):
            raise ValueError(f"{key_path}: not an EC key")
        return key, x509.load_pem_x509_certificate(cert_path.read_bytes())
    key = ec.generate_private_key(ec.SECP256R1())
    now = dt.datetime.now(dt.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(_name("crosspath TLS root"))
        .issuer_name(_name("crosspath TLS root"))
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + _VALIDITY)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .sign(key, hashes.SHA256())
    )
    directory.mkdir(parents=True, exist_ok=True)
    _write(key_path, _key_pem(key), private=True)
    _write(cert_path, cert.public_bytes(serialization.Encoding.PEM), private=False)
    return key, cert


def make_tls(directory: Path, nodes: Iterable[str], hosts: Iterable[str] = ()) -> list[Path]:
    """A TLS CA in ``directory`` (kept if there) and ``<node>.tls.pem`` / ``<node>.tls.key``
    for each node; the certificate files written."""
    ca_key, ca_cert = _ca(directory)
    sans: list[x509.GeneralName] = [x509.DNSName("localhost")]
    for host in ("127.0.0.1", *hosts):
        try:
            sans.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            sans.append(x509.DNSName(host))
    now = dt.datetime.now(dt.UTC)
    written = []
    for node in nodes:
        key = ec.generate_private_key(ec.SECP256R1())
        cert = (
            x509.CertificateBuilder()
            .subject_name(_name(node))
            .issuer_name(ca_cert.subject)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5))
            .not_valid_after(now + _VALIDITY)
            .add_extension(x509.SubjectAlternativeName([*sans, x509.DNSName(node)]), False)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(
                x509.ExtendedKeyUsage(
                    [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
                ),
                critical=False,
            )
            .sign(ca_key, hashes.SHA256())
        )
        _write(directory / f"{node}.tls.key", _key_pem(key), private=True)
        path = directory / f"{node}.tls.pem"
        _write(path, cert.public_bytes(serialization.Encoding.PEM), private=False)
        written.append(path)
    return written


def tls_options(directory: Path, node: str) -> dict[str, Any]:
    """``ZenohSettings.options`` for mutual TLS with the files :func:`make_tls` wrote.

    Endpoints must then be ``tls/host:port``; V2X over ``udp/`` stays unencrypted
    (it is signed), which the Zenoh peer setup of ``deploy/zenoh`` documents."""
    base = "transport/link/tls"
    cert, key, ca = (directory / f"{node}.tls.pem", directory / f"{node}.tls.key", CA_CERT)
    return {
        f"{base}/root_ca_certificate": str(directory / ca),
        f"{base}/listen_certificate": str(cert),
        f"{base}/listen_private_key": str(key),
        f"{base}/connect_certificate": str(cert),
        f"{base}/connect_private_key": str(key),
        f"{base}/enable_mtls": True,
        f"{base}/verify_name_on_connect": False,
    }


def _rule(
    rule_id: str, keys: list[str], messages: Iterable[str], flow: str = "ingress"
) -> dict[str, Any]:
    return {
        "id": rule_id,
        "permission": "allow",
        "flows": [flow],
        "messages": list(messages),
        "key_exprs": keys,
    }


def acl_config(
    prefix: str, vehicles: Iterable[str], rsus: Iterable[str], monitors: Iterable[str]
) -> dict[str, Any]:
    """A Zenoh ``access_control`` block: each node (TLS common name) may publish only on
    its own keys (SPEC.md 6) and subscribe to everything under ``prefix``."""
    p = prefix
    rules = [
        _rule(
            "subscribe",
            [f"{p}/**"],
            ("declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"),
        ),
        _rule("deliver", [f"{p}/**"], _ALL, flow="egress"),
    ]
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []

    def node(nid: str, keys: list[str]) -> None:
        rules.append(_rule(f"pub-{nid}", keys, _DATA))
        alive = [f"{p}/sim/alive/{nid}", f"{p}/sim/alive/{nid}/*"]  # and its generations
        rules.append(_rule(f"alive-{nid}", alive, ("liveliness_token",)))
        subjects.append({"id": nid, "cert_common_names": [nid]})
        policies.append(
            {"rules": ["subscribe", "deliver", f"pub-{nid}", f"alive-{nid}"], "subjects": [nid]}
        )

    for v in vehicles:
        node(
            v,
            [f"{p}/v2x/fp/{v}", f"{p}/v2x/rsu/*/ap/{v}", f"{p}/sim/truth/{v}", f"{p}/stats/{v}"],
        )
    for r in rsus:
        node(r, [f"{p}/v2x/rsu/{r}/**", f"{p}/stats/{r}"])
    for m in monitors:
        node(m, [f"{p}/sim/**", f"{p}/stats/{m}"])
    return {
        "access_control": {
            "enabled": True,
            "default_permission": "deny",
            "rules": rules,
            "subjects": subjects,
            "policies": policies,
        }
    }


def write_acl(path: Path, config: dict[str, Any]) -> None:
    """Write :func:`acl_config` as JSON (valid JSON5) for a router's ``config_file``."""
    path.write_text(json.dumps(config, indent=2) + "\n")

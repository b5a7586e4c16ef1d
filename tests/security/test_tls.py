"""Mutual TLS and access control for Zenoh (services.edge.tls), with real Zenoh sessions:
a client without a certificate cannot connect, and the router's ACL drops a publication
on a key expression that is not the publisher's."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from cryptography import x509

from services.edge.tls import CA_CERT, acl_config, make_tls, tls_options
from services.supervise.launcher import free_ports


def _config(keys: Path, node: str, mode: str, endpoint: str, **extra: Any) -> Any:
    import zenoh

    c = zenoh.Config()
    c.insert_json5("mode", json.dumps(mode))
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5(
        "listen/endpoints" if mode == "router" else "connect/endpoints", json.dumps([endpoint])
    )
    options = tls_options(keys, node)
    if extra.get("no_cert"):
        options = {k: v for k, v in options.items() if k.endswith("root_ca_certificate")}
        c.insert_json5("connect/timeout_ms", "2000")
    for key, value in options.items():
        c.insert_json5(key, json.dumps(value))
    if "acl" in extra:
        c.insert_json5("access_control", json.dumps(extra["acl"]["access_control"]))
    return c


def test_certificates_name_the_node(tmp_path: Path) -> None:
    written = make_tls(tmp_path, ["rsu1"], hosts=["10.0.0.2", "rsu.example"])
    cert = x509.load_pem_x509_certificate(written[0].read_bytes())
    assert cert.subject.rfc4514_string() == "CN=rsu1"
    sans = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert "rsu.example" in sans.get_values_for_type(x509.DNSName)
    assert (tmp_path / CA_CERT).exists() and (tmp_path / "rsu1.tls.key").stat().st_mode & 0o077 == 0


def test_mutual_tls_and_acl_with_real_zenoh(tmp_path: Path) -> None:
    import zenoh

    make_tls(tmp_path, ["router", "A", "rsu1"])
    port = free_ports(1)[0][1]
    endpoint = f"tls/localhost:{port}"
    acl = acl_config("crosspath", ["A"], ["rsu1"], ["monitor"])
    sessions: list[Any] = []
    try:
        sessions.append(zenoh.open(_config(tmp_path, "router", "router", endpoint, acl=acl)))
        car = zenoh.open(_config(tmp_path, "A", "client", endpoint))
        rsu = zenoh.open(_config(tmp_path, "rsu1", "client", endpoint))
        sessions += [car, rsu]
        got: list[str] = []
        sessions.append(
            car.declare_subscriber("crosspath/**", lambda s: got.append(str(s.key_expr)))
        )
        time.sleep(0.5)
        deadline = time.monotonic() + 5.0
        while "crosspath/v2x/rsu/rsu1/cmd/A" not in got and time.monotonic() < deadline:
            rsu.put("crosspath/v2x/rsu/rsu1/cmd/A", b"allowed")
            rsu.put("crosspath/v2x/fp/A", b"not rsu1's key")
            time.sleep(0.2)
        assert "crosspath/v2x/rsu/rsu1/cmd/A" in got
        assert "crosspath/v2x/fp/A" not in got
        # liveliness: a node's own token generations pass, a token on another's key not
        tokens: list[str] = []
        sessions.append(
            rsu.liveliness().declare_subscriber(
                "crosspath/sim/alive/**", lambda s: tokens.append(str(s.key_expr)), history=True
            )
        )
        sessions.append(car.liveliness().declare_token("crosspath/sim/alive/rsu1/3"))
        sessions.append(car.liveliness().declare_token("crosspath/sim/alive/A/3"))
        deadline = time.monotonic() + 5.0
        while "crosspath/sim/alive/A/3" not in tokens and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.3)
        assert tokens == ["crosspath/sim/alive/A/3"]
        refused = False
        try:
            sessions.append(zenoh.open(_config(tmp_path, "A", "client", endpoint, no_cert=True)))
        except zenoh.ZError:
            refused = True
        assert refused, "a client without a certificate connected"
    finally:
        for s in reversed(sessions):
            handle: Any = s
            if isinstance(s, zenoh.Session):
                handle.close()
            else:
                handle.undeclare()

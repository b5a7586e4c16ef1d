"""``crosspath keys ...``: the files it writes load as daemon credentials; errors are one line."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from protocol.auth import Role, decode_certificate
from services.cli.main import main
from services.edge.trust import Authority, read_revocations

PAPER = Path(__file__).resolve().parents[2] / "scenarios" / "paper-blind-intersection.toml"


def test_keys_commands(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    d = tmp_path / "keys"
    assert main(["keys", "init", str(d), "--scenario", str(PAPER)]) == 0
    auth = Authority.open(d)
    for node in ("A", "B", "rsu1", "monitor"):
        assert auth.credentials(node).subject == node
    rsu = decode_certificate((d / "rsu1.cert").read_bytes())
    assert rsu.role is Role.RSU and rsu.intersections == ("X1",)
    assert rsu.coverage is not None and (rsu.coverage.x, rsu.coverage.y) == (0.0, 0.0)
    assert main(["keys", "issue-vehicle", str(d), "C", "--days", "1"]) == 0
    assert (
        main(
            [
                "keys",
                "issue-rsu",
                str(d),
                "rsu2",
                "--intersection",
                "X2",
                "--center",
                "5,-5",
                "--radius",
                "100",
            ]
        )
        == 0
    )
    assert decode_certificate((d / "rsu2.cert").read_bytes()).covers("X2", 5.0, 90.0)
    assert main(["keys", "issue-monitor", str(d), "mon2"]) == 0
    assert main(["keys", "revoke", str(d), "B"]) == 0
    assert read_revocations(d / "revoked.txt") == {auth.credentials("B").key_id}
    assert main(["keys", "show", str(d / "rsu2.cert")]) == 0
    assert "intersections X2" in capsys.readouterr().out
    assert main(["keys", "tls", str(d), "A", "rsu1", "--host", "10.1.2.3"]) == 0
    assert (d / "tls-ca.pem").exists() and (d / "A.tls.key").exists()
    assert main(["keys", "acl", str(d), "--scenario", str(PAPER)]) == 0
    acl = json.loads((d / "acl.json5").read_text())["access_control"]
    assert acl["default_permission"] == "deny"
    assert {s["id"] for s in acl["subjects"]} == {"A", "B", "rsu1", "monitor"}


def test_keys_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    d = tmp_path / "keys"
    assert main(["keys", "init", str(d)]) == 0
    assert main(["keys", "init", str(d)]) == 1
    assert main(["keys", "revoke", str(d), "nobody"]) == 1
    assert main(["keys", "issue-vehicle", str(tmp_path / "none"), "A"]) == 1
    err = capsys.readouterr().err
    assert "already there" in err and "neither a subject" in err
    with pytest.raises(SystemExit) as exc:
        main(
            [
                "keys",
                "issue-rsu",
                str(d),
                "r",
                "--intersection",
                "X",
                "--center",
                "bad",
                "--radius",
                "1",
            ]
        )
    assert exc.value.code == 2

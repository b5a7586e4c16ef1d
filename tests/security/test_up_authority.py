"""``crosspath up`` makes a throw-away authority per run unless ``--insecure``."""

from __future__ import annotations

from pathlib import Path

from services.daemons.vehicle import VehicleDaemonConfig
from services.edge.settings import load_config
from services.edge.trust import load_security
from services.supervise.launcher import prepare_up

PAPER = Path(__file__).resolve().parents[2] / "scenarios" / "paper-blind-intersection.toml"


def _sets(argv: list[str]) -> dict[str, str]:
    pairs = [argv[i + 1] for i, a in enumerate(argv) if a == "--set"]
    return dict(p.split("=", 1) for p in pairs if p.startswith("security."))


def test_signed_by_default_with_keys_in_the_run_dir(tmp_path: Path) -> None:
    up = prepare_up(PAPER, "rsu", run_dir=tmp_path / "run")
    keys = tmp_path / "run" / "keys"
    assert {"root.key", "root.pub", "A.cert", "B.key", "rsu1.cert", "monitor.cert"} <= {
        p.name for p in keys.iterdir()
    }
    for node, argv in up.launcher.commands.items():
        sets = _sets(argv)
        assert sets["security.key"].endswith("{node}.key"), node
        fields = {"node_id": node, "scenario": str(PAPER), **sets}
        config = load_config(VehicleDaemonConfig, None, fields, env={})
        loaded = load_security(config.security, node)
        assert loaded is not None and loaded[0].credentials.subject == node
    again = prepare_up(PAPER, "rsu", run_dir=tmp_path / "run2")
    assert (tmp_path / "run2/keys/root.pub").read_bytes() != (keys / "root.pub").read_bytes()
    del again


def test_insecure_has_no_keys(tmp_path: Path) -> None:
    up = prepare_up(PAPER, "rsu", run_dir=tmp_path / "run", insecure=True)
    assert not (tmp_path / "run" / "keys").exists()
    assert all(not _sets(argv) for argv in up.launcher.commands.values())

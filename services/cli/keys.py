"""``crosspath keys ...``: the deployment's authority, keys, certificates and TLS files.

- ``keys init DIR [--scenario FILE]``: a new root (``root.key``, ``root.pub``,
  ``revoked.txt``); with a scenario, also a key and certificate for each of its
  cars, RSUs (intersection and coverage from the scenario) and the monitor;
- ``keys issue-vehicle DIR ID`` / ``keys issue-rsu DIR ID --intersection X
  --center X,Y --radius R`` / ``keys issue-monitor DIR ID``: one more identity;
- ``keys revoke DIR WHO``: add a subject's key (or a hex key id) to
  ``revoked.txt``; daemons re-read it within a second;
- ``keys tls DIR NODE... [--host H]``: a TLS CA and mutual-TLS certificates for
  Zenoh (``services.edge.tls``), and ``keys acl DIR --scenario FILE``: the Zenoh
  access-control block for routers (``DIR/acl.json5``);
- ``keys show FILE``: what a certificate says.

The daemons name their files in ``[security]`` (``services.edge.settings``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from protocol.auth import Coverage, decode_certificate, key_id
from services.edge.tls import acl_config, make_tls, write_acl
from services.edge.trust import DEFAULT_VALIDITY_S, Authority, rsu_grants
from services.model.scenario import ScenarioError, load_scenario

__all__ = ["configure", "run"]

MONITOR_ID = "monitor"
"""Node id of the monitor when a scenario is provisioned (``crosspath up``'s default)."""


def _dir(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("directory", type=Path, metavar="DIR", help="the keys directory")


def _validity(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--days", type=float, default=DEFAULT_VALIDITY_S / 86400, help="certificate validity"
    )


def configure_init(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath keys init``."""
    _dir(parser)
    parser.add_argument("--scenario", type=Path, help="also issue every actor of this scenario")
    parser.add_argument("--monitor", default=MONITOR_ID, help="monitor id (with --scenario)")
    _validity(parser)


def provision_scenario(auth: Authority, scenario_path: Path, monitor: str, days: float) -> None:
    """Issue keys for every car, RSU and the monitor of a scenario file."""
    sc = load_scenario(scenario_path)
    cars = [v.id for v in sc.vehicles]
    auth.provision(cars, rsu_grants(sc), [monitor], round(days * 86400))


def run_init(args: argparse.Namespace) -> int:
    try:
        auth = Authority.init(args.directory)
        if args.scenario is not None:
            provision_scenario(auth, args.scenario, args.monitor, args.days)
    except (FileExistsError, OSError, ScenarioError, ValueError) as exc:
        sys.stderr.write(f"crosspath keys init: {exc}\n")
        return 1
    print(f"authority in {args.directory} (root key id {key_id(auth.root_public).hex()})")
    return 0


def configure_issue_vehicle(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath keys issue-vehicle``."""
    _dir(parser)
    parser.add_argument("id", help="vehicle id")
    _validity(parser)


def run_issue_vehicle(args: argparse.Namespace) -> int:
    try:
        cert = Authority.open(args.directory).issue_vehicle(args.id, round(args.days * 86400))
    except (OSError, ValueError) as exc:
        sys.stderr.write(f"crosspath keys issue-vehicle: {exc}\n")
        return 1
    print(f"{args.id}: key id {cert.key_id.hex()}")
    return 0


def configure_issue_monitor(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath keys issue-monitor``."""
    _dir(parser)
    parser.add_argument("id", help="monitor node id")
    _validity(parser)


def run_issue_monitor(args: argparse.Namespace) -> int:
    try:
        cert = Authority.open(args.directory).issue_monitor(args.id, round(args.days * 86400))
    except (OSError, ValueError) as exc:
        sys.stderr.write(f"crosspath keys issue-monitor: {exc}\n")
        return 1
    print(f"{args.id}: key id {cert.key_id.hex()}")
    return 0


def _xy(text: str) -> tuple[float, float]:
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not X,Y in metres") from None
    return x, y


def configure_issue_rsu(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath keys issue-rsu``."""
    _dir(parser)
    parser.add_argument("id", help="RSU id")
    parser.add_argument(
        "--intersection", action="append", required=True, help="an intersection it coordinates"
    )
    parser.add_argument("--center", type=_xy, required=True, help="coverage centre X,Y [m]")
    parser.add_argument("--radius", type=float, required=True, help="coverage radius [m]")
    _validity(parser)


def run_issue_rsu(args: argparse.Namespace) -> int:
    try:
        cover = Coverage(args.center[0], args.center[1], args.radius)
        cert = Authority.open(args.directory).issue_rsu(
            args.id, args.intersection, cover, round(args.days * 86400)
        )
    except (OSError, ValueError) as exc:
        sys.stderr.write(f"crosspath keys issue-rsu: {exc}\n")
        return 1
    print(f"{args.id}: key id {cert.key_id.hex()}, {', '.join(cert.intersections)}")
    return 0


def configure_revoke(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath keys revoke``."""
    _dir(parser)
    parser.add_argument("who", help="a subject id with a certificate in DIR, or a hex key id")


def run_revoke(args: argparse.Namespace) -> int:
    try:
        kid = Authority.open(args.directory).revoke(args.who)
    except (OSError, ValueError) as exc:
        sys.stderr.write(f"crosspath keys revoke: {exc}\n")
        return 1
    print(f"revoked {kid.hex()} ({args.who})")
    return 0


def configure_tls(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath keys tls``."""
    _dir(parser)
    parser.add_argument("nodes", nargs="+", metavar="NODE", help="node ids (TLS common names)")
    parser.add_argument(
        "--host", action="append", default=[], help="extra host name or IP for the SANs"
    )


def run_tls(args: argparse.Namespace) -> int:
    try:
        written = make_tls(args.directory, args.nodes, args.host)
    except (OSError, ValueError) as exc:
        sys.stderr.write(f"crosspath keys tls: {exc}\n")
        return 1
    print(f"TLS CA {args.directory / 'tls-ca.pem'}; {len(written)} node certificate(s)")
    return 0


def configure_acl(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath keys acl``."""
    _dir(parser)
    parser.add_argument("--scenario", type=Path, required=True, help="the scenario file")
    parser.add_argument("--prefix", default="crosspath", help="key-expression prefix")
    parser.add_argument("--monitor", default=MONITOR_ID, help="monitor node id")


def run_acl(args: argparse.Namespace) -> int:
    try:
        sc = load_scenario(args.scenario)
        cfg = acl_config(
            args.prefix, [v.id for v in sc.vehicles], [r.id for r in sc.rsus], [args.monitor]
        )
        args.directory.mkdir(parents=True, exist_ok=True)
        write_acl(args.directory / "acl.json5", cfg)
    except (OSError, ScenarioError, ValueError) as exc:
        sys.stderr.write(f"crosspath keys acl: {exc}\n")
        return 1
    print(f"wrote {args.directory / 'acl.json5'}")
    return 0


def configure_show(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath keys show``."""
    parser.add_argument("file", type=Path, metavar="FILE", help="a .cert file")


def run_show(args: argparse.Namespace) -> int:
    try:
        c = decode_certificate(args.file.read_bytes())
    except (OSError, ValueError) as exc:
        sys.stderr.write(f"crosspath keys show: {exc}\n")
        return 1
    print(f"subject {c.subject} ({c.role.name.lower()}), key id {c.key_id.hex()}")
    print(f"issuer {c.issuer.hex()}, valid {c.not_before}..{c.not_after} (unix s)")
    if c.coverage is not None:
        cov = c.coverage
        print(
            f"intersections {', '.join(c.intersections)}; "
            f"coverage ({cov.x}, {cov.y}) r {cov.radius} m"
        )
    return 0


configure = configure_init
run = run_init

"""``crosspath bench security``: what signing costs (issue 13), and the flood benchmark.

Keys this module writes (``results/bench/security.json`` by default):

- ``sign_us_p50`` / ``sign_us_p99``: sealing one encoded 120-point future path
  (``services.edge.trust.Signer.seal``: Ed25519 signature and trailer), µs;
- ``verify_us_p50`` / ``verify_us_p99``: ``TrustStore.verify_datagram`` of one such
  datagram (digest form, certificate cached: trailer parse, replay window, Ed25519
  verification), µs; ``verify_with_cert_us_p50``: the same with the certificate in the
  trailer and a cold cache (one more Ed25519 verification, the root's), µs;
- ``signed_future_path_bytes`` (120 points, digest form, the usual case),
  ``signed_future_path_with_cert_bytes`` (once a second), ``unsigned_future_path_bytes``;
- ``signed_worst_case_bytes``: a ``max_points`` future path with 32-byte ids and
  2-byte deltas, signed: at most 1460;
- ``forged_cert_flood_core_pct``: the share of one core [%] that a flood of forged
  certificates costs ``TrustStore.verify_datagram`` at :data:`FORGED_FLOOD_HZ`, each
  datagram with a new certificate that names the deployment's root as its issuer (the
  costliest forgery: only a whole Ed25519 verification refuses it), measured after
  the store's burst of checks is spent; ``forged_cert_flood_core_pct_unpaced``: the
  same store without its pace (``cert_checks_per_s`` infinite), the baseline, and
  ``forged_cert_flood_ratio`` their ratio (``repeat`` datagrams, simulated arrival
  times);
- with ``--flood-duration S`` (> 0): the ``flood_*`` and ``baseline_*`` keys of
  ``services.bench.flood.flood_section`` (another helper's part: real daemons under a
  5000 msgs/s flood).

:func:`update_json` merges keys into the file, so other measurements can add theirs.
Medians on the machine at hand; machine-dependent.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

from protocol import FuturePath, Header, Kind, Mode, decode, encode, max_points
from protocol.auth import (
    Certificate,
    Role,
    decode_certificate,
    issue_certificate,
    key_id,
    public_bytes,
    run_tag,
    seal,
)
from services.edge.args import non_negative_float, output_file, positive_int
from services.edge.trust import (
    CERT_CHECK_BURST,
    CERT_CHECKS_PER_S,
    Credentials,
    Refused,
    Signer,
    TrustStore,
)

__all__ = ["FORGED_FLOOD_HZ", "configure", "forged_certificate", "measure", "run", "update_json"]

DEFAULT_OUT = Path("results/bench/security.json")
POINTS = 120


def update_json(path: Path, keys: dict[str, Any]) -> dict[str, Any]:
    """Merge ``keys`` into the JSON object in ``path`` (created if missing); the result."""
    doc: dict[str, Any] = {}
    if path.exists():
        try:
            loaded = json.loads(path.read_text())
        except ValueError:
            loaded = {}
        if isinstance(loaded, dict):
            doc = loaded
    doc.update(keys)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(doc, indent=2) + "\n")
    tmp.replace(path)
    return doc


def _path(sender: str, seq: int, n: int, wide: bool = False) -> FuturePath:
    """A straight eastbound future path of ``n`` points 0.084 s apart (1-byte deltas), or
    ``wide``: 2.9 m and 0.3 s apart diagonally (2-byte deltas in every column)."""
    step_m, step_s = (2.9, 0.3) if wide else (1.0, 0.084)
    k = np.arange(n, dtype=np.float64)
    x = -100.0 + k * step_m
    y = k * step_m if wide else np.full(n, -1.75)
    t = seq * 0.1 + k * step_s
    pts = np.column_stack([x, y, t])
    header = Header(sender, seq, round(seq * 100_000))
    return FuturePath(header, x[0], y[0], 12.0, 0.0, 4.5, 1.8, Mode.AUTO, pts)


def _credentials(subject: str) -> tuple[Credentials, bytes]:
    root = Ed25519PrivateKey.generate()
    key = Ed25519PrivateKey.generate()
    cert = issue_certificate(root, subject, Role.VEHICLE, public_bytes(key), 0, 2**32 - 1)
    return Credentials(key, cert, public_bytes(root)), public_bytes(root)


FORGED_FLOOD_HZ = 5000.0
"""Arrival rate of the forged-certificate flood [datagrams per s] (issue 13's flood)."""


def forged_certificate(creds: Credentials, root_id: bytes, variant: int) -> Certificate:
    """``creds``' certificate (issued by another root) made to name the root with key id
    ``root_id`` as its issuer, with a bogus signature that differs per ``variant``: the
    forgery a receiver can refuse only by a whole Ed25519 verification, new in every
    datagram at no cost to the forger (SPEC.md 2.10 layout)."""
    raw = bytearray(creds.certificate.raw)
    at = 43 + len(creds.subject)  # the issuer's key id
    raw[at : at + 8] = root_id
    raw[-8:] = variant.to_bytes(8, "little")
    return decode_certificate(bytes(raw))


class _SimClock:
    """Simulated arrival times of the flood [s]."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def _forged_flood_share(count: int, paced: bool) -> float:
    """Share of one core [%] that ``count`` datagrams, each with a new forgery, arriving
    at :data:`FORGED_FLOOD_HZ`, cost a trust store (``paced``: the daemons' pace of root
    checks, its burst spent first; else none)."""
    _, root = _credentials("car-a")
    evil, _ = _credentials("car-a")
    run = run_tag("bench")
    clock = _SimClock()
    store = TrustStore(
        root,
        run=run,
        monotonic=clock,
        cert_checks_per_s=CERT_CHECKS_PER_S if paced else math.inf,
        cert_check_burst=CERT_CHECK_BURST if paced else math.inf,
    )
    warm = int(store.cert_check_burst) if paced else 0
    batch = []
    for k in range(warm + count):
        cert = forged_certificate(evil, key_id(root), k)
        data = seal(encode(_path("car-a", k + 1, POINTS)), evil.key, run, cert)
        batch.append((data, decode(data)))
    for data, message in batch[:warm]:  # spend the burst: the flood's steady state
        with contextlib.suppress(Refused):
            store.verify_datagram(data, message)
    t0 = time.perf_counter()
    for k, (data, message) in enumerate(batch[warm:]):
        clock.t = k / FORGED_FLOOD_HZ
        with contextlib.suppress(Refused):
            store.verify_datagram(data, message)
    busy_s = time.perf_counter() - t0
    return round(100.0 * busy_s / (count / FORGED_FLOOD_HZ), 1)


def _forged_flood(count: int) -> dict[str, float]:
    """The ``forged_cert_flood_*`` keys."""
    paced = _forged_flood_share(count, paced=True)
    unpaced = _forged_flood_share(count, paced=False)
    return {
        "forged_cert_flood_core_pct": paced,
        "forged_cert_flood_core_pct_unpaced": unpaced,
        "forged_cert_flood_ratio": round(unpaced / paced, 2),
    }


def _us(samples: list[float], q: float) -> float:
    return round(float(np.percentile(samples, q)) * 1e6, 2)


def measure(repeat: int = 2000) -> dict[str, Any]:
    """The signing keys of the module docstring, measured ``repeat`` times each."""
    creds, root = _credentials("car-a")
    run = run_tag("bench")
    signer = Signer(creds, run=run, cert_every_s=float("inf"))
    first = signer.seal(encode(_path("car-a", 0, POINTS)))  # with the certificate
    plain = [encode(_path("car-a", k + 1, POINTS)) for k in range(repeat)]
    sign_s: list[float] = []
    sealed: list[bytes] = []
    for data in plain:
        t0 = time.perf_counter()
        out = signer.seal(data)
        sign_s.append(time.perf_counter() - t0)
        sealed.append(out)
    store = TrustStore(root, run=run)
    store.verify_datagram(first, decode(first))  # caches the certificate
    messages = [decode(d) for d in sealed]
    verify_s: list[float] = []
    for data, message in zip(sealed, messages, strict=True):
        t0 = time.perf_counter()
        store.verify_datagram(data, message)
        verify_s.append(time.perf_counter() - t0)
    cold: list[float] = []
    for k in range(min(repeat, 300)):
        fresh = TrustStore(root, run=run)
        s = Signer(creds, run=run)
        data = s.seal(plain[k])
        message = decode(data)
        t0 = time.perf_counter()
        fresh.verify_datagram(data, message)
        cold.append(time.perf_counter() - t0)
    creds32, _ = _credentials("v" * 32)
    worst = encode(_path("v" * 32, 1, max_points(Kind.FUTURE_PATH), wide=True))
    worst_signed = Signer(creds32, run=run).seal(worst)
    return {
        "sign_us_p50": _us(sign_s, 50),
        "sign_us_p99": _us(sign_s, 99),
        "verify_us_p50": _us(verify_s, 50),
        "verify_us_p99": _us(verify_s, 99),
        "verify_with_cert_us_p50": round(statistics.median(cold) * 1e6, 2),
        "unsigned_future_path_bytes": len(plain[0]),
        "signed_future_path_bytes": len(sealed[0]),
        "signed_future_path_with_cert_bytes": len(first),
        "signed_worst_case_bytes": len(worst_signed),
        "signed_worst_case_points": max_points(Kind.FUTURE_PATH),
        **_forged_flood(repeat),
        "points": POINTS,
        "repeat": repeat,
    }


def configure(parser: argparse.ArgumentParser) -> None:
    """Options of ``crosspath bench security``."""
    parser.add_argument(
        "--json", type=output_file, default=DEFAULT_OUT, metavar="OUT", help="merge results here"
    )
    parser.add_argument("--repeat", type=positive_int, default=2000, help="samples per figure")
    parser.add_argument(
        "--flood-duration",
        type=non_negative_float,
        default=0.0,
        metavar="S",
        help="also run the flood benchmark, S wall seconds per phase (60 for the issue's "
        "target; 0: skip)",
    )


def run(args: argparse.Namespace) -> int:
    """Measure, merge into ``--json``, print a summary."""
    keys = measure(args.repeat)
    if args.flood_duration > 0:
        try:
            from services.bench.flood import flood_section
        except ImportError as exc:  # another helper's module, maybe not there yet
            sys.stderr.write(f"crosspath bench security: no flood benchmark ({exc})\n")
        else:
            keys.update(flood_section(args.flood_duration))
    update_json(args.json, keys)
    print(
        f"sign {keys['sign_us_p50']} us, verify {keys['verify_us_p50']} us (p50); "
        f"120-point future path {keys['unsigned_future_path_bytes']} B unsigned, "
        f"{keys['signed_future_path_bytes']} B signed, "
        f"{keys['signed_future_path_with_cert_bytes']} B with certificate; "
        f"worst case signed {keys['signed_worst_case_bytes']} B; a flood of forged "
        f"certificates takes {keys['forged_cert_flood_core_pct']} % of a core "
        f"({keys['forged_cert_flood_core_pct_unpaced']} % unpaced)"
    )
    print(f"written to {args.json}")
    return 0

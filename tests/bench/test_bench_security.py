"""``crosspath bench security``: the signing figures exist, are sane, and merge into the file."""

from __future__ import annotations

import json
from pathlib import Path

from protocol import MAX_DATAGRAM
from services.bench.security import measure, update_json
from services.cli.main import main


def test_measure_keys_and_sizes() -> None:
    keys = measure(repeat=50)
    assert 0 < keys["sign_us_p50"] < 50_000
    assert 0 < keys["verify_us_p50"] < 50_000
    assert keys["signed_future_path_bytes"] == keys["unsigned_future_path_bytes"] + 79
    assert keys["signed_future_path_with_cert_bytes"] > keys["signed_future_path_bytes"]
    assert MAX_DATAGRAM - 8 < keys["signed_worst_case_bytes"] <= MAX_DATAGRAM
    assert keys["signed_worst_case_points"] >= 200
    # the forged-certificate flood is measured paced and unpaced (the verification counts
    # behind it are asserted in tests/edge/test_trust.py, not these wall-clock shares)
    assert keys["forged_cert_flood_core_pct"] > 0
    assert keys["forged_cert_flood_core_pct_unpaced"] > 0
    assert keys["forged_cert_flood_ratio"] > 0


def test_cli_merges_into_existing_file(tmp_path: Path) -> None:
    out = tmp_path / "security.json"
    update_json(out, {"flood_decision_latency_ms_p99": 12.0})
    assert main(["bench", "security", "--json", str(out), "--repeat", "20"]) == 0
    doc = json.loads(out.read_text())
    assert doc["flood_decision_latency_ms_p99"] == 12.0
    assert {"sign_us_p50", "verify_us_p50", "signed_future_path_bytes"} <= doc.keys()

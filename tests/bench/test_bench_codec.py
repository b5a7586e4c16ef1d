"""``crosspath bench codec``: result keys and sizes (times are reported, never asserted)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

from protocol import FuturePath, Kind, decode, encode, max_points
from protocol.codec import speedups_available
from services.bench import codec as bench

REQUIRED = {
    "sizes_bytes",
    "encode_decode_us",
    "encode_decode_us_p50",
    "speedup_vs_json",
    "size_ratio_vs_paper_json",
    "path_sizes_bytes",
}


def test_sample_path_is_a_decelerating_car() -> None:
    m = bench.sample_future_path(120)
    assert m.points.shape == (120, 3)
    assert np.allclose(np.diff(m.points[:, 2]), bench.SPACING_S)
    steps = np.diff(m.points[:, 0])
    assert np.all(steps > 0) and np.all(np.diff(steps) < 0)  # forward, slowing down
    assert steps[0] / bench.SPACING_S == pytest.approx(12.0, abs=0.1)


def test_measure_sizes_and_keys() -> None:
    result = bench.measure(points=120, repeat=2, number=2)
    assert set(result) >= REQUIRED
    sizes = result["sizes_bytes"]
    assert set(sizes) == set(bench.FORMATS) == set(result["encode_decode_us"])
    assert sizes["crosspath"] == sizes["crosspath_numpy"] == 297
    assert sizes["crosspath"] <= 800
    assert result["c_speedups"] is speedups_available()
    assert result["speedup_c_vs_numpy"] == pytest.approx(
        result["encode_decode_us"]["crosspath_numpy"] / result["encode_decode_us"]["crosspath"]
    )
    # the paper's JSON: about 60 KB for 120 points, at least 50 times ours
    assert 50_000 <= sizes["paper_json"] <= 70_000
    assert result["size_ratio_vs_paper_json"] == sizes["paper_json"] / sizes["crosspath"]
    assert result["size_ratio_vs_paper_json"] >= 50
    assert sizes["crosspath"] < sizes["msgpack"] < sizes["json_arrays"] < sizes["json"]
    assert all(t > 0 for t in result["encode_decode_us"].values())
    assert result["speedup_vs_json"] == pytest.approx(
        result["encode_decode_us"]["json"] / result["encode_decode_us"]["crosspath"]
    )
    assert result["kinds"]["future_path"] == {
        "bytes": 297,
        "max_points": max_points(Kind.FUTURE_PATH),
    }
    assert result["max_points"]["coordinated_path"] == max_points(Kind.COORDINATED_PATH)


def test_baselines_round_trip_the_message() -> None:
    m = bench.sample_future_path(120)
    for name, (enc, dec) in bench.CODECS.items():
        back = dec(enc(m))
        assert back.header.sender == m.header.sender, name
        tolerance = 0.0051 if name.startswith("crosspath") else 1e-6  # ours: 1 cm, 1 ms resolution
        assert np.allclose(back.points, m.points, rtol=0, atol=tolerance), name
    assert decode(bench.CODECS["crosspath"][0](m)).kind is Kind.FUTURE_PATH


def test_paper_json_looks_like_an_autoware_lane() -> None:
    lane = json.loads(bench.paper_json_encode(bench.sample_future_path(3)))
    waypoint = lane["waypoints"][0]
    assert set(waypoint["pose"]["pose"]["position"]) == {"x", "y", "z"}
    assert set(waypoint["pose"]["header"]["stamp"]) == {"secs", "nsecs"}
    assert len(lane["waypoints"]) == 3


def test_cli_writes_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    parser = argparse.ArgumentParser()
    bench.configure(parser)
    out = tmp_path / "sub" / "codec.json"
    args = parser.parse_args(["--json", str(out), "--repeat", "1", "--number", "1"])
    assert bench.run(args) == 0
    result = json.loads(out.read_text())
    assert set(result) >= REQUIRED
    assert result["sizes_bytes"]["crosspath"] == 297
    printed = capsys.readouterr().out
    assert "paper_json" in printed and "speedup" in printed


def test_cli_refuses_bad_point_counts() -> None:
    parser = argparse.ArgumentParser()
    bench.configure(parser)
    for bad in (
        "0",
        str(max_points(Kind.FUTURE_PATH) + 1),
        "x",
    ):  # refused while parsing: exit 2 before any measurement
        with pytest.raises(SystemExit) as exc:
            parser.parse_args(["--points", bad])
        assert exc.value.code == 2


def test_p50_and_targets_are_consistent() -> None:
    result = bench.measure(points=120, repeat=2, number=2)
    assert result["encode_decode_us_p50"] == result["encode_decode_us"]["crosspath"]
    met = result["targets"]["met"]
    assert met["speedup_vs_json"] == (result["speedup_vs_json"] >= bench.TARGET_SPEEDUP_VS_JSON)
    assert met["path_bytes"] is True


def test_realistic_paths_fit_450_bytes() -> None:
    """Diagonal and turning paths need deltas in both x and y: bigger than along an axis."""
    sizes = {name: len(encode(make(120))) for name, make in bench.PATHS.items()}
    assert sizes["axis"] == 297
    assert sizes["axis"] < sizes["diagonal"] <= bench.TARGET_PATH_BYTES
    assert sizes["axis"] < sizes["turning"] <= bench.TARGET_PATH_BYTES
    turn = bench.turning_future_path(120).points
    heading_change = np.arctan2(*(turn[-1, 1::-1] - turn[-2, 1::-1]))
    assert heading_change == pytest.approx(np.pi / 2, abs=0.01)  # ends northbound
    for make in bench.PATHS.values():
        m = make(120)
        back = decode(encode(m))
        assert isinstance(back, FuturePath)
        assert np.allclose(back.points, m.points, rtol=0, atol=0.0051)

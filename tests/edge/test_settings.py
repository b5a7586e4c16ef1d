"""Daemon configuration: precedence file < env < CLI, errors naming the field."""

from __future__ import annotations

import argparse
import io
from pathlib import Path

import pytest

from services.edge.settings import (
    CommonDaemonConfig,
    ConfigError,
    ZenohSettings,
    add_common_arguments,
    config_from_args,
    exit_on_config_error,
    load_config,
    overrides_from_args,
    parse_value,
)


class RsuLikeConfig(CommonDaemonConfig):
    """A daemon model derived from the common one, as the daemons do."""

    intersection: str = "x0"
    coverage_m: float = 150.0


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "daemon.toml"
    path.write_text(text)
    return path


def test_defaults() -> None:
    config = load_config(CommonDaemonConfig, None, {"node_id": "car-a"}, env={})
    assert config.key_prefix == "crosspath"
    assert config.zenoh == ZenohSettings()
    assert config.zenoh.multicast_scouting is False
    assert config.zenoh.max_links == 2
    assert config.time.epoch_unix is None and config.time.speed == 1.0
    assert config.log_level == "INFO"


def test_precedence_file_then_env_then_cli(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        """
node_id = "rsu-file"
stats_period_s = 5.0
coverage_m = 100.0
[zenoh]
listen = ["udp/127.0.0.1:7001"]
connect = ["tcp/127.0.0.1:7100"]
[time]
speed = 2.0
""",
    )
    env = {
        "CROSSPATH_NODE_ID": "rsu-env",
        "CROSSPATH_ZENOH__LISTEN": '["udp/127.0.0.1:7002", "tcp/127.0.0.1:7002"]',
        "CROSSPATH_TIME__SPEED": "4",
        "CROSSPATH_TIME__EPOCH_UNIX": "1700000000.5",
        "HOME": "/root",  # not ours
        "CROSSPATH_RESULTS_DIR": "/tmp/x",  # another tool's variable: ignored
    }
    overrides = {"node_id": "rsu-cli", "time.speed": 8.0}
    config = load_config(RsuLikeConfig, path, overrides, env=env)
    assert config.node_id == "rsu-cli"  # CLI beats env beats file
    assert config.time.speed == 8.0
    assert config.time.epoch_unix == 1700000000.5  # env only
    assert config.zenoh.listen == ["udp/127.0.0.1:7002", "tcp/127.0.0.1:7002"]  # env beats file
    assert config.zenoh.connect == ["tcp/127.0.0.1:7100"]  # file only
    assert config.stats_period_s == 5.0
    assert config.coverage_m == 100.0


def test_cli_arguments_to_overrides(tmp_path: Path) -> None:
    parser = argparse.ArgumentParser()
    add_common_arguments(parser)
    path = write(tmp_path, 'node_id = "car-a"\nlog_level = "debug"\n')
    args = parser.parse_args(
        [
            "--config",
            str(path),
            "--set",
            "zenoh.max_links=4",
            "--set",
            'zenoh.options={"transport/unicast/lowlatency": false}',
            "--set",
            "node_id=7",
            "--listen",
            "udp/127.0.0.1:7447",
            "--listen",
            "tcp/127.0.0.1:7447",
            "--prefix",
            "lab1/crosspath",
            "--log-level",
            "warning",
        ]
    )
    assert overrides_from_args(args) == {
        "zenoh.max_links": 4,
        "zenoh.options": {"transport/unicast/lowlatency": False},
        "node_id": 7,
        "zenoh.listen": ["udp/127.0.0.1:7447", "tcp/127.0.0.1:7447"],
        "key_prefix": "lab1/crosspath",
        "log_level": "warning",
    }
    config = config_from_args(CommonDaemonConfig, args, env={})
    assert config.node_id == "7"
    assert config.zenoh.max_links == 4
    assert config.zenoh.options == {"transport/unicast/lowlatency": False}
    assert config.log_level == "WARNING"
    assert config.key_prefix == "lab1/crosspath"
    assert "max_links" in config.zenoh.model_fields_set


@pytest.mark.parametrize(
    ("source", "field", "reason"),
    [
        ({"overrides": {"node_id": "car-a", "colour": "red"}}, "colour", "Extra inputs"),
        ({"overrides": {"node_id": "car-a", "zenoh.mode": "mesh"}}, "zenoh.mode", "'peer'"),
        ({"overrides": {"node_id": "car-a", "time.speed": 0}}, "time.speed", "greater than 0"),
        (
            {"overrides": {"node_id": "c", "zenoh.connect_timeout_s": 0}},
            "zenoh.connect_timeout_s",
            "greater than 0",
        ),
        ({"overrides": {"node_id": "car a"}}, "node_id", "invalid node id"),
        ({"overrides": {"node_id": "c", "key_prefix": "x/*"}}, "key_prefix", "invalid key prefix"),
        ({"env": {}}, "node_id", "Field required"),
        (
            {"overrides": {"node_id": "c", "zenoh.listen": ["7447"]}},
            "zenoh.listen",
            "not <proto>/<address>",
        ),
        (
            {"env": {"CROSSPATH_NODE_ID": "c", "CROSSPATH_ZENOH__LISTN": '["udp/a:1"]'}},
            "zenoh.listn",
            "Extra inputs",
        ),
        ({"env": {"CROSSPATH_ZENOH__LISTEN": "[udp"}}, "CROSSPATH_ZENOH__LISTEN", "invalid JSON"),
        ({"toml": "node_id = "}, "daemon.toml", "invalid TOML"),
        ({"toml": 'node_id = "c"\nzenoh = 3\n'}, "zenoh", "valid dictionary"),
        (
            {"toml": 'node_id = "c"\nzenoh = 3\n', "overrides": {"zenoh.mode": "peer"}},
            "zenoh",
            "is not a table",
        ),
    ],
)
def test_errors_name_the_field(
    tmp_path: Path, source: dict[str, object], field: str, reason: str
) -> None:
    toml = source.get("toml")
    path = write(tmp_path, str(toml)) if toml is not None else None
    env = source.get("env", {"CROSSPATH_NODE_ID": "c"})
    overrides = source.get("overrides", {})
    assert isinstance(env, dict) and isinstance(overrides, dict)
    with pytest.raises(ConfigError) as caught:
        load_config(CommonDaemonConfig, path, overrides, env=env)
    assert caught.value.field.endswith(field)
    assert reason in caught.value.reason
    assert isinstance(caught.value, ValueError)


def test_missing_file_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="No such file"):
        load_config(CommonDaemonConfig, tmp_path / "nope.toml", {"node_id": "c"}, env={})


def test_bad_set_syntax() -> None:
    parser = argparse.ArgumentParser()
    add_common_arguments(parser)
    with pytest.raises(ConfigError) as caught:
        overrides_from_args(parser.parse_args(["--set", "node_id"]))
    assert caught.value.field == "--set"


def test_exit_on_config_error_message() -> None:
    out = io.StringIO()
    error = ConfigError([("zenoh.mode", "Input should be 'peer', 'client' or 'router'")])
    assert exit_on_config_error("rsu", error, out) == 2
    assert out.getvalue() == (
        "crosspath rsu: config error: zenoh.mode: Input should be 'peer', 'client' or 'router'\n"
    )


@pytest.mark.parametrize(
    ("text", "value"),
    [
        ("2", 2),
        ("2.5", 2.5),
        ("true", True),
        ("null", None),
        ('["a", "b"]', ["a", "b"]),
        ('"quoted"', "quoted"),
        ("udp/0.0.0.0:7447", "udp/0.0.0.0:7447"),
        ("car-a", "car-a"),
    ],
)
def test_parse_value(text: str, value: object) -> None:
    assert parse_value(text) == value


def test_settings_are_frozen() -> None:
    config = load_config(CommonDaemonConfig, None, {"node_id": "c"}, env={})
    with pytest.raises(ValueError):
        config.node_id = "d"  # type: ignore[misc]


@pytest.mark.parametrize(
    ("file", "env", "cli", "expected"),
    [
        (None, None, None, 1.0),  # the model's default
        (2.0, None, None, 2.0),
        (2.0, "3", None, 3.0),  # env beats the file
        (2.0, "3", 4.0, 4.0),  # the command line beats both
        (None, "3", 4.0, 4.0),
        (2.0, None, 4.0, 4.0),
    ],
)
def test_layering_order_of_one_field(
    tmp_path: Path, file: float | None, env: str | None, cli: float | None, expected: float
) -> None:
    path = write(tmp_path, f"[time]\nspeed = {file}\n") if file is not None else None
    environ = {"CROSSPATH_NODE_ID": "c"} | ({"CROSSPATH_TIME__SPEED": env} if env else {})
    overrides = {"time.speed": cli} if cli is not None else {}
    config = load_config(CommonDaemonConfig, path, overrides, env=environ)
    assert config.time.speed == expected


def test_errors_name_the_source_of_the_bad_value(tmp_path: Path) -> None:
    path = write(tmp_path, 'node_id = "c"\nstats_period_s = -1\n')
    with pytest.raises(ConfigError) as caught:
        load_config(CommonDaemonConfig, path, {}, env={})
    assert caught.value.field == "stats_period_s"
    assert caught.value.reason.endswith(f"(from {path})")
    env = {"CROSSPATH_NODE_ID": "c", "CROSSPATH_TIME__SPEED": "0"}
    with pytest.raises(ConfigError) as caught:
        load_config(CommonDaemonConfig, path, {"stats_period_s": 1.0}, env=env)
    assert caught.value.field == "time.speed"
    assert caught.value.reason.endswith("(from CROSSPATH_TIME__SPEED)")
    with pytest.raises(ConfigError) as caught:
        load_config(CommonDaemonConfig, None, {"node_id": "c", "zenoh.listen": ["x"]}, env=env)
    assert caught.value.field == "zenoh.listen"
    assert caught.value.reason.endswith("(from the command line)")
    with pytest.raises(ConfigError) as caught:  # a missing field has no source
        load_config(CommonDaemonConfig, None, {}, env={})
    assert caught.value.reason == "Field required"


def test_environment_values_parsed_by_pydantic_settings() -> None:
    env = {
        "CROSSPATH_NODE_ID": "7",
        "CROSSPATH_LOG_JSON": "true",
        "CROSSPATH_TIME__EPOCH_UNIX": "null",
        "CROSSPATH_ZENOH": '{"mode": "client"}',
        "CROSSPATH_ZENOH__MAX_LINKS": "3",
        "CROSSPATH_ZENOH__OPTIONS": '{"transport/link/tx/lease": 3000}',
    }
    epoch_env = dict(env, CROSSPATH_TIME__EPOCH_UNIX="12.5")
    config = load_config(CommonDaemonConfig, None, {}, env=env)
    assert config.node_id == "7" and config.log_json is True and config.time.epoch_unix is None
    assert (config.zenoh.mode, config.zenoh.max_links) == ("client", 3)
    assert config.zenoh.options == {"transport/link/tx/lease": 3000}
    assert load_config(CommonDaemonConfig, None, {}, env=epoch_env).time.epoch_unix == 12.5
    with pytest.raises(ConfigError) as caught:
        load_config(CommonDaemonConfig, None, {}, env=dict(env, CROSSPATH_ZENOH__CONNECT="tcp/a:1"))
    assert caught.value.field == "CROSSPATH_ZENOH__CONNECT"
    assert "invalid JSON" in caught.value.reason


def test_built_directly_a_config_reads_only_its_arguments(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CROSSPATH_NODE_ID", "from-env")
    monkeypatch.setenv("CROSSPATH_TIME__SPEED", "9")
    config = CommonDaemonConfig(node_id="direct")
    assert config.node_id == "direct" and config.time.speed == 1.0
    # load_config with the real environment does read it
    loaded = load_config(CommonDaemonConfig, None, {})
    assert loaded.node_id == "from-env" and loaded.time.speed == 9.0

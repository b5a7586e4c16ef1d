"""``crosspath view``'s options: refused in one line with exit code 2 before serving."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.cli.main import main


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--port", "70000"], "--port: must be <= 65535"),
        (["--rate", "0"], "--rate: must be > 0"),
        (["--replay", "/nonexistent/trace.csv"], "--replay: /nonexistent/trace.csv: no such file"),
        (["--run-dir", "{tmp}"], "--run-dir:"),
    ],
)
def test_bad_options(
    argv: list[str],
    message: str,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr("services.cli.view.RUN_DIR_WAIT_S", 0.0)
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    try:
        code = main(["view", *argv])
    except SystemExit as exc:
        code = int(str(exc.code))
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("crosspath view: ") and message in err and err.count("\n") == 1, err


def test_trace_without_rows_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    empty = tmp_path / "trace.csv"
    empty.write_text("t,vehicle,s,x,y,speed,accel,reason,detail,mode\n")
    assert main(["view", "--replay", str(empty)]) == 2
    assert "the trace has no rows" in capsys.readouterr().err

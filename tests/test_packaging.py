"""The wheel works without the checkout (issue 11): build it, install it in a fresh venv
outside the source tree, and run the commands a new user runs first, from a directory that
is not the checkout, on the packaged default scenario.

The venv is fresh (no ``--system-site-packages``): the dependencies come from the package
index, and pip's cache makes every install after the first fast. Locally, a machine
without ``venv``/``ensurepip`` or without the index skips; with ``CI`` set it fails.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import venv
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NoReturn

import pytest

from services.model.catalog import DEFAULT_SCENARIO_NAME
from services.model.scenario import load_scenario

pytestmark = [pytest.mark.packaging, pytest.mark.timeout(900)]  # a first install downloads

ROOT = Path(__file__).resolve().parents[1]
IGNORED = shutil.ignore_patterns(
    ".git", ".venv", "results", "build", "dist", "*.egg-info", "__pycache__", ".*_cache",
    ".hypothesis", "*.so",
)  # fmt: skip
"""What a fresh clone does not have: the wheel is built from a clean copy, so a stale
``build/`` of the checkout cannot leak deleted modules into it."""

OFFLINE = ("NewConnectionError", "Failed to establish a new connection", "ProxyError",
           "Temporary failure in name resolution", "Network is unreachable")  # fmt: skip
"""pip's words for an unreachable package index."""


def _unavailable(why: str) -> NoReturn:
    """Skip on a developer's machine; fail on CI, where nothing may be missing."""
    if os.environ.get("CI"):
        pytest.fail(f"packaging test cannot run on CI: {why}")
    pytest.skip(why)


def _run(argv: Sequence[str | Path], cwd: Path, env: dict[str, str], timeout: float) -> str:
    proc = subprocess.run(
        [str(a) for a in argv], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout
    )
    if proc.returncode != 0:
        pytest.fail(
            f"{' '.join(map(str, argv))} exited {proc.returncode}\n"
            f"stdout:\n{proc.stdout[-3000:]}\nstderr:\n{proc.stderr[-3000:]}"
        )
    return proc.stdout


def _pip(argv: Sequence[str | Path], cwd: Path, env: dict[str, str]) -> None:
    """Run pip; an unreachable index is :func:`_unavailable`, any other failure fails."""
    proc = subprocess.run(
        [str(a) for a in argv], cwd=cwd, env=env, capture_output=True, text=True, timeout=600
    )
    if proc.returncode != 0 and any(w in proc.stderr for w in OFFLINE):
        _unavailable(f"package index unreachable: {proc.stderr.strip().splitlines()[-1]}")
    assert proc.returncode == 0, f"{argv}\n{proc.stderr[-3000:]}"


@dataclass(frozen=True)
class Installed:
    wheel: Path
    bin: Path
    cwd: Path
    env: dict[str, str]

    def crosspath(self, *args: str | Path, timeout: float = 300) -> str:
        return _run([self.bin / "crosspath", *args], self.cwd, self.env, timeout)


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Installed:
    """The wheel, built from a clean copy of the tree and installed into a fresh venv."""
    work = tmp_path_factory.mktemp("packaging")
    src, dist, env_dir, elsewhere = (work / d for d in ("src", "dist", "venv", "elsewhere"))
    shutil.copytree(ROOT, src, ignore=IGNORED)
    elsewhere.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["PATH"] = f"{env_dir / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    env["PYTHONNOUSERSITE"] = "1"

    _pip([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", src, "-w", dist], work, env)
    wheels = sorted(dist.glob("crosspath-*.whl"))
    assert len(wheels) == 1, wheels

    try:
        venv.create(env_dir, with_pip=True, clear=True)
    except (subprocess.CalledProcessError, OSError) as exc:
        _unavailable(f"cannot create a venv with pip (python3-venv missing?): {exc}")
    _pip([env_dir / "bin" / "python", "-m", "pip", "install", "-q", wheels[0]], elsewhere, env)
    return Installed(wheels[0], env_dir / "bin", elsewhere, env)


def test_the_wheel_carries_the_default_scenarios_and_no_tests(installed: Installed) -> None:
    names = zipfile.ZipFile(installed.wheel).namelist()
    assert f"scenarios/{DEFAULT_SCENARIO_NAME}.toml" in names
    assert "scenarios/__init__.py" in names
    assert "protocol/SPEC.md" in names
    assert not [n for n in names if n.startswith(("tests/", "deploy/", "results/"))]
    # the codec's C speed-ups are compiled into the wheel, their types beside them
    assert [n for n in names if n.startswith("protocol/_speedups.") and n.endswith(".so")]
    assert "protocol/_speedups.pyi" in names
    # and so is the reservation table's query kernel
    assert [n for n in names if n.startswith("services/rsu/_scan.") and n.endswith(".so")]
    assert "services/rsu/_scan.pyi" in names
    # and a route's projection
    assert [n for n in names if n.startswith("services/model/_geometry.") and n.endswith(".so")]
    assert "services/model/_geometry.pyi" in names


def test_the_installed_codec_uses_its_c_speedups(installed: Installed) -> None:
    code = (
        "from protocol import codec; from services.rsu import reservation, paths; "
        "from services.model import geometry; "
        "print(codec.speedups_available(), reservation.scan_available(), "
        "paths.kernel() is not None, geometry.kernel_available())"
    )
    assert _run([installed.bin / "python", "-c", code], installed.cwd, installed.env, 60) == (
        "True True True True\n"
    )


def test_the_installed_package_is_imported_not_the_checkout(installed: Installed) -> None:
    code = "import services, scenarios; print(services.__file__); print(scenarios.__file__)"
    out = _run([installed.bin / "python", "-c", code], installed.cwd, installed.env, 60)
    for line in out.splitlines():
        path = Path(line).resolve()
        assert path.is_relative_to(installed.bin.parent.resolve()), path
        assert not path.is_relative_to(ROOT), path


def test_version(installed: Installed) -> None:
    assert installed.crosspath("--version").split()[-1][0].isdigit()


def test_sim_runs_the_packaged_default_scenario_by_name(installed: Installed) -> None:
    out = installed.cwd / "out.json"
    installed.crosspath("sim", DEFAULT_SCENARIO_NAME, "--mode", "rsu", "--json", out)
    result = json.loads(out.read_text())
    assert result["mode"] == "rsu"
    assert result["collisions"] == 0
    assert set(result["vehicles"]) == {v.id for v in load_scenario(DEFAULT_SCENARIO_NAME).vehicles}
    for car in result["vehicles"].values():
        assert car["passing_time_s"] is not None and car["passing_time_s"] > 0


def test_experiment_paper_writes_its_artefacts(installed: Installed) -> None:
    out = installed.cwd / "paper"
    installed.crosspath("experiment", "paper", "--trials", "1", "--out", out, timeout=600)
    artefacts = ("results.json", "table.md", "REPORT.md", "passing_times.png", "speed_profiles.png")
    for name in artefacts:
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    doc = json.loads((out / "results.json").read_text())
    assert doc["scenario_name"] == DEFAULT_SCENARIO_NAME
    assert doc["trials"] == 1

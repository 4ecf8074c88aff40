"""``./dev``: serving installs the service extra only; testing installs dev (issue 17).

Runs the real script against a stand-in virtual environment whose ``python`` and
``roguenerf`` only record how they were called (no network, no install).
"""

from __future__ import annotations

import os
import stat
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]

RECORDER = """#!/bin/sh
echo "$(basename "$0") $*" >> "{log}"
"""


def _fake_venv(tmp_path: Path) -> tuple[Path, Path, dict]:
    venv, bin_dir, log = tmp_path / "venv", tmp_path / "venv" / "bin", tmp_path / "calls.log"
    bin_dir.mkdir(parents=True)
    tools = tmp_path / "tools"
    tools.mkdir()
    for exe in (bin_dir / "python", bin_dir / "roguenerf", tools / "redis-server", tools / "initdb"):
        exe.write_text(RECORDER.format(log=log))
        exe.chmod(exe.stat().st_mode | stat.S_IXUSR)
    env = {**os.environ, "ROGUENERF_VENV": str(venv), "PATH": f"{tools}:{os.environ['PATH']}"}
    return venv, log, env


def _dev(*args, env) -> subprocess.CompletedProcess:
    return subprocess.run([str(ROOT / "dev"), *args], env=env, capture_output=True, text=True, timeout=60)


def _installs(log: Path) -> list[str]:
    return [line for line in log.read_text().splitlines() if "pip install" in line and "-e" in line]


def test_serve_installs_the_service_extra_only_and_test_installs_dev(tmp_path):
    venv, log, env = _fake_venv(tmp_path)
    assert _dev("serve", "--port", "8123", env=env).returncode == 0
    assert _installs(log) == ["python -m pip install -q --disable-pip-version-check -e .[service]"]
    assert log.read_text().splitlines()[-1] == "roguenerf serve --port 8123"
    assert _dev("serve", env=env).returncode == 0  # stamped: nothing installed again
    assert len(_installs(log)) == 1

    assert _dev("test", "-q", env=env).returncode == 0  # serving's install does not cover the tests
    assert _installs(log)[1:] == ["python -m pip install -q --disable-pip-version-check -e .[dev]"]
    assert log.read_text().splitlines()[-1] == "python -m pytest -q"
    assert _dev("test", env=env).returncode == 0 and _dev("serve", env=env).returncode == 0
    assert len(_installs(log)) == 2  # dev includes service: both stamped
    torch = [line for line in log.read_text().splitlines() if "torch==2.13.0" in line]
    assert len(torch) == 2  # torch first, before each package install


def test_the_extras_are_what_the_script_promises():
    import tomllib

    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    serving = " ".join(extras["service"])
    for tool in ("pytest", "schemathesis", "matplotlib", "hypothesis"):
        assert tool not in serving
    assert "swagger-ui-bundle-v2" in serving  # /docs offline needs it when serving
    assert "psycopg" not in serving  # PostgreSQL is its own extra (the postgresql one) ...
    assert any(x.startswith("psycopg") for x in extras["postgresql"])
    dev = next(x for x in extras["dev"] if x.startswith("roguenerf["))
    assert {"service", "postgresql", "bench"} <= set(dev[len("roguenerf["):-1].split(","))  # ... that the tests need



def test_dev_roguenerf_forwards_to_the_venvs_command_line(tmp_path):
    """`./dev roguenerf ARGS` runs .venv/bin/roguenerf ARGS after the service install (issue 38:
    the CLI was not on the PATH and ./dev could not run it)."""
    venv, log, env = _fake_venv(tmp_path)
    done = _dev("roguenerf", "enhance", "scene dir", "--view", "r_0", env=env)
    assert done.returncode == 0, done.stderr
    assert _installs(log) == ["python -m pip install -q --disable-pip-version-check -e .[service]"]
    assert log.read_text().splitlines()[-1] == "roguenerf enhance scene dir --view r_0"
    assert _dev("roguenerf", "--help", env=env).returncode == 0
    assert len(_installs(log)) == 1  # stamped: nothing installed again
    assert log.read_text().splitlines()[-1] == "roguenerf --help"


def test_quick_runs_the_unit_tier_only_and_passes_other_args_on(tmp_path):
    venv, log, env = _fake_venv(tmp_path)
    one_file = "tests/unit/roguenerf/geometry/test_geometry.py"
    result = _dev("test", "--quick", "-q", one_file, env=env)
    assert result.returncode == 0, result.stderr
    assert log.read_text().splitlines()[-1] == (
        f"python -m pytest -m not service and not workers and not browser and not slow -q {one_file}")
    assert _dev("test", "-x", env=env).returncode == 0  # without --quick: every tier, args as given
    assert log.read_text().splitlines()[-1] == "python -m pytest -x"


def test_quick_tier_matches_the_registered_markers():
    import tomllib

    markers = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"]["markers"]
    names = {m.split(":", 1)[0] for m in markers}
    assert {"unit", "service", "workers", "browser", "slow"} <= names
    script = (ROOT / "dev").read_text()
    quick = script.split('QUICK_TIER="', 1)[1].split('"', 1)[0]
    assert quick == "not service and not workers and not browser and not slow"


def test_unknown_commands_are_refused_with_the_usage_and_install_nothing(tmp_path):
    venv, log, env = _fake_venv(tmp_path)
    for args in (("bogus",), ("--quick",), ()):
        result = _dev(*args, env=env)
        assert result.returncode == 2, (args, result.stderr)
        assert result.stderr.startswith("usage: ./dev serve"), result.stderr
        assert "./dev test [--quick] [pytest args]" in result.stderr
        assert "Traceback" not in result.stderr and result.stdout == ""
    assert not log.exists()  # nothing was installed or run

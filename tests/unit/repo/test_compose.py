"""docker-compose.yml, Dockerfile and .dockerignore, checked statically (Docker cannot run
here): the settings that matter for safety and for not losing jobs."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from service.settings import Settings

ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load((ROOT / "docker-compose.yml").read_text())


def _seconds(text: str) -> float:
    units = {"h": 3600, "m": 60, "s": 1, "ms": 0.001}
    parts = re.findall(r"(\d+(?:\.\d+)?)(ms|h|m|s)", str(text))
    assert parts and "".join(a + b for a, b in parts) == str(text), f"unparsable duration {text!r}"
    return sum(float(n) * units[u] for n, u in parts)


def _env(service: dict) -> dict[str, str]:
    env = service.get("environment", {})
    return dict(env) if isinstance(env, dict) else dict(item.split("=", 1) for item in env)


def test_services_and_network_exposure(compose):
    services = compose["services"]
    assert set(services) == {"api", "worker", "redis", "postgres"}
    for name in ("redis", "worker", "postgres"):
        assert "ports" not in services[name], name
    ports = services["api"]["ports"]
    assert ports and all(str(p).startswith("127.0.0.1:") for p in ports)


def test_redis_persists_with_append_only_file(compose):
    redis = compose["services"]["redis"]
    command = redis["command"]
    assert command[command.index("--appendonly") + 1] == "yes"
    assert any(v.endswith(":/data") for v in redis["volumes"])
    assert redis["volumes"][0].split(":")[0] in compose["volumes"]


def test_worker_drains_on_sigint_within_grace(compose):
    worker = compose["services"]["worker"]
    env = _env(worker)
    assert worker["stop_signal"] == "SIGINT"
    grace = _seconds(worker["stop_grace_period"])
    assert grace > float(env["ROGUENERF_CHECKPOINT_EVERY_S"])
    assert grace > float(env["ROGUENERF_DRAIN_TIMEOUT"])
    assert worker["command"] == ["python", "-m", "workers"]


def test_api_and_worker_share_settings_and_data(compose):
    api, worker = compose["services"]["api"], compose["services"]["worker"]
    fields = set(Settings.model_fields)
    for service in (api, worker):
        env = _env(service)
        assert env["ROGUENERF_REDIS_URL"].startswith("redis://redis:")
        assert env["ROGUENERF_DATABASE_URL"].startswith("postgresql://")
        assert service["depends_on"]["postgres"]["condition"] == "service_healthy"
        unknown = {k for k in env if k.removeprefix("ROGUENERF_").lower() not in fields}
        assert not unknown, f"compose sets variables Settings does not know: {unknown}"
        assert service["depends_on"]["redis"]["condition"] == "service_healthy"
    data = {v for v in api["volumes"] if v.endswith(":/data")}
    assert data and data == {v for v in worker["volumes"] if v.endswith(":/data")}
    assert "ROGUENERF_API_KEY" not in _env(worker)
    # ${ROGUENERF_API_KEY:-} arrives as "" when unset: that must mean "no key", not "empty key".
    assert Settings(api_key="", data_dir=ROOT / "data").api_key is None


def test_commands_point_at_real_entry_points(compose):
    from service.app import create_app

    api_cmd = compose["services"]["api"]["command"]
    assert "--factory" in api_cmd and "service.app:create_app" in api_cmd and callable(create_app)
    assert (ROOT / "workers" / "__main__.py").is_file()


def test_dockerfile_cpu_torch_and_non_root():
    text = (ROOT / "Dockerfile").read_text()
    assert re.search(r"^ARG TORCH_VERSION=2\.13\.0$", text, re.M)
    assert re.search(r"^ARG TORCH_INDEX_URL=https://download\.pytorch\.org/whl/cpu$", text, re.M)
    torch_line = text.index('pip install "torch==${TORCH_VERSION}" --index-url "${TORCH_INDEX_URL}"')
    assert torch_line < text.index('pip install ".[service,postgresql]"'), "torch must be installed before the package"
    assert re.search(r"^USER (?!root)\S+", text, re.M)
    assert "/healthz" in text
    # The packages the API and the worker run (jobs: what both share; docs/architecture.md, Layers).
    for package in ("roguenerf", "jobs", "service", "workers", "roguecli"):
        assert re.search(rf"^COPY {package} \./{package}$", text, re.M), package
    # API and worker containers share the host's cores (as `roguenerf serve` sets it)
    assert re.search(r"^\s+OMP_WAIT_POLICY=PASSIVE$", text, re.M)
    # The fused C kernels are compiled in the container, for its CPU: a compiler is installed,
    # and the package ships their source.
    assert re.search(r"apt-get install [^\n]*\bgcc\b", text)
    pyproject = (ROOT / "pyproject.toml").read_text()
    assert re.search(r'^roguenerf = \[.*"native/\*\.c"', pyproject, re.M)


def test_dockerignore_keeps_secrets_and_bulk_out():
    ignored = set((ROOT / ".dockerignore").read_text().split())
    assert {".git", ".venv", "data"} <= ignored


def test_postgres_job_table_matches_its_server(compose):
    from sqlalchemy.engine import make_url

    pg = compose["services"]["postgres"]
    env = _env(pg)
    url = make_url(_env(compose["services"]["worker"])["ROGUENERF_DATABASE_URL"])
    assert (url.host, url.port or 5432) == ("postgres", 5432)
    assert (url.username, url.database) == (env["POSTGRES_USER"], env["POSTGRES_DB"])
    assert url.password == env["POSTGRES_PASSWORD"]  # the same ${ROGUENERF_DB_PASSWORD:-...}
    # The data survives a restart: the cluster lives on a named volume.
    (volume,) = [v for v in pg["volumes"] if v.endswith(":/var/lib/postgresql/data")]
    assert volume.split(":")[0] in compose["volumes"]
    assert "pg_isready" in pg["healthcheck"]["test"]


def test_every_service_has_a_healthcheck_and_workers_scale(compose):
    services = compose["services"]
    for name, service in services.items():
        test = service.get("healthcheck", {}).get("test")
        assert test and test[0] == "CMD", name
    # The API container's check is the service's liveness route (no key needed there).
    assert "/healthz" in " ".join(services["api"]["healthcheck"]["test"])
    # Workers: several by default, more with --scale (no container_name, no published port,
    # which would make replicas collide).
    worker = services["worker"]
    assert worker["deploy"]["replicas"] >= 2 and "container_name" not in worker
    assert worker["depends_on"]["api"]["condition"] == "service_healthy"
    text = (ROOT / "docker-compose.yml").read_text()
    assert "--scale worker=3" in text
    assert "--scale worker=3" in (ROOT / "docs" / "service.md").read_text()


def test_worker_healthcheck_runs_against_a_real_database(compose, tmp_path):
    # The worker's check command, run here against a real SQLite job table and a dead URL.
    import os
    import subprocess
    import sys

    cmd = compose["services"]["worker"]["healthcheck"]["test"][1:]
    assert cmd[0] == "python"
    env = {k: v for k, v in os.environ.items() if not k.startswith("ROGUENERF_")}
    env["PYTHONPATH"] = str(ROOT)
    ok = subprocess.run([sys.executable, *cmd[1:]], env={**env, "ROGUENERF_DATA_DIR": str(tmp_path)},
                        capture_output=True, timeout=60)
    assert ok.returncode == 0, ok.stderr.decode()
    bad = subprocess.run([sys.executable, *cmd[1:]], capture_output=True, timeout=60,
                         env={**env, "ROGUENERF_DATA_DIR": str(tmp_path),
                              "ROGUENERF_DATABASE_URL": "postgresql://u@127.0.0.1:1/db"})
    assert bad.returncode != 0 and b"DatabaseError" in bad.stderr

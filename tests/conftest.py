"""Shared test settings: the real scenes in ../shared/data and a hypothesis profile for 2 cores."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest
import torch
from hypothesis import settings

# One intra-op thread per test process: tests also run worker subprocesses, and OpenMP threads
# spinning against each other on 2 cores made runs several times slower, not faster.
torch.set_num_threads(1)


def _resolve_anyio_lazy_imports() -> None:
    """Import every module anyio loads lazily, here, in the main thread. anyio is a pytest plugin,
    so pytest rewrites its modules on import; a live server's request thread importing one
    (starlette's FileResponse -> ``anyio.open_file``) while another thread parses made CPython
    3.11.7's ``ast.parse`` fail with "AST constructor recursion depth mismatch", and the
    request was dropped (test_reliability_auth, twice in ~10 full runs)."""
    import anyio

    # anyio has no __all__: its lazy importer lists the names in dir() (an earlier version of this
    # loop read __all__, found nothing and imported nothing).
    for name in dir(anyio):
        getattr(anyio, name)
    assert "anyio._core._fileio" in sys.modules, "anyio.open_file's module was not imported"


_resolve_anyio_lazy_imports()

settings.register_profile("ci", deadline=None, max_examples=30, derandomize=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

# The one-view command keeps its pose judgements per scene in the user's cache
# (roguenerf.enhance.settled): a test session keeps them in a folder of its own.
if "ROGUENERF_SETTLED_CACHE" not in os.environ:
    import atexit
    import shutil
    import tempfile

    os.environ["ROGUENERF_SETTLED_CACHE"] = tempfile.mkdtemp(prefix="roguenerf-settled-")
    atexit.register(shutil.rmtree, os.environ["ROGUENERF_SETTLED_CACHE"], True)

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("ROGUENERF_SHARED_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def lego_dir() -> Path:
    """The real lego scene (100 train / 25 test views, radiance-field renders and depths)."""
    path = SHARED_DATA / "lego"
    if not (path / "transforms.json").is_file():
        pytest.fail(f"the real lego scene is missing at {path} (set ROGUENERF_SHARED_DATA)")
    return path


@pytest.fixture
def one_thread():
    """One intra-op thread during a test, the caller's count restored after. The models here are
    tiny and a fit is many small tensor operations: on a shared 2-core machine a second OpenMP
    thread spinning against other processes costs far more than it gains (measured: 4x to 20x
    slower with 2 threads). A module takes it with ``pytestmark = pytest.mark.usefixtures("one_thread")``."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def toy(request, tmp_path_factory) -> dict:
    """A toy scene and a micro checkpoint for a module's uploads (``service_helpers.toy_upload``:
    ``folder``, ``scene``, ``zip``, ``zip_file``, ``ckpt``, ``checkpoint``). A module sets
    ``TOY_SCENE = {...}`` for other ``make_scene`` arguments (seed, size, views)."""
    from tests.service_helpers import toy_upload

    return toy_upload(tmp_path_factory.mktemp("toy"), **getattr(request.module, "TOY_SCENE", {}))


@pytest.fixture(scope="session")
def postgres_server():
    """One PostgreSQL server (Debian's, on loopback, in a temp dir) for the whole session."""
    from tests.service_helpers import PostgresServer

    server = PostgresServer()
    with server:
        yield server


@pytest.fixture(params=["sqlite", "postgresql"])
def database_url(request, tmp_path):
    """The job database, once on a SQLite file (WAL) and once on a fresh PostgreSQL database."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'jobs.db'}"
    return request.getfixturevalue("postgres_server").new_database()


# ----------------------------------------------------------------------------- test tiers
# Every test gets one tier marker by what it needs, so `./dev test --quick` (the unit tier:
# -m "not service and not workers and not browser and not slow") needs no server at all.
# The tier follows from the test's folder (tests/unit, tests/service, tests/workers,
# tests/browser), raised by what it uses, so new tests are placed without a decorator: a test
# that uses worker/API processes, Redis or PostgreSQL (their helpers or fixtures) is `workers`;
# one that runs the app in-process (LiveServer, TestClient) is at least `service`; the browser
# helpers make it `browser`. An explicit marker on a test or module wins.
TIERS = ("browser", "workers", "service", "unit")
_WORKER_FIXTURES = {"postgres_server", "database_url"}
_WORKER_NAMES = {"WorkerProcess", "ApiProcess", "PostgresServer", "redis_server"}
_SERVICE_NAMES = {"LiveServer", "TestClient", "create_app"}


def tier_of(module_name: str, module_globals: dict, fixtures) -> str:
    """The tier a test belongs to (see above): browser > workers > service > unit.
    ``module_name`` is the dotted name, ``tests.<folder>.…``."""
    found = {"unit"}
    parts = module_name.split(".")
    if len(parts) > 2 and parts[0] == "tests" and parts[1] in TIERS:
        found.add(parts[1])
    if _WORKER_FIXTURES & set(fixtures) or _WORKER_NAMES & set(module_globals):
        found.add("workers")
    if _SERVICE_NAMES & set(module_globals):
        found.add("service")
    if any(getattr(v, "__module__", None) == "tests.browser_helpers" for v in module_globals.values()):
        found.add("browser")
    return next(t for t in TIERS if t in found)


def pytest_collection_modifyitems(config, items):
    for item in items:
        if any(item.get_closest_marker(t) for t in TIERS):
            continue
        module = getattr(item, "module", None)
        name = module.__name__ if module else ""
        item.add_marker(tier_of(name, vars(module) if module else {}, item.fixturenames))

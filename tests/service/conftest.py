"""The live server the service tests share, once per module: ``server`` (uvicorn in a thread on a
free loopback port, on a fresh data directory, with ``FAST`` and the module's ``SERVER = {...}``
settings), a ``client`` of it (with the API key when ``SERVER`` sets one), ``scene_id`` (the
``toy`` scene and checkpoint registered), and ``s``: all of it as one ``reliability_helpers.Site``."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="module")
def server(request, tmp_path_factory):
    from service.settings import Settings
    from tests.service_helpers import FAST, LiveServer

    options = {**FAST, **getattr(request.module, "SERVER", {})}
    with LiveServer(Settings(data_dir=tmp_path_factory.mktemp("data"), **options)) as live:
        yield live


@pytest.fixture(scope="module")
def client(server):
    key = server.settings.api_key
    with server.client(headers={"Authorization": f"Bearer {key.get_secret_value()}"} if key else {}) as c:
        yield c


@pytest.fixture(scope="module")
def scene_id(client, toy) -> str:
    from tests.service_helpers import register

    r = register(client, toy["zip"], toy["checkpoint"])
    assert r.status_code == 201, r.text
    return r.json()["id"]


@pytest.fixture(scope="module")
def s(server, client, toy, scene_id):
    from tests.reliability_helpers import Site

    return Site(server, client, toy["scene"], scene_id, toy["checkpoint"], toy["zip"])

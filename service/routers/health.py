"""Liveness and readiness."""

from __future__ import annotations

import os
import uuid

from fastapi import APIRouter
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse

from service.errors import error_body
from service.state import ServicesDep

router = APIRouter(tags=["health"])


@router.get("/healthz", summary="Liveness: the process answers")
async def get_health() -> dict:
    return {"status": "ok"}


def _checks(services) -> dict[str, str]:
    checks: dict[str, str] = {}
    probe = services.layout.tmp / f".ready-{uuid.uuid4().hex}"
    try:
        probe.write_bytes(b"ok")
        probe.unlink()
        checks["data_dir"] = "ok"
    except OSError as exc:
        checks["data_dir"] = f"not writable: {exc}"
    try:
        services.store.db.ping()
        checks["database"] = "ok"
    except Exception as exc:
        checks["database"] = f"unreachable: {exc}"
    try:
        services.queue.pending()
        checks["queue"] = "ok"
    except Exception as exc:
        checks["queue"] = f"unreachable: {exc}"
    return checks


@router.get("/readyz", summary="Readiness: data dir writable, job database and queue reachable",
            responses={503: {"description": "a dependency is not ready"}})
async def get_ready(services: ServicesDep):
    checks = await run_in_threadpool(_checks, services)
    if all(v == "ok" for v in checks.values()):
        return {"status": "ready", "checks": checks, "queue": services.queue.backend, "pid": os.getpid()}
    failing = ", ".join(f"{k}: {v}" for k, v in checks.items() if v != "ok")
    return JSONResponse(error_body("not_ready", failing, checks=checks), status_code=503)

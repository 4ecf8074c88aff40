"""Claim a job and hand it to its task: fine-tuning (:mod:`workers.tasks`), a camera path
(:mod:`workers.paths`) or a 3DGS import (:mod:`workers.imports`), under a heartbeat (:mod:`workers.runtime`)."""

from __future__ import annotations

import logging
import uuid

from workers.imports import run_import_job
from workers.paths import run_path_job
from workers.runtime import Heartbeat, WorkerContext
from workers.tasks import run_finetune_job

log = logging.getLogger("roguenerf.worker")


def run_job(ctx: WorkerContext, job_id: str) -> str:
    """Claim and run one job; returns what happened (for logs and tests)."""
    lease = uuid.uuid4().hex
    job = ctx.store.claim(job_id, lease)
    if job is None:
        log.info("job %s not claimable (not queued any more); message dropped", job_id)
        return "skipped"
    log.info("job %s: attempt %s on scene %s", job_id, job["attempt"], job["scene_id"])
    beat = Heartbeat(ctx.store, job_id, lease, ctx.settings.heartbeat_period)
    beat.start()
    try:
        kind = (job.get("request") or {}).get("kind")
        if kind == "path":
            return run_path_job(ctx, job, lease, beat)
        if kind == "import":
            return run_import_job(ctx, job, lease, beat)
        return run_finetune_job(ctx, job, lease, beat)
    finally:
        beat.stop.set()
        beat.join()

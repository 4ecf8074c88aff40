"""The worker's kinds of job: fine-tuning (:mod:`workers.tasks`), a camera path
(:mod:`workers.paths`) and a 3DGS import (:mod:`workers.imports`), each a body run through the one
lifecycle of :mod:`jobs.lifecycle` (claim, heartbeat, how a job ends)."""

from __future__ import annotations

from jobs.lifecycle import WorkerContext
from jobs.lifecycle import run_job as run_claimed
from workers.imports import IMPORT
from workers.paths import PATH
from workers.tasks import FINETUNE

TASKS = {"finetune": FINETUNE, "path": PATH, "import": IMPORT}
"""A job's ``request["kind"]`` -> its task; a request without one is a fine-tune."""


def run_job(ctx: WorkerContext, job_id: str) -> str:
    """Claim and run one job; returns what happened (for logs and tests)."""
    return run_claimed(ctx, job_id, TASKS, default="finetune")

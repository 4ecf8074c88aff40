"""Fine-tuning jobs: status and cancellation."""

from __future__ import annotations

from fastapi import APIRouter, Response

from service.errors import ApiError, error_responses
from service.schemas import JobPublic
from service.state import ServicesDep
from workers.layout import ID_RE

router = APIRouter(prefix="/jobs", tags=["jobs"])


def job_or_404(services, job_id: str) -> dict:
    row = services.store.get_job(job_id) if ID_RE.match(job_id) else None
    if row is None:
        raise ApiError(404, "not_found", f"job {job_id!r} not found")
    return row


@router.get("/{job_id}", response_model=JobPublic, summary="State, progress, ETA, loss, metrics",
            responses=error_responses(404))
def read_job(job_id: str, services: ServicesDep) -> JobPublic:
    return JobPublic.from_row(job_or_404(services, job_id))


@router.post("/{job_id}/cancel", response_model=JobPublic,
             summary="Cancel: a queued job at once, a running one at its next step",
             responses={**error_responses(404, 409),
                        202: {"description": "cancellation requested; the job stops at its next step"}})
def cancel_job(job_id: str, services: ServicesDep, response: Response) -> JobPublic:
    job = job_or_404(services, job_id)
    if job["state"] in ("succeeded", "failed"):
        raise ApiError(409, "job_finished", f"job {job_id} already {job['state']}; nothing to cancel")
    job = services.store.request_cancel(job_id)
    if job["state"] == "running":
        response.status_code = 202
    return JobPublic.from_row(job)

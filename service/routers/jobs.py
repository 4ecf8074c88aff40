"""Fine-tuning jobs: status and cancellation."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query, Response
from fastapi.responses import FileResponse

from jobs.layout import ID_RE
from jobs.store import ACTIVE_STATES
from service.errors import ApiError, error_responses
from service.pagination import CursorQuery, LimitQuery, decode_cursor, page
from service.schemas import JobPage, JobPublic
from service.state import ServicesDep

router = APIRouter(prefix="/jobs", tags=["jobs"])


def job_or_404(services, job_id: str) -> dict:
    row = services.store.get_job(job_id) if ID_RE.match(job_id) else None
    if row is None:
        raise ApiError(404, "not_found", f"job {job_id!r} not found")
    return row


JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]


@router.get("", response_model=JobPage, summary="List jobs, newest first (paginated; filter by scene and state)",
            responses=error_responses(400, 422))
def list_jobs(
    services: ServicesDep,
    scene_id: Annotated[str | None, Query(max_length=64, description="only this scene's jobs")] = None,
    state: Annotated[list[JobState] | None, Query(description="only jobs in these states (repeatable)")] = None,
    limit: LimitQuery = 50,
    cursor: CursorQuery = None,
) -> JobPage:
    rows = services.store.list_jobs(scene_id=scene_id, states=tuple(dict.fromkeys(state or ())),
                                    limit=limit + 1, before=decode_cursor(cursor))
    rows, next_cursor = page(rows, limit)
    return JobPage(items=[JobPublic.from_row(r) for r in rows], next_cursor=next_cursor)


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
    if job["state"] not in ACTIVE_STATES:  # succeeded, failed or already cancelled: finished
        raise ApiError(409, "job_finished", f"job {job_id} already {job['state']}; nothing to cancel")
    job = services.store.request_cancel(job_id)
    if job["state"] not in ACTIVE_STATES and job["state"] != "cancelled":
        # It finished between the read and the cancel (a worker completed it meanwhile).
        raise ApiError(409, "job_finished", f"job {job_id} already {job['state']}; nothing to cancel")
    if job["state"] == "running":
        response.status_code = 202
    elif job["state"] == "cancelled" and (job["request"] or {}).get("kind") == "path":
        services.layout.remove_tree(services.layout.job_dir(job_id))  # its upload: no worker will run it
    return JobPublic.from_row(job)


RESULT_FILES = {
    "video": ("output/enhanced.mp4", "video/mp4", "enhanced.mp4"),
    "side_by_side": ("output/side_by_side.mp4", "video/mp4", "side_by_side.mp4"),
    "frames": ("output/frames.zip", "application/zip", "frames.zip"),
    "flicker": ("output/flicker.json", "application/json", "flicker.json"),
}


@router.get("/{job_id}/result", summary="A finished camera-path job's MP4 (or its frames zip, side-by-side, flicker)",
            response_class=FileResponse,
            responses={**error_responses(404, 409), 200: {"content": {"video/mp4": {}, "application/zip": {}},
                                                         "description": "the file"}})
def read_job_result(
    job_id: str,
    services: ServicesDep,
    what: Annotated[Literal["video", "side_by_side", "frames", "flicker"],
                    Query(description=("video (enhanced MP4), side_by_side (render | enhanced), frames (zip), "
                                       "flicker"))] = "video",
) -> FileResponse:
    job = job_or_404(services, job_id)
    if (job["request"] or {}).get("kind") != "path":
        raise ApiError(404, "not_found", f"job {job_id} is a fine-tuning job: its result is the scene's checkpoint")
    if job["state"] != "succeeded":
        raise ApiError(409, "job_not_finished", f"job {job_id} is {job['state']}; its result exists once it succeeded")
    relative, media_type, filename = RESULT_FILES[what]
    path = services.layout.job_dir(job_id) / relative
    if not path.is_file():
        raise ApiError(404, "not_found", f"job {job_id} has no {what} result")
    return FileResponse(path, media_type=media_type, filename=filename)

"""Route dependencies that several routers share: a scene row or 404, a scene's public view, a
job queued with its input folder."""

from __future__ import annotations

from pathlib import Path

from jobs.layout import ID_RE
from jobs.queue import QueueUnavailable
from service.errors import ApiError
from service.schemas import ScenePublic, iso
from service.state import Services
from service.storage import place


def scene_or_404(services: Services, scene_id: str) -> dict:
    row = services.store.get_scene(scene_id) if ID_RE.match(scene_id) else None
    if row is None:
        raise ApiError(404, "not_found", f"scene {scene_id!r} not found")
    return row


def scene_public(services: Services, row: dict, *, active_job: str | None | bool = False,
                 warnings: list[str] | None = None) -> ScenePublic:
    """The public view of a scene row (``active_job``: its active job's id when already known;
    ``warnings``: the registration's, e.g. unusable views)."""
    if active_job is False:
        active = services.store.active_job(row["id"])
        active_job = active["id"] if active else None
    return ScenePublic(
        id=row["id"], name=row.get("name"), views=row["views"], train_views=row["train_views"],
        test_views=row["test_views"],
        width=row["width"], height=row["height"], created_at=iso(row["created_at"]),
        active_version=row["active_version"], checkpoint_versions=services.layout.versions(row["id"]),
        active_job=active_job, warnings=warnings or [],
    )


def queue_with_input(services: Services, job: dict, source: Path) -> None:
    """Move a validated input folder into the new ``job``'s folder and queue the job; on any
    failure the job row and its folder go again (a 503 when the queue is down)."""
    layout = services.layout
    try:
        job_dir = layout.job_dir(job["id"])
        job_dir.mkdir(parents=True, exist_ok=True)
        place(source, job_dir / "input")
        services.queue.enqueue(job["id"])
    except BaseException as exc:
        services.store.delete_job(job["id"])
        layout.remove_tree(layout.job_dir(job["id"]))
        if isinstance(exc, QueueUnavailable):
            raise ApiError(503, "queue_unavailable", str(exc), headers={"Retry-After": "5"}) from None
        raise

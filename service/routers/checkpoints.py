"""POST /scenes/{id}/checkpoints: replace a scene's enhancer with an uploaded checkpoint;
GET /scenes/{id}/checkpoints/{version}: download a stored one (a fine-tuned one included).

The upload is validated by the library's ``load_checkpoint`` (safetensors only, header,
keys, shapes, finite weights, size) in a temporary file; only a checkpoint that loads is
renamed into ``checkpoints/vN.safetensors`` and made active. A refused upload leaves the
scene on its previous checkpoint and stores nothing.
"""

from __future__ import annotations

import logging
import os
from typing import Annotated

from fastapi import APIRouter, File, UploadFile
from fastapi.responses import FileResponse

from jobs.layout import fsync_dir
from roguenerf import RoGUENeRFError
from service.deps import scene_or_404, scene_public
from service.errors import ApiError, error_responses
from service.limits import checkpoint_error
from service.schemas import ScenePublic
from service.state import Services, ServicesDep
from service.storage import discard, save_upload

log = logging.getLogger("roguenerf.service")
router = APIRouter(prefix="/scenes", tags=["scenes"])


def _replace(services: Services, scene_id: str, upload: UploadFile) -> ScenePublic:
    from roguenerf import load_checkpoint

    settings, layout, store = services.settings, services.layout, services.store
    scene_or_404(services, scene_id)
    if store.active_job(scene_id) is not None:
        raise ApiError(409, "job_active",
                       f"scene {scene_id} has an active fine-tuning job; cancel it or wait before "
                       "replacing its checkpoint")
    tmp = layout.temp_dir()
    try:
        path = save_upload(upload.file, tmp / "upload.safetensors",
                           max_bytes=settings.max_checkpoint_bytes, what="checkpoint")
        try:
            load_checkpoint(path, max_bytes=settings.max_checkpoint_bytes)
        except RoGUENeRFError as exc:
            raise checkpoint_error(exc, path) from None
        version = store.allocate_version(scene_id)
        if version is None:
            raise ApiError(404, "not_found", f"scene {scene_id!r} not found")
        final = layout.checkpoint(scene_id, version)
        final.parent.mkdir(parents=True, exist_ok=True)
        os.replace(path, final)
        fsync_dir(final.parent)
    finally:
        discard(tmp)
    store.set_active_version(scene_id, version)
    log.info("scene %s: uploaded checkpoint is now v%d", scene_id, version)
    return scene_public(services, store.get_scene(scene_id))


CheckpointUpload = Annotated[UploadFile, File(description="enhancer checkpoint (.safetensors)")]


@router.post("/{scene_id}/checkpoints", status_code=201, response_model=ScenePublic,
             summary="Upload an enhancer checkpoint (.safetensors); it becomes the active version",
             responses=error_responses(400, 404, 409, 413, 422))
def create_checkpoint(scene_id: str, services: ServicesDep, checkpoint: CheckpointUpload) -> ScenePublic:
    return _replace(services, scene_id, checkpoint)


@router.get("/{scene_id}/checkpoints/{version}", response_class=FileResponse,
            summary="Download a stored checkpoint (.safetensors): a version number, or 'active'",
            responses={**error_responses(404, 422),
                       200: {"content": {"application/octet-stream": {}},
                             "description": "the checkpoint file, as load_checkpoint reads it"}})
def read_checkpoint(scene_id: str, version: str, services: ServicesDep) -> FileResponse:
    row = scene_or_404(services, scene_id)
    if version == "active":
        number = row["active_version"]
    elif version.isascii() and version.isdigit() and len(version) <= 9:
        number = int(version)
    else:
        raise ApiError(422, "validation_error", f"version: expected a number or 'active', got {version[:40]!r}")
    if number == 0:
        raise ApiError(404, "not_found", f"scene {scene_id} uses the server's default checkpoint (v0), "
                                         "which is not stored with the scene")
    path = services.layout.checkpoint(scene_id, number)
    if not path.is_file():
        raise ApiError(404, "not_found", f"scene {scene_id} has no checkpoint v{number} "
                                         f"(stored: {services.layout.versions(scene_id) or 'none'})")
    name = f"{(row.get('name') or scene_id)}-v{number}.safetensors"
    return FileResponse(path, media_type="application/octet-stream", filename=name)

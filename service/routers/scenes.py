"""Scenes: register (zipped scene folder, optional name), read, rename, delete, start fine-tuning."""

from __future__ import annotations

import logging
import unicodedata
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Annotated

from fastapi import APIRouter, File, Form, Header, Response, UploadFile

from jobs.layout import IMPORT_CHECKPOINT, IMPORT_DATASET, IMPORT_PLY, new_id, public_message
from jobs.queue import QueueUnavailable
from jobs.store import ActiveJobExists, IdempotencyMismatch, QueueFull, SceneBusy
from roguenerf import RoGUENeRFError
from service.deps import queue_with_input, scene_or_404, scene_public
from service.errors import ApiError, error_responses, library_error
from service.limits import checkpoint_error, queue_full
from service.pagination import CursorQuery, LimitQuery, decode_cursor, page
from service.schemas import JobCreate, JobPublic, ScenePage, ScenePublic, SceneUpdate
from service.state import Services, ServicesDep
from service.storage import ZipLimits, discard, extract_scene_zip, place, save_upload

log = logging.getLogger("roguenerf.service")
router = APIRouter(prefix="/scenes", tags=["scenes"])


MAX_NAME_CHARS = 120


def scene_name(given: str | None, filename: str | None) -> str | None:
    """The scene's name: ``given`` (the form field), else the uploaded zip's file name without
    its folder and ``.zip``; None when neither says anything. Whitespace runs become one space;
    control characters and more than :data:`MAX_NAME_CHARS` characters are refused (422)."""
    if given is None:
        if not filename:
            return None
        stem = PureWindowsPath(PurePosixPath(filename).name).name  # a browser may send C:\...\x.zip
        if stem.lower().endswith(".zip"):
            stem = stem[:-4]
        given = "".join(c for c in stem if unicodedata.category(c)[0] != "C")[:MAX_NAME_CHARS]
        return " ".join(unicodedata.normalize("NFC", given).split()) or None
    if any(unicodedata.category(c) in ("Cc", "Cf", "Cs", "Co", "Cn") for c in given.replace("\t", " ")):
        raise ApiError(422, "validation_error", "name: control or unassigned characters are not allowed")
    name = " ".join(unicodedata.normalize("NFC", given).split())
    if not name:
        raise ApiError(422, "validation_error", "name: must not be empty or only spaces (leave it out "
                                                "to use the zip's file name)")
    if len(name) > MAX_NAME_CHARS:
        raise ApiError(422, "validation_error", f"name: at most {MAX_NAME_CHARS} characters, got {len(name)}")
    return name


IMPORT_ADVICE = ("a scene also holds a radiance field's render and depth of every view. Send it with the "
                 "trained 3DGS point_cloud.ply to POST /scenes/import (on the page: the upload's \"3DGS .ply\" "
                 "field), or run `roguenerf import-3dgs DATASET --ply point_cloud.ply --output SCENE` (or "
                 "import-nerfstudio / import-gsplat with your field's renders) and upload SCENE zipped")
COLMAP_ZIP = f"archive: a COLMAP dataset (photos and poses), not a scene: {IMPORT_ADVICE}"
PHOTOS_ONLY_ZIP = (f"archive: photos and poses only (no view has a render or a depth), a dataset, not a scene: "
                   f"{IMPORT_ADVICE}")
"""The answers to a dataset sent to ``POST /scenes``."""


def _unwrapped(tmp: Path, root: Path, folder: Path) -> Path:
    """The extracted upload at ``folder``: ``root`` itself, or its single top-level folder moved
    there (``zip -r lego.zip lego/``)."""
    if root != folder:
        staging = tmp / "unwrapped"
        root.rename(staging)
        folder.rmdir()
        staging.rename(folder)
    return folder


def _register(services: Services, archive: UploadFile, checkpoint: UploadFile | None,
              name: str | None = None) -> ScenePublic:
    from roguenerf import load_checkpoint, load_scene

    settings, layout = services.settings, services.layout
    name = scene_name(name, archive.filename)
    scene_id = new_id()
    tmp = layout.temp_dir()
    try:
        root = extract_scene_zip(archive.file, tmp / "scene",
                                 ZipLimits(settings.max_scene_files, settings.max_scene_bytes))
        _unwrapped(tmp, root, tmp / "scene")
        from roguenerf import is_colmap_dataset

        if not (tmp / "scene" / "transforms.json").is_file() and is_colmap_dataset(tmp / "scene"):
            raise ApiError(422, "invalid_scene", COLMAP_ZIP)
        try:
            # confine: an uploaded transforms.json must not name files outside the upload.
            scene = load_scene(tmp / "scene", confine=True)
        except RoGUENeRFError as exc:
            raise library_error(exc, root=tmp / "scene") from None
        if all(f.render_path is None and f.depth_path is None for f in scene.frames):
            raise ApiError(422, "invalid_scene", PHOTOS_ONLY_ZIP)
        train = len(scene.indices("train"))
        if train == 0:
            raise ApiError(422, "invalid_scene", "scene has no 'train' views: neighbours come from them")
        from roguenerf import unusable_views

        warnings = [public_message(f"unusable view {v}", root=tmp / "scene", data_dir=settings.data_dir)
                    for v in unusable_views(scene)]
        version = 0
        if checkpoint is not None:
            (tmp / "checkpoints").mkdir()
            path = save_upload(checkpoint.file, tmp / "checkpoints" / "v1.safetensors",
                               max_bytes=settings.max_checkpoint_bytes, what="checkpoint")
            try:
                load_checkpoint(path, max_bytes=settings.max_checkpoint_bytes)
            except RoGUENeRFError as exc:
                raise checkpoint_error(exc, path) from None
            version = 1
        first = scene.frames[0]
        place(tmp, layout.scene_dir(scene_id))
    except BaseException:
        discard(tmp)
        raise
    try:
        row = services.store.create_scene(
            scene_id, views=len(scene.frames), train_views=train,
            test_views=len(scene.indices("test")), width=int(first.width), height=int(first.height),
            active_version=version, name=name,
        )
    except BaseException:
        layout.remove_tree(layout.scene_dir(scene_id))
        raise
    log.info("scene %s (%r) registered: %d views, checkpoint v%d", scene_id, name, len(scene.frames), version)
    for warning in warnings:
        log.warning("scene %s: %s", scene_id, warning)
    return scene_public(services, row, warnings=warnings)


@router.post("", status_code=201, response_model=ScenePublic, summary="Register a zipped scene folder",
             responses=error_responses(400, 413, 422))
def create_scene(
    services: ServicesDep,
    archive: Annotated[UploadFile, File(
        description="zip of a scene folder (transforms.json, images/, renders/, depths/)")],
    # Not `UploadFile | None`: that publishes a nullable schema, and a multipart "null" text
    # part is then schema-valid but refused. Omitting the part is how it is left out.
    checkpoint: Annotated[UploadFile, File(description="optional enhancer checkpoint (.safetensors)")] = None,
    name: Annotated[str, Form(max_length=1000, description=(
        f"optional label shown instead of the id (at most {MAX_NAME_CHARS} characters); "
        "default: the zip's file name without .zip"))] = None,
) -> ScenePublic:
    return _register(services, archive, checkpoint, name)


def _validate_import(services: Services, tmp: Path, archive: UploadFile, ply: UploadFile,
                     checkpoint: UploadFile | None, hold: int) -> int:
    """Store an import upload under ``tmp/input`` and check it with the library (the dataset's
    views and photos, the .ply, the checkpoint); returns the number of views."""
    from roguenerf import load_checkpoint, load_scene, read_dataset_views, read_ply

    settings = services.settings
    inputs = tmp / "input"
    dataset = _unwrapped(tmp, extract_scene_zip(archive.file, inputs / IMPORT_DATASET,
                                                ZipLimits(settings.max_scene_files, settings.max_scene_bytes)),
                         inputs / IMPORT_DATASET)
    ply_path = save_upload(ply.file, inputs / IMPORT_PLY, max_bytes=settings.max_scene_bytes, what="ply")
    try:
        read_ply(ply_path)
    except RoGUENeRFError as exc:
        raise ApiError(422, "invalid_input", "ply: " + str(exc).replace(f"{ply_path}: ", "")) from None
    try:
        if (dataset / "transforms.json").is_file():
            load_scene(dataset, confine=True)  # an uploaded transforms.json names files inside the upload only
        views, _format = read_dataset_views(dataset, hold=hold)
    except RoGUENeRFError as exc:
        raise library_error(exc, root=dataset) from None
    inside = dataset.resolve()
    for view in views:
        if not view.photo.resolve().is_relative_to(inside):
            raise ApiError(422, "invalid_archive", f"archive: view {view.name}'s photo lies outside the upload")
    if not any(view.split == "train" for view in views):
        raise ApiError(422, "invalid_input", f"hold: {hold} makes every one of the {len(views)} views a test view, "
                                             "and the scene has no 'train' views: neighbours come from them")
    if checkpoint is not None:
        path = save_upload(checkpoint.file, inputs / IMPORT_CHECKPOINT, max_bytes=settings.max_checkpoint_bytes,
                           what="checkpoint")
        try:
            load_checkpoint(path, max_bytes=settings.max_checkpoint_bytes)
        except RoGUENeRFError as exc:
            raise checkpoint_error(exc, path) from None
    return len(views)


@router.post("/import", status_code=202, response_model=JobPublic,
             summary="Import a 3DGS scene: its dataset (zip) and trained point_cloud.ply; returns a job",
             responses=error_responses(400, 413, 422, 503))
def import_scene(
    services: ServicesDep,
    response: Response,
    archive: Annotated[UploadFile, File(description=(
        "zip of the dataset the splats were trained on: COLMAP (images/ + sparse/0/) or a transforms.json "
        "with its photos"))],
    ply: Annotated[UploadFile, File(description="the trained 3DGS point_cloud.ply (Inria format)")],
    checkpoint: Annotated[UploadFile, File(description="optional enhancer checkpoint (.safetensors)")] = None,
    name: Annotated[str, Form(max_length=1000, description=(
        f"optional label of the new scene (at most {MAX_NAME_CHARS} characters); default: the zip's file name "
        "without .zip"))] = None,
    hold: Annotated[int, Form(ge=0, le=10_000, description=(
        "COLMAP datasets: every N-th view (name order) is a test view, as the 3DGS trainer's --eval; 0: none"))] = 8,
) -> JobPublic:
    """The worker renders every view from the splats (RGB, z-depth, opacity; the library's
    ``import_3dgs``, as ``roguenerf import-3dgs``) and registers the scene; the job's
    ``scene_id`` is the new scene's id, and its ``result`` says so once it succeeded."""
    settings, layout = services.settings, services.layout
    name = scene_name(name, archive.filename)
    scene_id = new_id()
    tmp = layout.temp_dir()
    try:
        views = _validate_import(services, tmp, archive, ply, checkpoint, hold)
        request = {"kind": "import", "name": name, "hold": hold, "views": views}
        try:
            job, _ = services.store.create_job(scene_id, request, max_queued=settings.max_queued_jobs)
        except QueueFull as exc:
            raise queue_full(exc) from None
        queue_with_input(services, job, tmp / "input")
    finally:
        discard(tmp)
    log.info("import job %s queued: scene %s (%r), %d views", job["id"], scene_id, name, views)
    response.headers["Location"] = f"/jobs/{job['id']}"
    return JobPublic.from_row(job)


@router.get("", response_model=ScenePage, summary="List scenes, newest first (paginated)",
            responses=error_responses(400, 422))
def list_scenes(services: ServicesDep, limit: LimitQuery = 50, cursor: CursorQuery = None) -> ScenePage:
    rows = services.store.list_scenes(limit=limit + 1, before=decode_cursor(cursor))
    rows, next_cursor = page(rows, limit)
    active = services.store.active_jobs([r["id"] for r in rows])
    return ScenePage(items=[scene_public(services, r, active_job=active.get(r["id"])) for r in rows],
                     next_cursor=next_cursor)


@router.get("/{scene_id}", response_model=ScenePublic, summary="Describe a scene",
            responses=error_responses(404))
def read_scene(scene_id: str, services: ServicesDep) -> ScenePublic:
    return scene_public(services, scene_or_404(services, scene_id))


@router.patch("/{scene_id}", response_model=ScenePublic, summary="Rename a scene",
              responses=error_responses(400, 404, 422))
def update_scene(scene_id: str, body: SceneUpdate, services: ServicesDep) -> ScenePublic:
    scene_or_404(services, scene_id)
    name = scene_name(body.name, None)
    if not services.store.rename_scene(scene_id, name):
        raise ApiError(404, "not_found", f"scene {scene_id!r} not found")
    return scene_public(services, services.store.get_scene(scene_id))


@router.delete("/{scene_id}", status_code=204,
               summary="Delete a scene, its checkpoints and its finished jobs (their videos too)",
               responses=error_responses(404, 409))
def delete_scene(scene_id: str, services: ServicesDep) -> Response:
    scene_or_404(services, scene_id)
    try:
        job_ids = services.store.delete_scene_and_jobs(scene_id)
    except SceneBusy as exc:
        raise ApiError(409, "scene_busy",
                       f"scene {scene_id} has an active job ({exc}); cancel it or wait for it first") from None
    if job_ids is None:
        raise ApiError(404, "not_found", f"scene {scene_id!r} not found")
    services.enhancers.evict(scene_id)
    services.layout.remove_tree(services.layout.scene_dir(scene_id))
    for job_id in job_ids:
        services.layout.remove_tree(services.layout.job_dir(job_id))
    log.info("scene %s deleted with %d finished jobs", scene_id, len(job_ids))
    return Response(status_code=204)


@router.post("/{scene_id}/finetune", status_code=202, response_model=JobPublic,
             summary="Start fine-tuning the scene's enhancer (returns a job)",
             responses=error_responses(400, 404, 409, 422, 503))
def create_finetune_job(
    scene_id: str,
    body: JobCreate,
    services: ServicesDep,
    response: Response,
    idempotency_key: Annotated[str | None, Header(max_length=200, description="same key, same job")] = None,
) -> JobPublic:
    settings = services.settings
    row = scene_or_404(services, scene_id)
    if body.steps is not None and body.steps > settings.max_job_steps:
        raise ApiError(422, "validation_error", f"steps: at most {settings.max_job_steps}, got {body.steps}")
    if body.minutes is not None and body.minutes > settings.max_job_minutes:
        raise ApiError(422, "validation_error",
                       f"minutes: at most {settings.max_job_minutes}, got {body.minutes}")
    request = body.model_dump(exclude_none=True)
    try:
        job, created = services.store.create_job(scene_id, request, idempotency_key=idempotency_key,
                                                 base_version=row["active_version"],
                                                 max_queued=settings.max_queued_jobs)
    except QueueFull as exc:
        raise queue_full(exc) from None
    except ActiveJobExists as exc:
        raise ApiError(409, "job_active",
                       f"scene {scene_id} already has an active fine-tuning job ({exc.job_id}); "
                       "wait for it or cancel it") from None
    except IdempotencyMismatch as exc:
        raise ApiError(409, "idempotency_conflict", str(exc)) from None
    if created:
        try:
            services.queue.enqueue(job["id"])
        except QueueUnavailable as exc:
            services.store.delete_job(job["id"])
            raise ApiError(503, "queue_unavailable", str(exc), headers={"Retry-After": "5"}) from None
    response.headers["Location"] = f"/jobs/{job['id']}"
    return JobPublic.from_row(job)

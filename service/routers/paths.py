"""Camera paths: upload a zip of frames + camera path, get a job; the MP4 comes from GET /jobs/{id}/result."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated, Literal

from fastapi import APIRouter, File, Form, Response, UploadFile

from jobs.store import ActiveJobExists, QueueFull
from roguenerf import RoGUENeRFError
from service.deps import queue_with_input, scene_or_404
from service.errors import ApiError, error_responses, library_error
from service.limits import queue_full
from service.schemas import JobPublic
from service.state import ServicesDep
from service.storage import ZipLimits, discard, extract_scene_zip

log = logging.getLogger("roguenerf.service")
CARRY_AGREEMENT = 0.0
"""The form's default ``carry_agreement``: the library's (``TemporalConfig.carry_agreement``,
written out so that importing the routes does not load torch; a test keeps them equal)."""
CARRY_SHARE = 0.0
"""The form's default ``carry_share``: the library's (``TemporalConfig.carry_share``), as
:data:`CARRY_AGREEMENT`."""
CARRY_NEARER = 0.0
"""The form's default ``carry_nearer``: the library's (``TemporalConfig.carry_nearer``), as
:data:`CARRY_AGREEMENT`."""
SCHEDULE = "fixed"
"""The form's default ``schedule``: the library's (``TemporalConfig.schedule``), as
:data:`CARRY_AGREEMENT`."""
BETWEEN_AGREEMENT = 0.0
"""The form's default ``between_agreement``: the library's (``TemporalConfig.between_agreement``),
as :data:`CARRY_AGREEMENT`."""

router = APIRouter(prefix="/scenes", tags=["paths"])
PATH_ARCHIVE = "the path archive"
"""What error messages call the uploaded path folder (never "the scene", nor a server path)."""


FORCE_ADVICE = "force=true (a form field of this upload)"
"""How a client goes on when the path does not fit the scene (the library names it in its message)."""


def validate_path_upload(services, row: dict, root: Path, *, max_pixels: int, depth_type: str = "z",
                         depth_scale: float = 1.0, background: str = "zero", force: bool = False) -> int:
    """Check an extracted path upload with the library, the checks ``enhance_path`` runs before
    its first frame included (``check_path``: depth type, cameras in the scene's world); returns
    its frame count (ApiError otherwise)."""
    from roguenerf import (
        DATAPARSER_FILE,
        DataparserTransform,
        check_path,
        find_camera_file,
        find_path_frames,
        read_camera_path,
        read_image_size,
    )

    scene_id = row["id"]
    try:
        camera_file = find_camera_file(root)
        parser_file = services.layout.scene_files(scene_id) / DATAPARSER_FILE
        parser = DataparserTransform.read(parser_file) if parser_file.is_file() else None
        camera_path = read_camera_path(camera_file, dataparser=parser)
        if camera_path.width * camera_path.height > max_pixels:
            raise ApiError(413, "image_too_large", f"camera path renders {camera_path.width}x{camera_path.height}, "
                                                   f"more than the allowed {max_pixels} pixels")
        pairs = find_path_frames(root, len(camera_path))
        for rgb, _depth in pairs:
            size = read_image_size(rgb, max_pixels=max_pixels)
            if size != (camera_path.width, camera_path.height):
                raise ApiError(422, "invalid_path", f"{rgb.relative_to(root)}: render is {size[0]}x{size[1]}, the "
                                                    f"camera path says {camera_path.width}x{camera_path.height}")
        enhancer = services.enhancers.get(scene_id, row["active_version"])  # the job's scene and neighbours
        check_path(enhancer.scene, camera_path, root, depth_type=depth_type, depth_scale=depth_scale,
                   background=background, neighbours=max(1, enhancer.num_neighbours or 1), force=force,
                   override=FORCE_ADVICE)
    except RoGUENeRFError as exc:
        raise library_error(exc, root=root, root_name=PATH_ARCHIVE) from None
    return len(pairs)


@router.post("/{scene_id}/paths", status_code=202, response_model=JobPublic,
             summary="Enhance a camera path (zip of frames + camera path); returns a job",
             responses=error_responses(400, 404, 409, 413, 422, 503))
def create_path_job(
    scene_id: str,
    services: ServicesDep,
    response: Response,
    archive: Annotated[UploadFile, File(description=(
        "zip: camera_path.json (nerfstudio) or transforms.json, plus rgb/NAME.png and depth/NAME.npy[.gz] "
        "per frame (or NAME.png + NAME.npy side by side)"))],
    depth_type: Annotated[Literal["z", "ray"], Form(description="z, or ray (distance along the ray)")] = "z",
    depth_scale: Annotated[float, Form(gt=0, lt=1e9, description="multiplies the stored depth")] = 1.0,
    background: Annotated[Literal["zero", "max"], Form(description="what no-surface pixels hold")] = "zero",
    quality: Annotated[int, Form(ge=0, le=51, description="x264 CRF (lower is better)")] = 20,
    model_every: Annotated[int, Form(ge=1, le=16, description=(
        "run the model on one frame in this many and carry its results into the frames between "
        "(faster, less flicker, less detail on the carried frames); 1: every frame"))] = 1,
    carry_between: Annotated[bool, Form(description=(
        "with model_every > 1, make the model frames first and carry each frame between two of them from both, "
        "mixed by how near each is; false: from the last model frame only"))] = True,
    carry_agreement: Annotated[float, Form(ge=0, le=200, description=(
        "with model_every > 1, carry a frame only where the model frames' renders, reprojected into it, "
        "match its render to this PSNR in dB (e.g. 28; 0, the default: wherever 95 % of it is seen)"))
    ] = CARRY_AGREEMENT,
    carry_share: Annotated[float, Form(ge=0, le=1000, description=(
        "with model_every > 1, carry a frame only where what the model frames' renders, reprojected into it, "
        "miss of its render is at most this share of the enhancer's change there (mean squares; 0: no such "
        "test)"))] = CARRY_SHARE,
    carry_nearer: Annotated[float, Form(ge=0, le=1000, description=(
        "with model_every > 1, carry a frame only where the model frames it is carried from are at most this "
        "many times as far from it as its nearest training photo (camera centres; 0: no such test)"))
    ] = CARRY_NEARER,
    schedule: Annotated[Literal["fixed", "gate"], Form(description=(
        "with model_every > 1 and carry_between, where the model frames go: fixed, every model_every-th frame; "
        "gate, as far apart as carry_nearer lets every frame between them be carried, at most model_every"))
    ] = SCHEDULE,
    between_agreement: Annotated[float, Form(ge=0, le=200, description=(
        "with model_every > 1 and carry_between, carry a frame only where the two model frames around it, "
        "reprojected into it, also agree with each other to this PSNR in dB (0: no such test)"))
    ] = BETWEEN_AGREEMENT,
    both_ways: Annotated[bool, Form(description=(
        "blend each frame with the frames after it too (a second pass from the last frame back: no lag); "
        "false: one pass, faster. The fast setting (enhance-path --fast): model_every=4, carry_nearer=1, "
        "both_ways=false"))] = True,
    force: Annotated[bool, Form(description=(
        "enhance the path even when its cameras do not fit the scene (far from its cameras or seeing none of its "
        "training photos: OpenGL vs OpenCV, another unit or world, z vs ray depth; a 422 otherwise)"))] = False,
) -> JobPublic:
    settings, layout = services.settings, services.layout
    row = scene_or_404(services, scene_id)
    if schedule == "gate" and not carry_between:
        raise ApiError(422, "validation_error", "schedule: places the model frames that frames are carried "
                                                "between: needs carry_between=true")
    tmp = layout.temp_dir()
    try:
        root = extract_scene_zip(archive.file, tmp / "input",
                                 ZipLimits(settings.max_scene_files, settings.max_scene_bytes))
        frames = validate_path_upload(services, row, root, max_pixels=settings.max_upload_pixels,
                                      depth_type=depth_type, depth_scale=depth_scale, background=background,
                                      force=force)
        request = {"kind": "path", "frames": frames, "depth_type": depth_type, "depth_scale": depth_scale,
                   "background": background, "quality": quality, "force": force, "model_every": model_every,
                   "carry_agreement": carry_agreement, "carry_share": carry_share, "carry_nearer": carry_nearer,
                   "carry_between": carry_between, "schedule": schedule,
                   "between_agreement": between_agreement, "both_ways": both_ways}
        try:
            job, _ = services.store.create_job(scene_id, request, base_version=row["active_version"],
                                               max_queued=settings.max_queued_jobs)
        except QueueFull as exc:
            raise queue_full(exc) from None
        except ActiveJobExists as exc:
            raise ApiError(409, "job_active", f"scene {scene_id} already has an active job ({exc.job_id}); "
                                              "wait for it or cancel it") from None
        queue_with_input(services, job, root)
    finally:
        discard(tmp)
    log.info("path job %s queued for scene %s: %d frames", job["id"], scene_id, frames)
    response.headers["Location"] = f"/jobs/{job['id']}"
    return JobPublic.from_row(job)

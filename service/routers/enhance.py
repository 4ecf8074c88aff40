"""POST /enhance: one render in, the enhanced PNG out."""

from __future__ import annotations

import json
import time
from typing import Annotated

from fastapi import APIRouter, File, Form, UploadFile
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import Response
from pydantic import ValidationError

from roguenerf import CameraMismatchError, InputError, RoGUENeRFError
from service.deps import scene_or_404
from service.errors import ApiError, error_responses, library_error
from service.limits import check_depth_coverage, decode_field
from service.schemas import Camera
from service.state import Services, ServicesDep

router = APIRouter(tags=["enhance"])

RETRY_AFTER_S = 1

RESPONSE_PNG = {"compress_level": 1, "strategy": "rle"}
"""How the answer is compressed: zlib's run-length strategy encodes a 504x378 enhanced render
about 4x faster than the library's default (level 6; ~25 instead of ~105 ms of CPU) at about
the same size (renders: within a few % either way). Same pixels whatever the setting; the
bytes differ from ``write_png``'s default ones. See bench/http_overhead.py."""


def parse_camera(text: str) -> Camera:
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ApiError(422, "validation_error", f"camera: not valid JSON ({exc})") from None
    try:
        return Camera.model_validate(data)
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in e['loc']) or 'camera'}: {e['msg']}" for e in exc.errors()[:5]
        )
        raise ApiError(422, "validation_error", f"camera: {problems}") from None


def camera_tensors(camera: Camera):
    """``(K (3, 3), world_from_cam (4, 4) or (3, 4) OpenCV)`` as float64, validated with
    messages that name the camera fields. The pose handed to the library is the converted,
    unchecked one, so the service computes exactly what a direct library call with these inputs
    computes (a 3x4 pose gets its last row there, in the one check, ``check_pose``)."""
    import torch

    from roguenerf import check_intrinsics, check_pose, intrinsics_matrix, opengl_to_opencv

    pose = torch.tensor(camera.transform_matrix, dtype=torch.float64)
    if camera.convention == "opengl":
        pose = opengl_to_opencv(pose)
    check_pose(pose.clone(), "camera.transform_matrix")
    try:
        K = intrinsics_matrix(camera.fl_x, camera.fl_y, camera.cx, camera.cy, dtype=torch.float64)
    except InputError as exc:  # the library calls it "K"; the client sent fl_x, fl_y, cx, cy
        raise InputError(f"camera (fl_x, fl_y, cx, cy): {exc}") from None
    check_intrinsics(K, "camera (fl_x, fl_y, cx, cy)")
    return K, pose


FORCE_ADVICE = "force=true (a form field of this request)"
"""How a client goes on when the camera does not fit the scene (the library names it in its message)."""


def camera_fix(exc: CameraMismatchError, camera: Camera, scene_id: str) -> str:
    """The fix of a camera that does not fit the scene, in the request's own fields."""
    if exc.cause == "convention":
        other = "opengl" if camera.convention == "opencv" else "opencv"
        return f'send "convention": "{other}" in camera (it said "{camera.convention}")'
    if exc.cause == "scale":
        return "send the pose (and depth) in the scene's units, those of GET /scenes/{id}/views"
    return ("send a pose in the scene's world: GET /scenes/{id}/views lists its views' cameras in this form "
            f"(scene {scene_id})")


def _enhance(services: Services, scene: dict, render_bytes: bytes, depth_bytes: bytes,
             camera: Camera, depth_scale: float, force: bool = False) -> tuple[bytes, object, int, str | None]:
    from roguenerf import encode_png, ray_to_z_depth, read_depth, read_image

    limit = services.settings.max_upload_pixels
    try:
        render = decode_field("render", read_image, render_bytes, max_pixels=limit)
        depth = decode_field("depth", read_depth, depth_bytes, scale=depth_scale, max_pixels=limit)
        height, width = render.shape[1:]
        if tuple(depth.shape[1:]) != (height, width):
            raise ApiError(422, "invalid_input",
                           f"depth: expected {height}x{width} (H x W) like the render, got "
                           f"{depth.shape[1]}x{depth.shape[2]}")
        if camera.w is not None and camera.w != width or camera.h is not None and camera.h != height:
            raise ApiError(422, "invalid_input",
                           f"camera: w x h = {camera.w}x{camera.h} but the render is {width}x{height}")
        K, world_from_cam = camera_tensors(camera)
        check_depth_coverage(depth)
        if camera.depth_type == "ray":
            depth = ray_to_z_depth(depth[0], K)[None].to(depth.dtype)
        version = scene["active_version"]
        enhancer = services.enhancers.get(scene["id"], version)
        warning = None
        if enhancer.use_neighbours and enhancer.num_neighbours:
            # The test enhance-path runs on its cameras: a pose in the wrong convention, unit or
            # world sees none of the neighbours, and its "enhanced" image is worse than the render.
            from roguenerf import check_camera

            try:
                warning = check_camera(enhancer.scene, depth, K, world_from_cam, neighbours=enhancer.num_neighbours,
                                       force=force, override=FORCE_ADVICE)
            except CameraMismatchError as exc:
                raise ApiError(422, library_error(exc).code,
                               f"{exc.problem}. Fix: {camera_fix(exc, camera, scene['id'])}; to enhance it "
                               f"anyway: {FORCE_ADVICE}") from None
        result = enhancer.enhance(render, depth, K, world_from_cam)
        return encode_png(result.image, **RESPONSE_PNG), result, version, warning
    except RoGUENeRFError as exc:
        raise library_error(exc) from None


@router.post(
    "/enhance",
    summary="Enhance one render of a registered scene",
    response_class=Response,
    responses={
        200: {"content": {"image/png": {}},
              "description": "the enhanced image, same size as the render; X-Enhance-Seconds, "
                             "X-Neighbours, X-Checkpoint-Version and (when relevant) X-Enhance-Note headers"},
        **error_responses(400, 404, 409, 413, 422, 500, 503),
    },
)
async def create_enhancement(
    services: ServicesDep,
    scene_id: Annotated[str, Form(min_length=1, description="id returned by POST /scenes")],
    render: Annotated[UploadFile, File(description="the radiance field's render (PNG)")],
    depth: Annotated[UploadFile, File(description=".npy float32 HxW, or 16-bit PNG with depth_scale")],
    camera: Annotated[str, Form(
        min_length=1, description="JSON: transform_matrix, convention, fl_x, fl_y, cx, cy, depth_type")],
    depth_scale: Annotated[float, Form(gt=0, description="multiplier for 16-bit PNG depth (e.g. 0.001 for mm)")] = 1.0,
    force: Annotated[bool, Form(description=(
        "enhance even when the camera does not fit the scene (its pixels land nowhere near the training photos' "
        "surfaces: wrong convention, unit or world; a 422 otherwise); the problem comes back in X-Enhance-Note"))
    ] = False,
) -> Response:
    start = time.perf_counter()
    slots = services.enhance_slots
    # Refuse before any thread-pool hop: under load the pool's threads compete with the running
    # enhancements, and a refusal must come back at once.
    if slots.locked():
        raise ApiError(503, "over_capacity",
                       f"all {services.settings.enhance_concurrency} enhancement slots are busy; retry shortly",
                       headers={"Retry-After": str(RETRY_AFTER_S)})
    scene = await run_in_threadpool(scene_or_404, services, scene_id)
    cam = parse_camera(camera)
    async with slots:
        render_bytes = await render.read()
        depth_bytes = await depth.read()
        png, result, version, warning = await run_in_threadpool(
            _enhance, services, scene, render_bytes, depth_bytes, cam, depth_scale, force)
    headers = {
        "X-Enhance-Seconds": f"{result.seconds:.4f}",
        "X-Total-Seconds": f"{time.perf_counter() - start:.4f}",
        "X-Neighbours": ",".join(result.neighbours),
        # the neighbours whose pose was refined against this render (roguenerf.enhance.align)
        "X-Pose-Refined": ",".join(n for n, done in zip(result.neighbours, result.aligned or []) if done),
        "X-Checkpoint-Version": str(version),
    }
    if result.colour_offset is not None:  # the RGB offset matching the neighbours' colour (roguenerf.enhance.colour)
        headers["X-Colour-Offset"] = ",".join(f"{x:.6f}" for x in result.colour_offset)
    if result.trust is not None:  # share of the enhancer's change kept (roguenerf.enhance.trust)
        headers["X-Trust"] = f"{result.trust:.4f}"
        headers["X-Neighbour-Agreement"] = f"{result.agreement:.4f}"
    note = "; ".join(n for n in (f"forced: {warning}" if warning and force else warning, result.note) if n)
    if note:
        headers["X-Enhance-Note"] = note.encode("ascii", "replace").decode()
    return Response(content=png, media_type="image/png", headers=headers)

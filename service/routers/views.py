"""A registered scene's views: cameras, render / photo / depth files, scores against the photo.

What a client (the web page included) needs to send a scene's own view to ``POST /enhance``
and to judge the answer: ``GET /scenes/{id}/views`` gives each view's camera in the form
``/enhance`` takes; ``.../render`` and ``.../depth`` are the other two fields; ``.../photo``
is the ground truth; ``POST .../score`` compares any image with the photo using the
library's ``psnr``, ``ssim`` and ``flip``. Everything is read with the library's ``load_scene``.
"""

from __future__ import annotations

import io
from typing import Annotated, Literal

from fastapi import APIRouter, File, Query, UploadFile
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import Response

from roguenerf import RoGUENeRFError
from service.deps import scene_or_404
from service.errors import ApiError, error_responses, library_error
from service.limits import decode_field
from service.schemas import ImageScore, ViewCamera, ViewList, ViewPublic
from service.state import Services, ServicesDep

router = APIRouter(prefix="/scenes", tags=["views"])

PNG = {"compress_level": 1, "strategy": "rle"}
"""Fast PNG encoding (same pixels as any other setting; see routers/enhance.py)."""

_WHAT = {"photo": "photo", "render": "radiance-field render", "depth": "depth map"}


def _scene(services: Services, scene_id: str):
    from roguenerf import load_scene

    scene_or_404(services, scene_id)
    try:
        return load_scene(services.layout.scene_files(scene_id))
    except RoGUENeRFError as exc:  # validated at registration; only a damaged data dir gets here
        raise library_error(exc) from None


def _frame(scene, scene_id: str, index: int, kind: str | None = None):
    if not 0 <= index < len(scene.frames):
        raise ApiError(404, "not_found", f"scene {scene_id} has no view {index} (views 0 to {len(scene.frames) - 1})")
    frame = scene.frames[index]
    path = {"photo": frame.image_path, "render": frame.render_path, "depth": frame.depth_path}.get(kind)
    if kind is not None and path is None:
        raise ApiError(404, "not_found", f"view {index} ({frame.name}) of scene {scene_id} has no {_WHAT[kind]}")
    return frame


def view_public(index: int, frame) -> ViewPublic:
    import torch

    from roguenerf import opencv_to_opengl

    pose = opencv_to_opengl(frame.world_from_cam.to(torch.float64))
    K = frame.K
    return ViewPublic(
        index=index, name=frame.name, split=frame.split, width=int(frame.width), height=int(frame.height),
        has_photo=frame.image_path is not None, has_render=frame.render_path is not None,
        has_depth=frame.depth_path is not None,
        camera=ViewCamera(transform_matrix=pose.tolist(), convention="opengl",
                          fl_x=float(K[0, 0]), fl_y=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]),
                          depth_type="z", w=int(frame.width), h=int(frame.height)),
    )


def _list(services: Services, scene_id: str, split: str | None) -> ViewList:
    scene = _scene(services, scene_id)
    return ViewList(items=[view_public(i, f) for i, f in enumerate(scene.frames)
                           if split is None or f.split == split])


@router.get("/{scene_id}/views", response_model=ViewList,
            summary="A scene's views: name, split, size, and the camera in the form POST /enhance takes",
            responses=error_responses(404, 422))
def list_views(
    scene_id: str,
    services: ServicesDep,
    split: Annotated[Literal["train", "test"] | None, Query(description="only this split")] = None,
) -> ViewList:
    return _list(services, scene_id, split)


def _file(services: Services, scene_id: str, index: int, kind: str) -> Response:
    from roguenerf import encode_png

    scene = _scene(services, scene_id)
    _frame(scene, scene_id, index, kind)
    try:
        if kind == "depth":
            import numpy as np

            buf = io.BytesIO()
            np.save(buf, scene.depth(index)[0].numpy().astype(np.float32), allow_pickle=False)
            return Response(buf.getvalue(), media_type="application/octet-stream",
                            headers={"Content-Disposition": f'attachment; filename="depth-{index}.npy"'})
        image = scene.photo(index) if kind == "photo" else scene.render(index)
        return Response(encode_png(image, **PNG), media_type="image/png")
    except RoGUENeRFError as exc:
        raise library_error(exc) from None


_PNG_RESPONSE = {200: {"content": {"image/png": {}}}, **error_responses(404, 422)}


@router.get("/{scene_id}/views/{index}/render", response_class=Response, responses=_PNG_RESPONSE,
            summary="The view's radiance-field render (PNG): the `render` field of POST /enhance")
def read_render(scene_id: str, index: int, services: ServicesDep) -> Response:
    return _file(services, scene_id, index, "render")


@router.get("/{scene_id}/views/{index}/photo", response_class=Response, responses=_PNG_RESPONSE,
            summary="The view's photo (PNG), the ground truth")
def read_photo(scene_id: str, index: int, services: ServicesDep) -> Response:
    return _file(services, scene_id, index, "photo")


@router.get("/{scene_id}/views/{index}/depth", response_class=Response,
            responses={200: {"content": {"application/octet-stream": {}}}, **error_responses(404, 422)},
            summary="The view's z-depth (.npy float32 HxW): the `depth` field of POST /enhance")
def read_depth(scene_id: str, index: int, services: ServicesDep) -> Response:
    return _file(services, scene_id, index, "depth")


def _score(services: Services, scene_id: str, index: int, data: bytes) -> ImageScore:
    import math

    from roguenerf import flip, psnr, read_image, ssim

    scene = _scene(services, scene_id)
    frame = _frame(scene, scene_id, index, "photo")
    image = decode_field("image", read_image, data, max_pixels=services.settings.max_upload_pixels)
    if tuple(image.shape[1:]) != (frame.height, frame.width):
        raise ApiError(422, "invalid_input",
                       f"image: expected {frame.width}x{frame.height} (W x H) like view {index}, "
                       f"got {image.shape[2]}x{image.shape[1]}")
    try:
        photo = scene.photo(index)
        p = float(psnr(image[None], photo[None])[0])
        s = float(ssim(image[None], photo[None])[0])
        f = float(flip(image[None], photo[None])[0])
    except RoGUENeRFError as exc:
        raise library_error(exc) from None
    return ImageScore(psnr=p if math.isfinite(p) else None, ssim=s, flip=f)


@router.post("/{scene_id}/views/{index}/score", response_model=ImageScore,
             summary="PSNR and SSIM of an image (PNG/JPEG of the view's size) against the view's photo",
             responses=error_responses(400, 404, 413, 422))
async def score_image(
    scene_id: str,
    index: int,
    services: ServicesDep,
    image: Annotated[UploadFile, File(description="PNG or JPEG, the view's size (e.g. an /enhance answer)")],
) -> ImageScore:
    data = await image.read()
    return await run_in_threadpool(_score, services, scene_id, index, data)

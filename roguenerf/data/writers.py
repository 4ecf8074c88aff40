"""Write the scene-folder format of ``../shared/data/lego`` (read back by :func:`load_scene`).

Layout: ``images/NAME.png`` (photos), ``renders/NAME.png``, ``depths/NAME.npy`` (float32 z),
optional ``acc/NAME.png``, and ``transforms.json`` with OpenGL ``transform_matrix`` poses.
Every file is written atomically (temporary file, fsync, rename); ``transforms.json`` is
written last, so a folder with a ``transforms.json`` is complete.
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from roguenerf.errors import InputError
from roguenerf.geometry.cameras import check_intrinsics, check_pose, opencv_to_opengl
from roguenerf.imageio import atomic_write, encode_npy, encode_png
from roguenerf.images import float_image_error

_SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]*$")


def write_scene_folder(
    root: str | Path,
    *,
    names: Sequence[str],
    photos: Tensor,
    renders: Tensor | None,
    depths: Tensor | None,
    world_from_cam: Tensor,
    K: Tensor,
    splits: Sequence[str],
    acc: Tensor | None = None,
) -> Path:
    """Write a scene folder.

    Args:
        root: output folder (created).
        names: M unique view names (letters, digits, ``_ . -``); used as file stems.
        photos: ``(M, 3, H, W)`` float in [0, 1] (stored as 8-bit PNG).
        renders: ``(M, 3, H, W)`` float in [0, 1], or None (photos-only scene).
        depths: ``(M, 1, H, W)`` z-depth in pose units (stored as float32 ``.npy``), or None.
        world_from_cam: ``(M, 4, 4)`` OpenCV camera-to-world (stored as OpenGL).
        K: ``(M, 3, 3)`` or ``(3, 3)`` pixel-centre intrinsics.
        splits: M values, "train" or "test".
        acc: optional ``(M, 1, H, W)`` accumulated opacity in [0, 1] (``acc/NAME.png``).
    Returns:
        ``root``.
    """
    root = Path(root)
    names = list(names)
    splits = list(splits)
    m = len(names)
    if m == 0:
        raise InputError("names: expected at least one view, got none")
    for name in names:
        if not isinstance(name, str) or not _SAFE_NAME.match(name):
            raise InputError(f"names: {name!r} is not a safe file stem (letters, digits, '_', '.', '-')")
    if len(set(names)) != m:
        raise InputError("names: expected unique view names, got duplicates")
    if len(splits) != m or any(s not in ("train", "test") for s in splits):
        raise InputError(f"splits: expected {m} values of 'train'/'test', got {splits[:5]}...")
    height, width = _check_images("photos", photos, m, 3)
    if renders is not None:
        _check_images("renders", renders, m, 3, (height, width))
    if depths is not None:
        _check_images("depths", depths, m, 1, (height, width))
    if acc is not None:
        _check_images("acc", acc, m, 1, (height, width))
    world_from_cam = torch.as_tensor(world_from_cam, dtype=torch.float64)
    if world_from_cam.shape != (m, 4, 4):
        raise InputError(f"world_from_cam: expected shape ({m}, 4, 4), got {tuple(world_from_cam.shape)}")
    world_from_cam = check_pose(world_from_cam, "world_from_cam")
    K = torch.as_tensor(K, dtype=torch.float64)
    shared = K.shape == (3, 3)
    if not shared and K.shape != (m, 3, 3):
        raise InputError(f"K: expected shape (3, 3) or ({m}, 3, 3), got {tuple(K.shape)}")
    check_intrinsics(K, "K")
    if (K[..., 0, 1] != 0).any():
        raise InputError("K: skew must be 0 (transforms.json has no skew entry)")

    gl = opencv_to_opengl(world_from_cam)
    frames = []
    for i, name in enumerate(names):
        frame = {"file_path": f"images/{name}.png"}
        atomic_write(root / frame["file_path"], encode_png(photos[i], name=f"photos[{i}]"), make_parents=True)
        if renders is not None:
            frame["render_path"] = f"renders/{name}.png"
            atomic_write(root / frame["render_path"], encode_png(renders[i], name=f"renders[{i}]"), make_parents=True)
        if depths is not None:
            frame["depth_path"] = f"depths/{name}.npy"
            depth = depths[i, 0].detach().cpu().numpy().astype(np.float32)
            atomic_write(root / frame["depth_path"], encode_npy(depth), make_parents=True)
        if acc is not None:
            frame["acc_path"] = f"acc/{name}.png"
            atomic_write(root / frame["acc_path"], encode_png(acc[i], name=f"acc[{i}]"), make_parents=True)
        if not shared:
            frame.update(camera_fields(K[i], width, height))
        frame["transform_matrix"] = gl[i].tolist()
        frame["split"] = splits[i]
        frames.append(frame)
    transforms = {"camera_model": "OPENCV"}
    if shared:
        transforms.update(camera_fields(K, width, height))
    transforms.update({**CONVENTIONS, "frames": frames})
    atomic_write(root / "transforms.json", json.dumps(transforms, indent=1).encode("utf-8"), make_parents=True)
    return root


CONVENTIONS = {
    "depth_definition": "z-depth along the camera's viewing axis, pose units, float32 .npy, HxW",
    "pixel_convention": "pixel (row v, col u) centre is at image coordinates (u+0.5, v+0.5)",
}
"""What a scene folder's ``transforms.json`` states about its depths and pixel centres."""


def camera_fields(K: Tensor, width: int, height: int) -> dict:
    """A frame's (or the file's) intrinsics as ``transforms.json`` holds them."""
    return {
        "fl_x": float(K[0, 0]),
        "fl_y": float(K[1, 1]),
        "cx": float(K[0, 2]),
        "cy": float(K[1, 2]),
        "w": width,
        "h": height,
    }


def _check_images(name: str, x: Tensor, m: int, channels: int, size: tuple[int, int] | None = None):
    if not isinstance(x, Tensor):
        raise InputError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    if x.ndim != 4 or x.shape[0] != m or x.shape[1] != channels or (size is not None and tuple(x.shape[2:]) != size):
        want = f"({m}, {channels}, {size[0]}, {size[1]})" if size else f"({m}, {channels}, H, W)"
        raise InputError(f"{name}: expected shape {want}, got {tuple(x.shape)}")
    if not x.is_floating_point():
        if name != "depths":  # photos, renders, acc: images in [0, 1] (roguenerf.images)
            raise float_image_error(name, x.dtype)
        raise InputError(f"{name}: expected a float tensor, got {x.dtype}")
    return int(x.shape[2]), int(x.shape[3])

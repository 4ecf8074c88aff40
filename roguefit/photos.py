"""Read a posed photo set: ``transforms.json`` (nerfstudio style) with photos, poses, near/far.

The format of ``../shared/data/real/*``: ``w, h, fl_x, fl_y, cx, cy`` (a frame may carry its
own), ``frames[i].file_path``, ``frames[i].transform_matrix`` (OpenGL camera-to-world) and
optional ``frames[i].near`` / ``far`` depth bounds. A scene folder of ours (with renders) is
read the same way; its renders and depths are ignored.

Views are split as the paper does: every ``hold``-th view (0, hold, 2 hold, ...) is held out.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import torch
from torch import Tensor

from roguenerf.errors import InputError
from roguenerf.geometry.cameras import check_pose, opengl_to_opencv
from roguenerf.imageio import read_image


@dataclasses.dataclass
class PhotoSet:
    """A posed photo set in memory.

    names: M view names (file stems); photos ``(M, 3, H, W)`` float32 in [0, 1];
    K ``(M, 3, 3)`` float64 pixel-centre intrinsics; world_from_cam ``(M, 4, 4)`` float64 OpenCV;
    near, far ``(M,)`` float64 depth bounds; splits: "train" / "test" per view;
    bounds_note: how near/far were obtained.
    """

    root: Path
    names: list[str]
    photos: Tensor
    K: Tensor
    world_from_cam: Tensor
    near: Tensor
    far: Tensor
    splits: list[str]
    bounds_note: str

    def indices(self, split: str) -> list[int]:
        return [i for i, s in enumerate(self.splits) if s == split]

    @property
    def height(self) -> int:
        return int(self.photos.shape[2])

    @property
    def width(self) -> int:
        return int(self.photos.shape[3])


def _number(value, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(f"{where}: expected a finite number, got {value!r}")
    return float(value)


def read_photo_set(root: str | Path, *, hold: int = 8) -> PhotoSet:
    """Read ``root/transforms.json`` and its photos; every ``hold``-th view is the test split.

    Raises InputError with the offending file or key (relative to ``root``) for anything that
    cannot be read: a missing file, a photo of another size, a bad pose, bounds with far <= near.
    """
    root = Path(root)
    path = root / "transforms.json"
    if not path.is_file():
        raise InputError(f"{root}: expected a posed photo set with transforms.json, found none")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"transforms.json: cannot be read as JSON ({exc})") from None
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list) or not data["frames"]:
        raise InputError("transforms.json: expected an object with a non-empty 'frames' list")
    if hold < 2:
        raise InputError(f"hold: expected >= 2 (every hold-th view is held out), got {hold}")
    frames = sorted(data["frames"], key=lambda f: str(f.get("file_path", "")) if isinstance(f, dict) else "")
    names, photos, Ks, poses, nears, fars = [], [], [], [], [], []
    size = None
    for i, frame in enumerate(frames):
        where = f"transforms.json frames[{i}]"
        if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
            raise InputError(f"{where}: expected an object with a 'file_path' string")
        rel = frame["file_path"]
        file = (root / rel).resolve()
        if not file.is_relative_to(root.resolve()):
            raise InputError(f"{where}: file_path {rel!r} points outside the photo set")
        if not file.is_file():
            raise InputError(f"{rel}: missing file")
        try:
            photo = read_image(file)
        except InputError as exc:
            raise InputError(f"{rel}: {str(exc).replace(str(file), '').strip(': ')}") from None
        h, w = int(photo.shape[1]), int(photo.shape[2])
        if size is None:
            size = (h, w)
        elif (h, w) != size:
            raise InputError(f"{rel}: expected {size[1]}x{size[0]} like the first photo, got {w}x{h}")
        cam = {k: frame.get(k, data.get(k)) for k in ("fl_x", "fl_y", "cx", "cy")}
        if any(v is None for v in cam.values()):
            raise InputError(f"{where}: intrinsics fl_x, fl_y, cx, cy missing (top level or per frame)")
        fx, fy = _number(cam["fl_x"], f"{where} fl_x"), _number(cam["fl_y"], f"{where} fl_y")
        cx, cy = _number(cam["cx"], f"{where} cx"), _number(cam["cy"], f"{where} cy")
        json_w, json_h = data.get("w", w), data.get("h", h)
        if (json_w, json_h) != (w, h):
            raise InputError(f"{rel}: transforms.json says {json_w}x{json_h}, the photo is {w}x{h}")
        if fx <= 0 or fy <= 0:
            raise InputError(f"{where}: focal lengths must be > 0, got {fx}, {fy}")
        matrix = frame.get("transform_matrix")
        try:
            pose = torch.tensor(matrix, dtype=torch.float64)
        except (TypeError, ValueError):
            raise InputError(f"{where}: transform_matrix is not a 4x4 list of numbers") from None
        if pose.shape != (4, 4) or not torch.isfinite(pose).all():
            raise InputError(f"{where}: transform_matrix is not a finite 4x4 matrix")
        pose = check_pose(opengl_to_opencv(pose), f"{where} transform_matrix")
        near, far = frame.get("near"), frame.get("far")
        if (near is None) != (far is None):
            raise InputError(f"{where}: give both 'near' and 'far' or neither")
        if near is not None:
            near, far = _number(near, f"{where} near"), _number(far, f"{where} far")
            if not 0 < near < far:
                raise InputError(f"{where}: expected 0 < near < far, got near={near}, far={far}")
        names.append(Path(rel).stem)
        photos.append(photo)
        Ks.append(torch.tensor([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=torch.float64))
        poses.append(pose)
        nears.append(near)
        fars.append(far)
    if len(set(names)) != len(names):
        raise InputError("transforms.json: two frames share a file stem; view names must be unique")
    if len(names) < 3:
        raise InputError(f"transforms.json: expected at least 3 views to fit a radiance field, got {len(names)}")
    world_from_cam = torch.stack(poses)
    if all(n is None for n in nears):
        near_t, far_t, note = _bounds_from_cameras(world_from_cam)
    elif any(n is None for n in nears):
        raise InputError("transforms.json: some frames have near/far bounds and some do not")
    else:
        near_t = torch.tensor(nears, dtype=torch.float64)
        far_t = torch.tensor(fars, dtype=torch.float64)
        note = "near/far from transforms.json"
    splits = ["test" if i % hold == 0 else "train" for i in range(len(names))]
    return PhotoSet(root=root, names=names, photos=torch.stack(photos), K=torch.stack(Ks),
                    world_from_cam=world_from_cam, near=near_t, far=far_t, splits=splits, bounds_note=note)


def look_at_point(world_from_cam: Tensor) -> Tensor:
    """The point closest (least squares) to every camera's optical axis ``(3,)`` float64."""
    origins = world_from_cam[:, :3, 3]
    axes = world_from_cam[:, :3, 2]
    axes = axes / axes.norm(dim=-1, keepdim=True)
    eye = torch.eye(3, dtype=torch.float64)
    proj = eye - axes[:, :, None] * axes[:, None, :]
    A = proj.sum(0)
    b = (proj @ origins[:, :, None]).sum(0)[:, 0]
    if torch.linalg.cond(A) > 1e8:  # all axes parallel: no common point
        return origins.mean(0) + axes.mean(0) * (origins - origins.mean(0)).norm(dim=-1).max().clamp_min(1.0)
    return torch.linalg.solve(A, b)


def _bounds_from_cameras(world_from_cam: Tensor) -> tuple[Tensor, Tensor, str]:
    centre = look_at_point(world_from_cam)
    dist = (world_from_cam[:, :3, 3] - centre).norm(dim=-1).clamp_min(1e-6)
    return 0.2 * dist, 5.0 * dist, "near/far estimated as 0.2x and 5x each camera's distance to the look-at point"

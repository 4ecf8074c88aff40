"""Enhance novel renders of one registered scene, with the training photos' features cached.

Dimension legend: N neighbours, F feature channels, H x W image size.

conv_H of a training photo does not depend on the novel view (paper section 3.3), so a
:class:`SceneEnhancer` encodes each training photo the first time it is chosen as a neighbour
and keeps the features; every later request reuses them. The cache is filled under a lock so
that concurrent ``enhance`` calls (the service runs several in a thread pool) never encode the
same photo twice or see a half-filled cache.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from roguenerf.errors import InputError, NonFiniteOutputError

DEFAULT_TILE = 512
"""Images whose height or width exceed this are enhanced tile by tile (bounded memory)."""

NO_NEIGHBOUR_NOTE = "no neighbour sees this view: enhanced without neighbours"


@dataclass
class EnhanceResult:
    image: Tensor
    """``(3, H, W)`` float32 in [0, 1], on the CPU."""
    neighbours: list[str]
    """Names of the training views whose photos were used (nearest first); empty when none."""
    seconds: float
    """Wall-clock time of this call (neighbour encoding included when it happened)."""
    note: str | None = None
    """Why the result differs from the usual path, e.g. no neighbour sees the view."""


def _check_image(x: Tensor, name: str, channels: int) -> Tensor:
    if not isinstance(x, Tensor):
        raise InputError(f"{name}: expected a torch.Tensor ({channels}, H, W), got {type(x).__name__}")
    if x.ndim != 3 or x.shape[0] != channels:
        raise InputError(f"{name}: expected shape ({channels}, H, W), got {tuple(x.shape)}")
    if x.shape[1] < 1 or x.shape[2] < 1:
        raise InputError(f"{name}: expected a non-empty image, got {tuple(x.shape)}")
    return x


def _resolve_exclude(scene, train: list[int], exclude) -> list[int]:
    """Map ``exclude`` (scene indices or view names) to positions in the training list."""
    if exclude is None:
        return []
    items = [exclude] if isinstance(exclude, (int, str)) else list(exclude)
    position = {scene_index: pos for pos, scene_index in enumerate(train)}
    out = []
    for item in items:
        index = scene.index(item) if isinstance(item, str) else int(item)
        if index in position:
            out.append(position[index])
    return out


class SceneEnhancer:
    """An enhancer bound to one scene: neighbour selection, cached conv_H features, tiling.

    Args:
        scene: a :class:`~roguenerf.data.scene.Scene`; its ``train`` views are the neighbours.
        model: an :class:`~roguenerf.models.enhancer.Enhancer` (put in eval mode and moved to
            ``device`` here; do not train it while this object is in use).
        num_neighbours: neighbours per request; default ``model.config.num_neighbours``.
        tile: images larger than this (height or width) are enhanced with
            :func:`~roguenerf.models.tiling.enhance_tiled`; default :data:`DEFAULT_TILE`.
        device: where the model runs.
    """

    def __init__(self, scene, model, *, num_neighbours: int | None = None, tile: int | None = None,
                 device: str | torch.device = "cpu"):
        if num_neighbours is not None and int(num_neighbours) < 0:
            raise InputError(f"num_neighbours: expected >= 0, got {num_neighbours}")
        if tile is not None and int(tile) < 16:
            raise InputError(f"tile: expected >= 16 pixels, got {tile}")
        self.scene = scene
        self.device = torch.device(device)
        self.model = model.to(self.device).eval()
        config = getattr(model, "config", None)
        default_n = getattr(config, "num_neighbours", 5) if config is not None else 5
        self.use_neighbours = bool(getattr(config, "use_neighbours", True)) if config is not None else True
        self.num_neighbours = int(default_n if num_neighbours is None else num_neighbours)
        self.tile = int(DEFAULT_TILE if tile is None else tile)
        self.train = list(scene.indices("train"))
        self.train_names = [scene.frames[i].name for i in self.train]
        poses = scene.poses()
        intrinsics = scene.intrinsics()
        if self.train:
            self.train_poses = poses[self.train].to(torch.float32)
            self.train_K = intrinsics[self.train].to(torch.float32)
        else:
            self.train_poses = torch.zeros(0, 4, 4)
            self.train_K = torch.zeros(0, 3, 3)
        self._features: dict[int, Tensor] = {}
        self._depths: dict[int, Tensor] = {}
        self._lock = threading.Lock()

    def _neighbour_data(self, positions: list[int]) -> tuple[Tensor, Tensor]:
        """Features ``(N, F, Hs, Ws)`` and depths ``(N, 1, Hs, Ws)`` of training positions, cached."""
        with self._lock:
            missing = [p for p in positions if p not in self._features]
            if missing:
                photos = torch.stack([self.scene.photo(self.train[p]) for p in missing]).to(self.device)
                with torch.inference_mode():
                    feats = self.model.encode_neighbours(photos.float())
                for p, f in zip(missing, feats):
                    self._features[p] = f
                    self._depths[p] = self.scene.depth(self.train[p]).to(self.device, torch.float32)
            features = torch.stack([self._features[p] for p in positions])
            depths = torch.stack([self._depths[p] for p in positions])
        return features, depths

    def cached_views(self) -> int:
        """How many training photos have been encoded so far."""
        with self._lock:
            return len(self._features)

    def select(self, world_from_cam: Tensor, *, exclude=None) -> list[int]:
        """Scene indices of the neighbours of a pose (nearest first), per the paper's rule."""
        from roguenerf.geometry import select_neighbours

        if not self.use_neighbours or self.num_neighbours == 0 or not self.train:
            return []
        excluded = _resolve_exclude(self.scene, self.train, exclude)
        picked = select_neighbours(world_from_cam.to(torch.float32), self.train_poses,
                                   self.num_neighbours, exclude=excluded or None)
        return [self.train[int(p)] for p in picked]

    def enhance(self, render: Tensor, depth: Tensor, K: Tensor, world_from_cam: Tensor, *,
                exclude: int | str | Sequence[int | str] | None = None) -> EnhanceResult:
        """Enhance one render.

        Args:
            render: ``(3, H, W)`` float in [0, 1].
            depth: ``(1, H, W)`` z-depth; ``<= 0`` or non-finite means unknown.
            K: ``(3, 3)`` intrinsics (pixel-centre convention).
            world_from_cam: ``(4, 4)`` OpenCV camera-to-world.
            exclude: scene indices or view names never used as neighbours (the target itself
                when it is a training view).
        Returns:
            :class:`EnhanceResult`; raises :class:`~roguenerf.errors.RoGUENeRFError` instead of
            returning a non-finite image.
        """
        from roguenerf.geometry import check_intrinsics, check_pose, reproject
        from roguenerf.models import NeighbourBatch

        start = time.perf_counter()
        _check_image(render, "render", 3)
        _check_image(depth, "depth", 1)
        if depth.shape[1:] != render.shape[1:]:
            raise InputError(f"depth: expected size {tuple(render.shape[1:])} like the render, "
                             f"got {tuple(depth.shape[1:])}")
        if not torch.isfinite(render).all():
            raise InputError("render: contains NaN or infinite values")
        K = check_intrinsics(torch.as_tensor(K).to(torch.float32), "K")
        world_from_cam = check_pose(torch.as_tensor(world_from_cam).to(torch.float32), "world_from_cam")
        if K.shape != (3, 3) or world_from_cam.shape != (4, 4):
            raise InputError(f"K, world_from_cam: expected (3, 3) and (4, 4), got "
                             f"{tuple(K.shape)} and {tuple(world_from_cam.shape)}")

        dev = self.device
        render_b = render.to(dev, torch.float32).clamp(0, 1)[None]
        depth_b = depth.to(dev, torch.float32)[None]
        K_b = K.to(dev)[None]
        pose_b = world_from_cam.to(dev)[None]

        chosen = self.select(world_from_cam, exclude=exclude)
        note = None
        batch = None
        if chosen:
            positions = [self.train.index(i) for i in chosen]
            features, depths = self._neighbour_data(positions)
            n_K = self.train_K[positions].to(dev)
            n_pose = self.train_poses[positions].to(dev)
            with torch.inference_mode():
                n = len(positions)
                probe = reproject(depths, depths, depth_b.expand(n, -1, -1, -1), n_K,
                                  K_b.expand(n, -1, -1), n_pose, pose_b.expand(n, -1, -1),
                                  leniency=getattr(self.model.config, "leniency", 0.25))
            if float(probe.valid.sum()) == 0.0:
                note = NO_NEIGHBOUR_NOTE
                chosen = []
            else:
                batch = NeighbourBatch(features=features[None], depth=depths[None],
                                       K=n_K[None], world_from_cam=n_pose[None])

        with torch.inference_mode():
            height, width = render.shape[1:]
            if max(height, width) > self.tile:
                from roguenerf.models.tiling import enhance_tiled

                out = enhance_tiled(self.model, render_b, depth_b, K_b, pose_b, batch, tile=self.tile,
                                    overlap=min(32, self.tile // 4))
            else:
                out = self.model(render_b, depth_b, K_b, pose_b, batch)
        if not torch.isfinite(out).all():
            raise NonFiniteOutputError("the enhancer produced non-finite values for this view; the model or "
                                 "its inputs are broken (check the checkpoint and the depth)")
        image = out[0].clamp(0, 1).to("cpu", torch.float32)
        names = [self.scene.frames[i].name for i in chosen]
        return EnhanceResult(image=image, neighbours=names, seconds=time.perf_counter() - start, note=note)

    def enhance_view(self, index: int | str) -> EnhanceResult:
        """Enhance the scene's own render of view ``index`` (scene index or name).

        A training view is never its own neighbour.
        """
        i = self.scene.index(index) if isinstance(index, str) else int(index)
        frame = self.scene.frames[i]
        return self.enhance(self.scene.render(i), self.scene.depth(i), frame.K, frame.world_from_cam,
                            exclude=i if frame.split == "train" else None)

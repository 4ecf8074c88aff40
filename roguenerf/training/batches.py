"""Training batches: random target crops and the part of each neighbour photo a crop can see.

Dimension legend: B batch, N neighbours per target, c crop side, Hs x Ws the neighbour photos'
size (a scene's training views share one size), h x w a neighbour window, P photos encoded.

Two ways to give the enhancer its neighbours (``NEIGHBOUR_ENCODINGS``), equal in loss and in
every gradient (tests/unit/roguenerf/training/test_training_windows.py):

``"whole"``
    conv_H encodes every distinct neighbour photo the batch uses, whole, at full resolution.
``"window"``
    For each target crop and neighbour, the crop's known-depth pixels are projected into the
    neighbour (float64 relative pose, as :func:`~roguenerf.reprojection.reproject`);
    conv_H encodes only the bounding window of the bilinear taps they can read, widened by
    conv_H's receptive radius (:func:`~roguenerf.models.layers.receptive_radius`) and clamped
    to the photo, with K's principal point shifted by the window offset.

Why the window gives the whole photo's values:

* **Features.** conv_H is a stack of stride-1 convolutions with zero padding. Inside the
  window, a feature more than the receptive radius r away from every window edge that is not
  an image edge sees exactly the pixels it sees in the whole photo; at an image edge the
  window's edge *is* the image's, so conv_H's own zero padding is the same padding (an
  explicitly zero-padded photo would not be: the second convolution pads its *input* feature
  map with zeros, not with the first layer's response to zeros).
* **Sampling.** Every pixel the reprojection can mark valid projects inside the photo; its
  bilinear taps (after the border clamp of the outer half pixel) lie in the taps' bounding
  box, which the window contains with r + 1 pixels to spare (one pixel for the float32 model
  coordinates against the float64 ones here: floor() may fall one pixel lower). So the
  window-frame "inside the image" test passes for exactly the same pixels (the window lies
  inside the photo, so no pixel passes there that fails in the photo), the border clamp only
  acts at real image edges (where window and photo edges coincide) and the neighbour depth used
  by the visibility test is read from the same pixels. Points that are invalid are sampled
  at pixel (0, 0) and masked, in both paths, with zero gradient.
* **Everything after the reprojection** (flow refinement, attention, fusion, Uformer) works on
  the target crop's grid: the flow network encodes the *aligned* neighbour features (target
  grid, 1/8 resolution) and ``flow_warp`` resamples them on that grid with zero padding at the
  crop's edges, never reading the neighbour photo again. The neighbour's size reaches no other
  part of the model (the camera attention sees poses only).

With conv_H frozen (``TrainConfig.freeze_neighbour_encoder``) the training views' features are
encoded once, whole (``SceneData.features``), and the batch gathers windows of those features
instead of photos: no receptive margin is needed then (the features already are the whole
photo's), only the taps' box and :data:`WINDOW_SLACK`.

Windows share one size per neighbour slot (each target's neighbours ordered by window area
first; the enhancer max-pools over neighbours, so their order does not matter), so conv_H
runs N times on ``(B, 3, h_j, w_j)`` batches. When the windows would be more pixels than the
distinct whole photos, the batch encodes those instead (same values).
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from roguenerf.errors import InputError
from roguenerf.reprojection import DEPTH_EPS, MAX_DEPTH
from roguenerf.training.config import NEIGHBOUR_ENCODINGS

WINDOW_SLACK = 1
"""Pixels added beyond conv_H's receptive radius on each side of a window: the model computes
the projected coordinates in float32, which may floor one pixel below the float64 ones here."""

INSIDE_TOLERANCE = 0.5
"""Pixels: points up to this far outside the photo's pixel area still count when bounding the
window (the model's float32 "inside" test may pass where the float64 one just fails)."""


@dataclass
class StepBatch:
    """One training step's inputs (CPU tensors), as :func:`prepare_batch` makes them.

    render, photo ``(B, 3, c, c)``; depth ``(B, 1, c, c)``; K ``(B, 3, 3)`` (crop offset applied);
    pose ``(B, 4, 4)``. Neighbours (None when the batch has none), for ``encoding``:

    ``"whole"``: ``neighbour_photos`` ``(U, 3, Hs, Ws)`` the distinct photos, ``neighbour_slot``
    ``(B, N)`` which of them each (target, neighbour) uses, ``neighbour_depth`` ``(B, N, 1, Hs, Ws)``.
    ``"window"``: ``neighbour_photos`` N tensors ``(B, 3, h_j, w_j)`` (slot j's windows, one
    size per slot), ``neighbour_depth`` N tensors ``(B, 1, h_j, w_j)``, ``windows``
    ``(B, N, 4)`` int64 (y0, x0, h, w) of each window in its photo.

    With cached conv_H features (``data.features``), ``neighbour_features`` takes the place of
    ``neighbour_photos`` (same layouts with F channels) and ``neighbour_photos`` is None.

    Both: ``neighbours`` ``(B, N)`` positions of the neighbour photos in slot order,
    ``neighbour_K`` ``(B, N, 3, 3)`` (window offset applied), ``neighbour_pose`` ``(B, N, 4, 4)``.
    """

    targets: Tensor
    origins: Tensor
    """``(B, 2)`` int64 (y0, x0) of each target crop."""
    render: Tensor
    depth: Tensor
    photo: Tensor
    K: Tensor
    pose: Tensor
    neighbours: Tensor | None = None
    neighbour_photos: Tensor | list[Tensor] | None = None
    neighbour_features: Tensor | list[Tensor] | None = None
    neighbour_slot: Tensor | None = None
    neighbour_depth: Tensor | list[Tensor] | None = None
    neighbour_K: Tensor | None = None
    neighbour_pose: Tensor | None = None
    windows: Tensor | None = None
    encoding: str = "none"
    dataset: int = 0
    sampler_state: Tensor | None = None
    """The sampling generator's state after this batch was drawn (what a resume restarts from)."""


def sample_crops(data, count: int, crop: int, generator: torch.Generator) -> Tensor:
    """``(count, 2)`` int64 random (y0, x0) of c x c crops inside ``data``'s images (c clamped to them)."""
    c_h, c_w = min(crop, data.height), min(crop, data.width)
    y0 = torch.randint(0, data.height - c_h + 1, (count,), generator=generator)
    x0 = torch.randint(0, data.width - c_w + 1, (count,), generator=generator)
    return torch.stack([y0, x0], dim=1)


def _gather_windows(images: Tensor, index: Tensor, y0: Tensor, x0: Tensor, h: int, w: int) -> Tensor:
    """``images`` ``(M, C, H, W)``; ``index``, ``y0``, ``x0`` ``(P,)`` -> ``(P, C, h, w)`` contiguous
    (one gather, no Python loop)."""
    rows = (y0[:, None] + torch.arange(h))[:, :, None]
    cols = (x0[:, None] + torch.arange(w))[:, None, :]
    out = images[index[:, None, None], :, rows, cols]  # (P, h, w, C): advanced indices come first
    return out.permute(0, 3, 1, 2).contiguous()


def crop_targets(data, targets: Tensor, origins: Tensor, crop: int):
    """Same c x c crop of render, depth and photo per target, K shifted by the crop offset.

    Returns render ``(B, 3, c, c)``, depth ``(B, 1, c, c)``, photo ``(B, 3, c, c)``, K ``(B, 3, 3)``.
    """
    c_h, c_w = min(crop, data.height), min(crop, data.width)
    y0, x0 = origins[:, 0], origins[:, 1]
    render = _gather_windows(data.renders, targets, y0, x0, c_h, c_w)
    depth = _gather_windows(data.depths, targets, y0, x0, c_h, c_w)
    photo = _gather_windows(data.photos, targets, y0, x0, c_h, c_w)
    K = data.K[targets].clone()
    K[:, 0, 2] -= x0.to(K.dtype)
    K[:, 1, 2] -= y0.to(K.dtype)
    return render, depth, photo, K


def neighbour_windows(depth: Tensor, K: Tensor, world_from_cam: Tensor, nb_K: Tensor, nb_world_from_cam: Tensor,
                      size: tuple[int, int], margin: int) -> Tensor:
    """The part of each neighbour photo that holds everything a target crop can read.

    Args:
        depth: ``(B, 1, c, c)`` target crop z-depth; K ``(B, 3, 3)`` (crop offset applied);
            world_from_cam ``(B, 4, 4)``.
        nb_K: ``(B, N, 3, 3)``; nb_world_from_cam ``(B, N, 4, 4)``.
        size: ``(Hs, Ws)`` of the neighbour photos.
        margin: pixels each window extends beyond the bilinear taps (conv_H's receptive radius);
            :data:`WINDOW_SLACK` is added to it.
    Returns:
        ``(B, N, 4)`` int64 inclusive pixel bounds ``(y_lo, x_lo, y_hi, x_hi)`` inside the photo:
        the taps' bounding box widened by ``margin + WINDOW_SLACK``. A (target, neighbour) pair
        of which no pixel can be valid gets the single pixel (0, 0).
    """
    hs, ws = size
    b, n = nb_K.shape[:2]
    c_h, c_w = depth.shape[-2:]
    d = depth.to(torch.float64).reshape(b, 1, c_h * c_w)
    known = torch.isfinite(d) & (d > DEPTH_EPS) & (d < MAX_DEPTH)
    z = torch.where(known, d, 1.0)
    # pts = z * K^-1 [u + 0.5, v + 0.5, 1] in the target camera, then into each neighbour.
    v, u = torch.meshgrid(torch.arange(c_h, dtype=torch.float64) + 0.5,
                          torch.arange(c_w, dtype=torch.float64) + 0.5, indexing="ij")
    pix = torch.stack([u.reshape(-1), v.reshape(-1), torch.ones(c_h * c_w, dtype=torch.float64)])  # (3, P)
    rays = torch.linalg.inv(K.to(torch.float64)) @ pix  # (B, 3, P)
    pts = rays * z  # (B, 3, P)
    src_from_dst = torch.linalg.inv(nb_world_from_cam.to(torch.float64)) @ world_from_cam.to(torch.float64)[:, None]
    pts_src = src_from_dst[..., :3, :3] @ pts[:, None] + src_from_dst[..., :3, 3:]  # (B, N, 3, P)
    uvw = nb_K.to(torch.float64) @ pts_src
    z_src = pts_src[:, :, 2]
    in_front = torch.isfinite(uvw).all(dim=2) & (z_src > DEPTH_EPS)
    w_div = torch.where(in_front, z_src, 1.0)
    x = uvw[:, :, 0] / w_div - 0.5
    y = uvw[:, :, 1] / w_div - 0.5
    tol = INSIDE_TOLERANCE
    valid = (known & in_front & (x >= -0.5 - tol) & (x <= ws - 0.5 + tol)
             & (y >= -0.5 - tol) & (y <= hs - 0.5 + tol))  # (B, N, P)
    seen = valid.any(dim=-1)
    pad = margin + WINDOW_SLACK

    def bounds(t: Tensor, extent: int) -> tuple[Tensor, Tensor]:
        t = t.clamp(0, extent - 1)  # the border clamp of the outer half pixel
        lo = torch.where(valid, t, torch.inf).amin(dim=-1).floor()
        hi = torch.where(valid, t, -torch.inf).amax(dim=-1).floor() + 1  # the second bilinear tap
        lo = torch.where(seen, lo - pad, 0.0).long().clamp(min=0)
        hi = torch.where(seen, hi + pad, 0.0).long().clamp(max=extent - 1)
        return lo, hi

    y_lo, y_hi = bounds(y, hs)
    x_lo, x_hi = bounds(x, ws)
    return torch.stack([y_lo, x_lo, y_hi, x_hi], dim=-1)


def place_windows(bounds: Tensor, size: tuple[int, int]) -> tuple[Tensor, Tensor, Tensor]:
    """Windows that share one size per neighbour slot, so each slot is one conv_H batch.

    ``bounds`` ``(B, N, 4)`` from :func:`neighbour_windows`. Each target's neighbours are first
    ordered by window area, largest first (the enhancer max-pools over neighbours: their order
    does not change its output), so that slot j gathers windows of like size; slot j's size is
    the largest of its B windows, and each window grows from its low corner (moved back to stay
    inside the photo) to that size.

    Returns ``order`` ``(B, N)`` (slot j of target b is its neighbour ``order[b, j]``),
    ``origins`` ``(B, N, 2)`` int64 (y0, x0) in that order, and ``sizes`` ``(N, 2)`` int64 (h, w).
    """
    hs, ws = size
    extent = bounds[..., 2:] - bounds[..., :2] + 1  # (B, N, 2)
    order = torch.argsort(-(extent[..., 0] * extent[..., 1]), dim=1, stable=True)
    bounds = torch.gather(bounds, 1, order[..., None].expand(-1, -1, 4))
    extent = torch.gather(extent, 1, order[..., None].expand(-1, -1, 2))
    sizes = extent.amax(dim=0)  # (N, 2)
    limit = torch.tensor([hs, ws]) - sizes  # (N, 2): the largest origin that keeps a window inside
    origins = torch.minimum(bounds[..., :2], limit)
    return order, origins, sizes


def displace(render: Tensor, depth: Tensor, shift: Tensor) -> tuple[Tensor, Tensor]:
    """``render`` ``(B, C, h, w)`` and ``depth`` ``(B, 1, h, w)`` read at each pixel plus ``shift``
    ``(B, 2, h, w)`` (x then y, pixels): the render bilinearly, the depth at the nearest pixel (no
    depth between two surfaces), both with the border pixels repeated beyond the edges (kornia's
    ``remap`` on pixel coordinates, ``align_corners=True``: 0 and ``w - 1`` are the edge pixels' centres)."""
    from kornia.geometry.transform import remap

    _, _, h, w = render.shape
    ys, xs = torch.meshgrid(torch.arange(h, dtype=shift.dtype), torch.arange(w, dtype=shift.dtype), indexing="ij")
    map_x, map_y = xs + shift[:, 0], ys + shift[:, 1]
    warped = remap(render, map_x.to(render.dtype), map_y.to(render.dtype), mode="bilinear",
                   padding_mode="border", align_corners=True)
    warped_depth = remap(depth, map_x.to(depth.dtype), map_y.to(depth.dtype), mode="nearest",
                         padding_mode="border", align_corners=True)
    return warped, warped_depth


def warp_renders(render: Tensor, depth: Tensor, max_shift: float, generator: torch.Generator,
                 share: float = 0.5, grid: int = 4) -> tuple[Tensor, Tensor]:
    """``render`` ``(B, 3, c, c)`` and ``depth`` ``(B, 1, c, c)`` displaced together (:func:`displace`)
    along a smooth random shift on a random ``share`` of the crops; the others unchanged.

    Each shift component is a ``grid`` x ``grid`` lattice of uniform draws in [-1, 1], upsampled
    bicubically (clamped to [-1, 1]) and scaled by ``max_shift`` pixels. A field's novel views
    are wrong at large scales (misplaced structure, floaters) where its training views, the
    fine-tune's targets, are right; this puts such errors into the targets, with the render and
    its depth still agreeing as a field's do. Draws ``B (1 + 2 grid^2)`` numbers from
    ``generator`` whatever the outcome."""
    import torch.nn.functional as F

    b, _, h, w = render.shape
    pick = torch.rand(b, generator=generator) < share
    lattice = torch.rand(b, 2, grid, grid, generator=generator) * 2.0 - 1.0
    if max_shift <= 0 or not bool(pick.any()):
        return render, depth
    shift = F.interpolate(lattice, size=(h, w), mode="bicubic", align_corners=True).clamp(-1.0, 1.0)
    warped, warped_depth = displace(render, depth, shift * float(max_shift))
    keep = ~pick[:, None, None, None]
    return torch.where(keep, render, warped), torch.where(keep, depth, warped_depth)


def corrupt_depths(depth: Tensor, max_log: float, generator: torch.Generator, share: float = 0.5,
                   grid: int = 4) -> Tensor:
    """``depth`` ``(B, 1, c, c)`` with a smooth random error on a random ``share`` of the crops;
    the others, the render and the photo unchanged: the reprojections read the wrong depth.

    The error multiplies each valid depth (> 0, finite) by ``exp(max_log * e)``, ``e`` a ``grid``
    x ``grid`` lattice of uniform draws in [-1, 1] upsampled bicubically (clamped). A field's
    novel views carry such geometry error (floaters, a surface too near or too far, depths mixed
    at silhouettes) while its render can still look right; a model trained on exact depths
    learns to trust every reprojection, and here its target is the photo whatever the
    reprojections say. Draws ``B (1 + grid^2)`` numbers from ``generator`` whatever the outcome."""
    import torch.nn.functional as F

    b, _, h, w = depth.shape
    pick = torch.rand(b, generator=generator) < share
    lattice = torch.rand(b, 1, grid, grid, generator=generator) * 2.0 - 1.0
    if max_log <= 0 or not bool(pick.any()):
        return depth
    error = F.interpolate(lattice, size=(h, w), mode="bicubic", align_corners=True).clamp(-1.0, 1.0)
    valid = (depth > 0) & torch.isfinite(depth)
    scaled = torch.where(valid, depth * torch.exp(error * float(max_log)).to(depth.dtype), depth)
    return torch.where(pick[:, None, None, None], scaled, depth)


def prepare_batch(data, targets: Tensor, origins: Tensor, crop: int, *, encoding: str = "window",
                  margin: int = 0, use_neighbours: bool = True,
                  augment: Callable[[Tensor, Tensor], tuple[Tensor, Tensor]] | None = None,
                  pose_noise: Callable[[Tensor], Tensor] | None = None,
                  drawn: Tensor | None = None) -> StepBatch:
    """Everything one step needs but the model: crops, and the neighbour photos or windows to encode.

    Args:
        data: a :class:`~roguenerf.training.loop.SceneData`.
        targets: ``(B,)`` int64 positions in ``data``; origins ``(B, 2)`` from :func:`sample_crops`.
        encoding: ``"window"`` or ``"whole"`` (module docstring).
        margin: conv_H's receptive radius (``receptive_radius(model.conv_H)``); window encoding
            only; ignored (0) when ``data.features`` holds cached conv_H features, which the
            batch then cuts instead of photos.
        use_neighbours: False gives a batch without neighbours.
        augment: ``(render, depth) -> (render, depth)`` applied to the target crops before the
            neighbour windows are bounded, so the windows hold what the changed depth reads
            (:func:`warp_renders`, :func:`corrupt_depths`).
        pose_noise: ``(B, N, 4, 4) -> (B, N, 4, 4)`` float64, the neighbours' poses as the model
            gets them (``TrainConfig.neighbour_pose_noise``); the windows are bounded with these
            (what the model reads), the photos and depths are the neighbours' own.
        drawn: ``(B,)`` bool: these targets (training views) take their render and depth crops
            from ``data.drawn_renders`` / ``data.drawn_depths``
            (:meth:`~roguenerf.training.loop.SceneData.draw_from_neighbours`) before ``augment``.
    """
    cached = getattr(data, "features", None)
    if cached is not None:
        margin = 0
    if encoding not in NEIGHBOUR_ENCODINGS:
        raise InputError(f"encoding: expected one of {', '.join(NEIGHBOUR_ENCODINGS)}, got {encoding!r}")
    render, depth, photo, K = crop_targets(data, targets, origins, crop)
    if drawn is not None and bool(drawn.any()):
        c_h, c_w = render.shape[-2:]
        pick, y0, x0 = drawn.nonzero().squeeze(1), origins[drawn, 0], origins[drawn, 1]
        render[pick] = _gather_windows(data.drawn_renders, targets[pick], y0, x0, c_h, c_w)
        depth[pick] = _gather_windows(data.drawn_depths, targets[pick], y0, x0, c_h, c_w)
    if augment is not None:
        render, depth = augment(render, depth)
    batch = StepBatch(targets=targets, origins=origins, render=render, depth=depth, photo=photo, K=K,
                      pose=data.poses[targets])
    lists = data.neighbours[targets]  # (B, N)
    if lists.shape[1] == 0 or not use_neighbours:
        return batch
    b, n = lists.shape
    used, slot = torch.unique(lists, return_inverse=True)
    nb_pose = data.poses[lists]
    if pose_noise is not None:
        nb_pose = pose_noise(nb_pose)
    if encoding == "window":
        bounds = neighbour_windows(depth, K, batch.pose, data.K[lists], nb_pose,
                                   (data.height, data.width), margin)
        order, corner, sizes = place_windows(bounds, (data.height, data.width))
        if b * int((sizes[:, 0] * sizes[:, 1]).sum()) < len(used) * data.height * data.width:
            lists = torch.gather(lists, 1, order)
            nb_pose = torch.gather(nb_pose, 1, order[..., None, None].expand(-1, -1, 4, 4))
            photos, depths = [], []
            images = data.photos if cached is None else cached
            for j, (h, w) in enumerate(sizes.tolist()):  # one conv_H batch per slot (N, not B x N)
                y0, x0 = corner[:, j, 0], corner[:, j, 1]
                photos.append(_gather_windows(images, lists[:, j], y0, x0, h, w))
                depths.append(_gather_windows(data.depths, lists[:, j], y0, x0, h, w))
            nb_K = data.K[lists].clone()
            nb_K[..., 0, 2] -= corner[..., 1].to(nb_K.dtype)
            nb_K[..., 1, 2] -= corner[..., 0].to(nb_K.dtype)
            if cached is None:
                batch.neighbour_photos = photos
            else:
                batch.neighbour_features = photos
            batch.neighbour_depth, batch.neighbour_K = depths, nb_K
            batch.neighbour_pose = nb_pose
            batch.windows = torch.cat([corner, sizes.expand(b, n, 2)], dim=-1)
            batch.neighbours, batch.encoding = lists, "window"
            return batch
    if cached is None:
        batch.neighbour_photos = data.photos[used]
    else:
        batch.neighbour_features = cached[used]
    batch.neighbour_slot = slot
    batch.neighbour_depth = data.depths[lists]
    batch.neighbour_K = data.K[lists]
    batch.neighbour_pose = nb_pose
    batch.neighbours, batch.encoding = lists, "whole"
    return batch


def model_inputs(model, batch: StepBatch, device: torch.device):
    """``(args, photo)``: ``model(*args)`` is the enhanced crop ``(B, 3, c, c)``; conv_H runs here
    (with grad, unless conv_H is frozen), or not at all when the batch carries cached features."""
    from roguenerf.models import NeighbourBatch

    nb = None
    K, pose = batch.neighbour_K, batch.neighbour_pose
    cached = batch.neighbour_features is not None
    if batch.encoding == "window":  # one conv_H batch per neighbour slot; sources of per-slot sizes
        windows = batch.neighbour_features if cached else batch.neighbour_photos
        sources = [model.neighbour_source(p.to(device) if cached else model.encode_neighbours(p.to(device)),
                                          d.to(device))
                   for p, d in zip(windows, batch.neighbour_depth)]
        nb = NeighbourBatch(features=None, depth=None, K=K.to(device), world_from_cam=pose.to(device),
                            sources=sources)
    elif batch.encoding == "whole":
        features = (batch.neighbour_features.to(device) if cached
                    else model.encode_neighbours(batch.neighbour_photos.to(device)))
        nb = NeighbourBatch(features=features[batch.neighbour_slot.to(device)],
                            depth=batch.neighbour_depth.to(device), K=K.to(device), world_from_cam=pose.to(device))
    args = (batch.render.to(device), batch.depth.to(device), batch.K.to(device), batch.pose.to(device), nb)
    return args, batch.photo.to(device)


class Prefetcher:
    """Runs ``make()`` in a background thread, ``depth`` results ahead of the consumer.

    ``next(prefetcher)`` returns the results in order; an exception raised by ``make`` is raised
    there. :meth:`close` (also on ``with`` exit) stops the thread. ``make`` must not share
    mutable state with the consumer (here: it owns the sampling generator).
    """

    def __init__(self, make: Callable[[], object], depth: int = 2):
        self._make = make
        self._queue: queue.Queue = queue.Queue(maxsize=max(1, depth))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="roguenerf-batches", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                with torch.no_grad():  # not inference_mode: the model saves these inputs for backward
                    item = (True, self._make())
                while not self._stop.is_set():
                    try:
                        self._queue.put(item, timeout=0.1)
                        break
                    except queue.Full:
                        continue
        except BaseException as exc:  # handed to the consumer
            self._queue.put((False, exc))

    def __iter__(self):
        return self

    def __next__(self):
        ok, item = self._queue.get()
        if not ok:
            raise item
        return item

    def close(self) -> None:
        self._stop.set()
        while self._thread.is_alive():
            try:
                self._queue.get(timeout=0.05)
            except queue.Empty:
                pass
        self._thread.join()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

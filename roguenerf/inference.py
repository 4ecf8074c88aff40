"""Enhance novel renders of one registered scene, with the training photos' features cached.

Dimension legend: N neighbours, F feature channels, H x W image size.

conv_H of a training photo does not depend on the novel view (paper section 3.3), so a
:class:`SceneEnhancer` encodes each training photo the first time it is chosen as a neighbour
and keeps the features; every later request reuses them. The cache is filled under a lock so
that concurrent ``enhance`` calls (the service runs several in a thread pool) never encode the
same photo twice or see a half-filled cache.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import torch
from torch import Tensor

from roguenerf.data.scene import ByteLRU
from roguenerf.enhance.options import (  # noqa: F401 (re-exported)
    DEFAULT_TILE,
    NEAR_DEGREES,
    NEAR_EXTRA,
    EnhanceOptions,
    tile_for,
    tile_overlap,
)
from roguenerf.errors import InputError, NonFiniteOutputError
from roguenerf.images import check_float_image
from roguenerf.models.layers import receptive_radius
from roguenerf.runtime import FreedMemoryGuard, release_freed_memory

DEFAULT_CACHE_BYTES = 512 << 20
"""Budget of the per-scene neighbour cache (features + depth, float32), least recently used
first out. A photo whose entry alone would take more than budget / neighbours per request is
never cached: each tile then encodes just the crop of it that the tile sees (bounded memory
for very large images, at the cost of re-encoding; the same values). With the shipped model
(16 features, an entry is 72 bytes a pixel) a 1920 x 1080 scene's three neighbours (149 MB
each) are cached, a 2016 x 1512 scene's (219 MB each) are encoded per tile: one such view's
peak memory about 1.1 GB instead of 1.8 (``python -m bench.sizes``, docs/results.md)."""

ENCODE_PIXELS = 512 * 512
"""Neighbour photos larger than two of this are encoded in strips of about this many pixels
(:meth:`SceneEnhancer._encode`): the same features in a bounded working memory."""

PROBE_PIXELS = 128 * 128
"""The "does any neighbour see this view" check looks at about this many target pixels."""

NO_NEIGHBOUR_NOTE = "no neighbour sees this view: enhanced without neighbours"

ALIGN_SIDE = 512
"""Pose refinement (:mod:`roguenerf.enhance.align`) works on copies of the neighbour photos and
depths no larger than this (long side), the last :data:`ALIGN_CACHE` of them cached (about 3 MB
a photo)."""

SELECT_CACHE = 256
"""How many neighbours' copies the measured neighbour rule keeps (no larger than
:data:`~roguenerf.enhance.select.SELECT_SIDE`, about 0.2 MB each; least recently used first out)."""

ALIGN_CACHE = 32
"""How many neighbours' small copies pose refinement keeps (least recently used first out)."""

DEPTH_CACHE_BYTES = 128 * 1024 * 1024
"""Budget of the neighbours' full-size depths a :class:`SceneEnhancer` keeps (least recently
used first out; :class:`~roguenerf.data.scene.ByteLRU`): 12 MB each at 2016 x 1512, so a
long-running process (the service) no longer keeps every neighbour's depth it ever read."""


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
    aligned: list[bool] | None = None
    """Per neighbour (as ``neighbours``): whether its pose was refined for this view
    (:mod:`roguenerf.enhance.align`); None when pose refinement is off."""
    colour_offset: list[float] | None = None
    """The view's RGB offset to the agreeing neighbours' colour (:mod:`roguenerf.enhance.colour`;
    what was added varies smoothly around it across the image); None where nothing was added
    (colour matching off, fewer than two neighbours, or too few pixels where they agree)."""
    agreement: float | None = None
    """Share of the view's pixels where two or more neighbours agree
    (:func:`~roguenerf.enhance.colour.neighbour_agreement`, measured on the small copies of
    colour matching); None where not measured (colour matching and trust both off, or fewer than
    two neighbours)."""
    agreement_map: Tensor | None = None
    """Where two or more neighbours agree, ``(1, h, w)`` bool on the small copy that gave
    ``agreement`` (its mean); None where ``agreement`` is."""
    trust: float | None = None
    """Share of the enhancer's change that was kept (:mod:`roguenerf.enhance.trust`): 1 where the
    neighbours agree on enough of the view, less where they mostly disagree (the mean over the
    image where it was set per pixel: agreement under ``TrustConfig.local_below``); None where
    trust is off or fewer than two neighbours were used (nothing to compare)."""
    candidates: list[dict] | None = None
    """A measured neighbour rule's candidates (:mod:`roguenerf.enhance.select`): per candidate
    its name, measurements and whether it was chosen; None under the other rules."""
    stages: list = field(default_factory=list)
    """What each stage after the model did (:class:`~roguenerf.enhance.stages.StageRecord`, in
    order); empty where none ran (stages off, or fewer than two neighbours)."""
    timings: dict = field(default_factory=dict)
    """Wall-clock seconds of each step of this call, in order: ``checks`` (the inputs), ``select``
    (the neighbour rule), ``probe`` (whether any neighbour sees the view), ``align`` (the
    neighbours' pose fits), ``encode`` (the neighbour photos' features, where not cached yet, or
    the photos read for a per-tile encoding), ``model`` (reprojection, flow, attention and the
    restorer, tiles included, and a per-tile encoding), ``agreement`` (the
    neighbours reprojected into the small copy the stages read) and one entry per stage that ran
    (``colour``, ``trust``). Their sum is ``seconds`` within the bookkeeping between them."""


def _check_image(x: Tensor, name: str, channels: int) -> Tensor:
    if not isinstance(x, Tensor):
        raise InputError(f"{name}: expected a torch.Tensor ({channels}, H, W), got {type(x).__name__}")
    if channels == 3:
        check_float_image(x, name)
    elif not x.is_floating_point():
        raise InputError(f"{name}: expected a floating-point z-depth map, got dtype {x.dtype}; convert it "
                         "first, e.g. depth.float() * scale for integer millimetres (scale = 0.001)")
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


class _PathFit(NamedTuple):
    """A neighbour's last pose fit along a path (:class:`PoseMemory`)."""

    pose: Tensor
    """``(4, 4)`` float64."""
    accepted: bool
    distance: float
    """From the view's camera centre to the photo's, when it was fitted."""
    settled: bool
    """The fit found nothing to gain: not fitted again."""


@dataclass
class PoseMemory:
    """Neighbour poses fitted along a camera path (:meth:`SceneEnhancer.neighbour_poses`): each
    neighbour's pose is fitted the first time a frame uses it and reused after, so the same photo
    lands the same way on every frame and the fit is paid once.

    A fit is only as good as the view it was made against: a neighbour usually joins the set
    while the path is still far from it, and the render there matches the photo worst. With
    ``refit_nearer`` in (0, 1) a frame whose camera is nearer the photo's than ``refit_nearer``
    times the distance of the last fit fits it again (and keeps that fit): a few fits per
    neighbour (each halving the distance at 0.5), made from ever nearer. A neighbour whose fit
    found nothing to gain (refused ``early`` or for its ``gain``: the dataset pose is right) is
    not fitted again. 0: fitted once. Paths take :attr:`TemporalConfig.refit_nearer
    <roguenerf.enhance.temporal.TemporalConfig.refit_nearer>`."""

    refit_nearer: float = 0.0
    fits: dict[int, _PathFit] = field(default_factory=dict)
    """Training position -> its last fit."""

    def refit(self, position: int, world_from_cam: Tensor, photo_pose: Tensor) -> bool:
        """Whether the neighbour at ``position`` must be fitted for the view at ``world_from_cam``."""
        last = self.fits.get(position)
        if last is None:
            return True
        return (self.refit_nearer > 0 and not last.settled
                and _distance(world_from_cam, photo_pose) < self.refit_nearer * last.distance)

    def keep(self, position: int, fit, world_from_cam: Tensor, photo_pose: Tensor) -> None:
        """Keep ``fit`` (an :class:`~roguenerf.enhance.align.Alignment`) made for the view at
        ``world_from_cam``."""
        self.fits[position] = _PathFit(fit.world_from_cam.clone(), fit.accepted, _distance(world_from_cam, photo_pose),
                                       fit.nothing_to_gain)


def _distance(a: Tensor, b: Tensor) -> float:
    return float((torch.as_tensor(a)[:3, 3].double() - torch.as_tensor(b)[:3, 3].double()).norm())


class SceneEnhancer:
    """An enhancer bound to one scene: the pipeline ``select -> align -> model -> stages``
    (:mod:`roguenerf.enhance`), with cached conv_H features and tiling.

    Args:
        scene: a :class:`~roguenerf.data.scene.Scene`; its ``train`` views are the neighbours.
        model: an :class:`~roguenerf.models.enhancer.Enhancer` (put in eval mode and moved to
            ``device`` here; do not train it while this object is in use).
        options: an :class:`~roguenerf.enhance.EnhanceOptions`: the neighbour rule (default: the
            model's count plus up to :data:`NEAR_EXTRA` more within :data:`NEAR_DEGREES`), pose
            refinement (``align``: each neighbour photo's pose is refined against the render, so a
            pose a little off still lands on it), the stages after the model (``colour``: the
            low-frequency colour brought to the agreeing neighbour photos'; ``trust``: only part of
            the change kept where the neighbours mostly disagree) and the tile size. Default:
            ``EnhanceOptions()``, every stage on.
        num_neighbours, tile, align, colour, trust: shortcuts for
            :meth:`EnhanceOptions.from_flags <roguenerf.enhance.EnhanceOptions.from_flags>` when
            ``options`` is not given (a count gives exactly that many neighbours; each stage True,
            False or its config).
        device: where the model runs.
        cache_bytes: budget of the neighbour cache (:data:`DEFAULT_CACHE_BYTES`).
        settled_file: where the pose judgements (:attr:`settled`) are kept between processes
            (:mod:`roguenerf.enhance.settled`; e.g. :func:`~roguenerf.enhance.settled.default_path`
            of the scene's folder): read here, written as they grow (its folder must exist).
            None: this object only.
    """

    def __init__(self, scene, model, *, options: EnhanceOptions | None = None, num_neighbours: int | None = None,
                 tile: int | None = None, device: str | torch.device = "cpu", cache_bytes: int = DEFAULT_CACHE_BYTES,
                 align=None, colour=None, trust=None, settled_file: str | os.PathLike | None = None):
        shortcuts = {"num_neighbours": num_neighbours, "tile": tile, "align": align, "colour": colour, "trust": trust}
        given = [name for name, value in shortcuts.items() if value is not None]
        if options is None:
            options = EnhanceOptions.from_flags(
                neighbours=num_neighbours, tile=tile, align=True if align is None else align,
                colour=True if colour is None else colour, trust=True if trust is None else trust)
        elif not isinstance(options, EnhanceOptions):
            raise InputError(f"options: expected an EnhanceOptions, got {type(options).__name__}")
        elif given:
            raise InputError(f"{', '.join(given)}: give them in options (EnhanceOptions), not beside it")
        self.options = options
        self.scene = scene
        self.device = torch.device(device)
        self.model = model.to(self.device).eval()
        config = getattr(model, "config", None)
        default_n = getattr(config, "num_neighbours", 5) if config is not None else 5
        self.use_neighbours = bool(getattr(config, "use_neighbours", True)) if config is not None else True
        self.num_neighbours, self.near_extra = options.neighbours.counts(int(default_n))
        self.tile = tile_for(options.tile, self.device)  # where the view's size is not known (view_tile)
        self.train = list(scene.indices("train"))
        self.train_names = [scene.frames[i].name for i in self.train]
        poses = scene.poses()
        intrinsics = scene.intrinsics()
        # Poses stay float64: relative poses are formed from them in float64 (reprojection,
        # camera attention, neighbour ranking) and only then cast, so scenes far from the
        # origin (UTM / ECEF, 1e6 units) keep their geometry. Intrinsics are fine in float32.
        if self.train:
            self.train_poses = poses[self.train].to(torch.float64)
            self.train_K = intrinsics[self.train].to(torch.float32)
        else:
            self.train_poses = torch.zeros(0, 4, 4, dtype=torch.float64)
            self.train_K = torch.zeros(0, 3, 3)
        from roguenerf.enhance.stages import agreement_test, stages_for

        self.align = options.align
        self.colour = options.colour
        self.trust = options.trust
        self.stages = stages_for(options)
        self._agreement_test = agreement_test(self.stages)
        self._small: OrderedDict[int, tuple[Tensor, Tensor, Tensor, dict]] = OrderedDict()
        self._tiny: OrderedDict[int, tuple[Tensor, Tensor, Tensor]] = OrderedDict()
        self.cache_bytes = int(cache_bytes)
        self._sources: OrderedDict[int, Tensor] = OrderedDict()
        self._depths = ByteLRU(DEPTH_CACHE_BYTES)
        self._lock = threading.Lock()
        self.settled: set[int] = set()
        """Training positions whose pose fit found nothing to gain on an earlier view
        (:attr:`AlignConfig.reuse <roguenerf.enhance.align.AlignConfig.reuse>`), or in an
        earlier process (``settled_file``)."""
        self.settled_file = None
        if settled_file is not None and self.align is not None and self.align.reuse:
            from roguenerf.enhance import settled

            self.settled_file = Path(settled_file)
            known = settled.load(self.settled_file, scene, self.train_names, self.align)
            self.settled = {p for p, name in enumerate(self.train_names) if name in known}

    def _source_bytes(self, position: int) -> int:
        frame = self.scene.frames[self.train[position]]
        features = getattr(self.model.config, "features", 64)
        return (features + 2) * frame.height * frame.width * 4

    def cacheable(self, position: int) -> bool:
        """Whether training position ``position``'s neighbour entry fits the cache budget."""
        return self._source_bytes(position) * max(1, self.num_neighbours + self.near_extra) <= self.cache_bytes

    def _depth(self, position: int) -> Tensor:
        """``(1, Hs, Ws)`` rendered depth of a training position (kept within
        :data:`DEPTH_CACHE_BYTES`: 4 bytes a pixel)."""
        depth = self._depths.get((position,))
        if depth is None:
            depth = self.scene.depth(self.train[position]).to(self.device, torch.float32)
            self._depths.put((position,), depth)
        return depth

    def _encode(self, photo: Tensor) -> Tensor:
        """``model.encode_neighbours(photo)`` for one ``(1, 3, H, W)`` photo, in strips of rows of
        about :data:`ENCODE_PIXELS` pixels where the photo is larger than two of them: each strip
        encoded with a margin of conv_H's receptive radius (zero padding only at the photo's
        real borders), so the values are the whole photo's (to float rounding) and the encoder's
        working memory stays that of one strip."""
        h, w = photo.shape[-2:]
        if h * w <= 2 * ENCODE_PIXELS:
            return self.model.encode_neighbours(photo)
        halo = receptive_radius(self.model.conv_H)
        rows = max(8, ENCODE_PIXELS // w)
        out = None
        for y0 in range(0, h, rows):
            y1 = min(y0 + rows, h)
            a, b = max(0, y0 - halo), min(h, y1 + halo)
            part = self.model.encode_neighbours(photo[..., a:b, :])
            if out is None:
                out = part.new_empty(*part.shape[:2], h, w)
            out[..., y0:y1, :] = part[..., y0 - a:y1 - a, :]
            del part
        return out

    def _cached_sources(self, positions: list[int]) -> list[Tensor]:
        """``(1, F + 2, Hs, Ws)`` sampling sources (features, depth, mask) of cacheable positions."""
        with self._lock:
            out = []
            for p in positions:
                if p not in self._sources:
                    photo = self.scene.photo(self.train[p]).to(self.device, torch.float32)[None]
                    with torch.inference_mode():
                        feats = self._encode(photo)
                        del photo
                        self._sources[p] = self.model.neighbour_source(feats, self._depth(p)[None])
                        del feats
                    used = sum(t.numel() * t.element_size() for t in self._sources.values())
                    while used > self.cache_bytes and len(self._sources) > 1:
                        _, old = self._sources.popitem(last=False)
                        used -= old.numel() * old.element_size()
                self._sources.move_to_end(p)
                out.append(self._sources[p])
        return out

    def _small_neighbour(self, position: int) -> tuple[Tensor, Tensor, Tensor, dict]:
        """Photo ``(3, h, w)``, depth ``(1, h, w)`` and K of a training position, no larger than
        :data:`ALIGN_SIDE`, and the fit's cache of its levels (all cached): what the pose
        refinement reads."""
        from roguenerf.enhance.align import shrink

        with self._lock:
            if position not in self._small:
                i = self.train[position]
                self._small[position] = (*shrink(self.scene.photo(i), self.scene.depth(i),
                                                 self.train_K[position], ALIGN_SIDE), {})
                while len(self._small) > ALIGN_CACHE:
                    self._small.popitem(last=False)
            self._small.move_to_end(position)
            return self._small[position]

    def neighbour_poses(self, positions: list[int], render: Tensor, depth: Tensor, K: Tensor,
                        world_from_cam: Tensor, *, memory: PoseMemory | None = None) -> tuple[Tensor, list[bool]]:
        """``(N, 4, 4)`` float64 poses of the neighbours at training ``positions`` for this view:
        refined against the render where :attr:`align` is on and the fit is accepted, else the
        dataset's; and, per neighbour, whether it was refined. With ``memory`` (kept by the
        caller: a camera path) a neighbour's pose is fitted the first time it is used and reused
        after, fitted again on a view nearer the photo (:class:`PoseMemory`). Without it, where
        :attr:`AlignConfig.reuse <roguenerf.enhance.align.AlignConfig.reuse>` is on, a neighbour
        whose fit found nothing to gain on an earlier view (:attr:`settled`) keeps its dataset
        pose without a fit."""
        from roguenerf.enhance.align import align_neighbour, shrink

        poses = self.train_poses[positions].clone()
        if self.align is None:
            return poses, [False] * len(positions)
        reuse = memory is None and self.align.reuse
        small = None
        done = []
        grown = False
        for j, p in enumerate(positions):
            if memory is not None and not memory.refit(p, world_from_cam, self.train_poses[p]):
                poses[j] = memory.fits[p].pose
                done.append(memory.fits[p].accepted)
                continue
            if reuse and p in self.settled:  # nothing to gain on an earlier view: the dataset pose
                done.append(False)
                continue
            if small is None:
                small = shrink(render, depth, K, ALIGN_SIDE)
                target = {}  # the view's levels, built by the first fit and read by the others
            photo, photo_depth, photo_K, levels = self._small_neighbour(p)
            fit = align_neighbour(photo, photo_depth, photo_K, poses[j], *small, world_from_cam, config=self.align,
                                  cache=levels, target_cache=target)
            if reuse and fit.nothing_to_gain:
                self.settled.add(p)
                grown = True
            poses[j] = fit.world_from_cam
            done.append(fit.accepted)
            if memory is not None:
                memory.keep(p, fit, world_from_cam, self.train_poses[p])
        if grown and self.settled_file is not None:
            from roguenerf.enhance import settled

            settled.save(self.settled_file, self.scene, [self.train_names[p] for p in sorted(self.settled)], self.align)
        return poses, done

    def view_tile(self, size: tuple[int, int]) -> int:
        """The tile a view of ``size`` (height, width) is enhanced in (:func:`tile_for`)."""
        return tile_for(self.options.tile, self.device, size)

    def _crop_provider(self, positions: list[int], world_from_cam: Tensor, poses: Tensor):
        """Per-tile neighbours for photos too large to cache: for each tile, each neighbour's
        features are computed on just the part of its photo the tile projects into (plus the
        bilinear and conv_H margins), which gives the same values as the whole photo's."""
        from roguenerf.models import NeighbourBatch
        from roguenerf.reprojection import reproject, sampling_source

        photos = [self.scene.photo(self.train[p]).to(self.device, torch.float32) for p in positions]
        depths = [self._depth(p) for p in positions]
        Ks = self.train_K[positions].to(self.device)
        poses = poses.to(self.device)
        leniency = getattr(self.model.config, "leniency", 0.25)
        with torch.inference_mode():
            depth_sources = [sampling_source(d[None], d[None]) for d in depths]

        halo = receptive_radius(self.model.conv_H) if self.model.conv_H is not None else 0
        trim = FreedMemoryGuard()

        def provider(depth_tile: Tensor, K_tile: Tensor):
            # Crop sizes differ from tile to tile: the kept-freed heap fragments and the RSS
            # would grow tile after tile. Return the freed blocks to the OS once it has grown
            # by TRIM_MARGIN (not every tile: each trim's pages are faulted in again).
            trim()
            sources, crop_K = [], []
            for photo, depth, depth_source, K_j, pose_j in zip(photos, depths, depth_sources, Ks, poses):
                hs, ws = depth.shape[-2:]
                rp = reproject(depth[None], depth[None], depth_tile, K_j, K_tile[0], pose_j,
                               world_from_cam, leniency=leniency, source=depth_source)
                valid = rp.valid[0, 0] > 0
                if bool(valid.any()):
                    xs, ys = rp.coords[0, ..., 0][valid], rp.coords[0, ..., 1][valid]
                    x0 = max(int(torch.floor(xs.min())) - 1, 0)
                    x1 = min(int(torch.ceil(xs.max())) + 2, ws)
                    y0 = max(int(torch.floor(ys.min())) - 1, 0)
                    y1 = min(int(torch.ceil(ys.max())) + 2, hs)
                else:  # nothing to see: a small crop whose depth is all unknown
                    x0, x1, y0, y1 = 0, min(ws, 2), 0, min(hs, 2)
                # conv_H's receptive radius: a crop encoded with this margin gives exactly the
                # whole photo's features inside the crop (zero padding only at real borders).
                hx0, hy0 = max(x0 - halo, 0), max(y0 - halo, 0)
                hx1, hy1 = min(x1 + halo, ws), min(y1 + halo, hs)
                feats = self.model.encode_neighbours(photo[None, :, hy0:hy1, hx0:hx1])
                feats = feats[..., y0 - hy0:y1 - hy0, x0 - hx0:x1 - hx0]
                crop_depth = depth[None, :, y0:y1, x0:x1]
                if not bool(valid.any()):
                    crop_depth = torch.zeros_like(crop_depth)
                sources.append(self.model.neighbour_source(feats, crop_depth))
                K_c = K_j.clone()
                K_c[0, 2] -= x0
                K_c[1, 2] -= y0
                crop_K.append(K_c)
            return NeighbourBatch(None, None, torch.stack(crop_K)[None], poses[None], sources=sources)

        return provider

    def cached_views(self) -> int:
        """How many training photos' features are in the cache now."""
        with self._lock:
            return len(self._sources)

    def select(self, world_from_cam: Tensor, *, exclude=None, view=None) -> list[int]:
        """Scene indices of the neighbours of a pose (nearest first), per the rule
        (:class:`~roguenerf.enhance.NeighbourRule`): the paper's ranking, the model's count, then
        up to :attr:`near_extra` more of the next nearest that are within the rule's
        ``near_degrees`` of the pose's rotation. A measured rule needs ``view = (render, depth,
        K)`` to measure its candidates; without it, every candidate it may choose from."""
        return self._choose(world_from_cam, exclude, view)[0]

    def _choose(self, world_from_cam: Tensor, exclude, view) -> tuple[list[int], list[dict] | None]:
        """``select``, and a measured rule's candidates (name, measurements, chosen) or None."""
        from roguenerf.geometry import rotation_angle

        if not self.use_neighbours or self.num_neighbours == 0 or not self.train:
            return [], None
        rule = self.options.neighbours
        pose = torch.as_tensor(world_from_cam).to(torch.float64)
        if rule.measured:
            from roguenerf.enhance.select import choose

            positions = self.candidates(pose, rule.candidates, exclude=exclude)
            if view is None:
                return [self.train[p] for p in positions], None
            measured = self.measure(*view, pose, positions)
            kept = choose(measured, least=rule.least, most=rule.most, min_coverage=rule.min_coverage,
                          error_ratio=rule.error_ratio, near_degrees=rule.near_degrees)
            report = [{"name": self.train_names[c.position], **c.as_dict(), "chosen": c in kept} for c in measured]
            return [self.train[c.position] for c in kept], report
        picked = self.candidates(pose, self.num_neighbours + self.near_extra, exclude=exclude)
        kept = picked[: self.num_neighbours]
        for p in picked[self.num_neighbours:]:
            if float(rotation_angle(pose[:3, :3], self.train_poses[p, :3, :3])) <= rule.near_degrees:
                kept.append(p)
        return [self.train[p] for p in kept], None

    def candidates(self, world_from_cam: Tensor, count: int, *, exclude=None) -> list[int]:
        """Training positions of the ``count`` nearest training views of a pose, by the paper's
        rule (nearest first)."""
        from roguenerf.geometry import select_neighbours

        if not self.train or count <= 0:
            return []
        excluded = _resolve_exclude(self.scene, self.train, exclude)
        pose = torch.as_tensor(world_from_cam).to(torch.float64)
        return [int(p) for p in select_neighbours(pose, self.train_poses, count, exclude=excluded or None)]

    def photo_distance(self, world_from_cam: Tensor, *, exclude=None) -> float:
        """Distance from a pose's camera centre to the nearest training camera's (pose units;
        ``exclude``: views left out, as :meth:`select`'s); ``inf`` where there is none."""
        excluded = set(_resolve_exclude(self.scene, self.train, exclude))
        kept = [p for p in range(len(self.train)) if p not in excluded]
        if not kept:
            return math.inf
        centre = torch.as_tensor(world_from_cam).to(torch.float64)[:3, 3]
        return float((self.train_poses[kept, :3, 3] - centre).norm(dim=-1).min())

    def measure(self, render: Tensor, depth: Tensor, K: Tensor, world_from_cam: Tensor,
                positions: list[int]) -> list:
        """:func:`~roguenerf.enhance.select.measure_candidates` for the training ``positions``
        (their small copies cached)."""
        from roguenerf.enhance.align import shrink
        from roguenerf.enhance.select import SELECT_SIDE, measure_candidates

        tiny = []
        for p in positions:
            with self._lock:
                entry = self._tiny.get(p)
            if entry is None:
                photo, photo_depth, photo_K, _ = self._small_neighbour(p)
                entry = shrink(photo, photo_depth, photo_K, SELECT_SIDE)
                with self._lock:
                    self._tiny[p] = entry
                    while len(self._tiny) > SELECT_CACHE:
                        self._tiny.popitem(last=False)
            tiny.append((*entry, self.train_poses[p]))
        return measure_candidates(render, depth, K, world_from_cam, tiny, positions=positions,
                                  leniency=getattr(self.model.config, "leniency", 0.25))

    def enhance(self, render: Tensor, depth: Tensor, K: Tensor, world_from_cam: Tensor, *,
                exclude: int | str | Sequence[int | str] | None = None, progress=None,
                neighbours: Sequence[int | str] | None = None, pose_memory: PoseMemory | None = None) -> EnhanceResult:
        """Enhance one render.

        Args:
            render: ``(3, H, W)`` float in [0, 1] (values outside are clamped). Integer and bool
                tensors (e.g. ``uint8`` 0-255) raise :class:`~roguenerf.errors.InputError`:
                convert them first (``x.float() / 255``); see :mod:`roguenerf.images`.
            depth: ``(1, H, W)`` float z-depth; unknown where
                :func:`~roguenerf.geometry.depth.known_depth_mask` is False (non-finite,
                ``<= DEPTH_EPS`` = 1e-6, or ``>= MAX_DEPTH`` = 1e10).
            K: ``(3, 3)`` intrinsics (pixel-centre convention).
            world_from_cam: ``(4, 4)`` or ``(3, 4)`` OpenCV camera-to-world (a proper rotation:
                :func:`~roguenerf.geometry.check_pose`); used in float64 (pass float64 for
                scenes far from the origin: float32 cannot hold 5e6 to better than 0.5).
            exclude: scene indices or view names never used as neighbours (the target itself
                when it is a training view).
            progress: optional ``callback(done, total)`` called after each tile of a tiled image.
            neighbours: training views (scene indices or names) to use instead of the rule's
                choice, in this order (an empty list: none).
            pose_memory: what the caller keeps across calls (the frames of one camera path):
                each neighbour's refined pose is fitted once and reused (:class:`PoseMemory`).
        Returns:
            :class:`EnhanceResult`; raises :class:`~roguenerf.errors.RoGUENeRFError` instead of
            returning a non-finite image.
        """
        from roguenerf.geometry import as_world_from_cam, check_intrinsics
        from roguenerf.models import NeighbourBatch

        start = time.perf_counter()
        timings: dict[str, float] = {}
        last = start

        def lap(name: str) -> None:
            nonlocal last
            now = time.perf_counter()
            timings[name] = now - last
            last = now

        _check_image(render, "render", 3)
        _check_image(depth, "depth", 1)
        if depth.shape[1:] != render.shape[1:]:
            raise InputError(f"depth: expected size {tuple(render.shape[1:])} like the render, "
                             f"got {tuple(depth.shape[1:])}")
        if not torch.isfinite(render).all():
            raise InputError("render: contains NaN or infinite values")
        K = check_intrinsics(torch.as_tensor(K).to(torch.float32), "K")
        world_from_cam = torch.as_tensor(world_from_cam)
        if world_from_cam.is_floating_point():
            world_from_cam = world_from_cam.to(torch.float64)
        world_from_cam = as_world_from_cam(world_from_cam, "world_from_cam")  # 3x4 padded
        if K.shape != (3, 3) or world_from_cam.shape != (4, 4):
            raise InputError(f"K, world_from_cam: expected (3, 3) and (4, 4) or (3, 4), got "
                             f"{tuple(K.shape)} and {tuple(world_from_cam.shape)}")

        dev = self.device
        render_b = render.to(dev, torch.float32).clamp(0, 1)[None]
        depth_b = depth.to(dev, torch.float32)[None]
        K_b = K.to(dev)[None]
        pose_b = world_from_cam.to(dev)[None]

        lap("checks")
        measured = None
        if neighbours is None:
            chosen, measured = self._choose(world_from_cam, exclude, (render, depth, K))
        else:
            chosen = [self.scene.index(n) if isinstance(n, str) else int(n) for n in neighbours]
            strangers = [n for n, i in zip(neighbours, chosen, strict=True) if i not in self.train]
            if strangers:
                raise InputError(f"neighbours: {strangers} are not training views of this scene")
        lap("select")
        note = None
        batch = None
        aligned = None
        if chosen:
            positions = [self.train.index(i) for i in chosen]
            seen_at_all = self._any_neighbour_sees(positions, depth_b, K_b, pose_b)
            lap("probe")
            if not seen_at_all:
                note = NO_NEIGHBOUR_NOTE
                chosen = []
            else:
                n_K = self.train_K[positions].to(dev)
                n_pose, done = self.neighbour_poses(positions, render, depth, K, world_from_cam, memory=pose_memory)
                aligned = done if self.align is not None else None
                n_pose = n_pose.to(dev)
                lap("align")
                if all(self.cacheable(p) for p in positions):
                    batch = NeighbourBatch(None, None, n_K[None], n_pose[None],
                                           sources=self._cached_sources(positions))
                else:
                    batch = self._crop_provider(positions, pose_b[0], n_pose)

        lap("encode")
        with torch.inference_mode():
            height, width = render.shape[1:]
            tile = self.view_tile((height, width))
            if max(height, width) > tile or callable(batch):
                from roguenerf.models.tiling import enhance_tiled

                out = enhance_tiled(self.model, render_b, depth_b, K_b, pose_b, batch, tile=tile,
                                    overlap=tile_overlap(tile), progress=progress)
            else:
                out = self.model(render_b, depth_b, K_b, pose_b, batch)
        if callable(batch):  # a very large image: hand its working set back to the OS now
            batch = None
            release_freed_memory()
        if not torch.isfinite(out).all():
            raise NonFiniteOutputError("the enhancer produced non-finite values for this view; the model or "
                                 "its inputs are broken (check the checkpoint and the depth)")
        image = out[0].clamp(0, 1).to("cpu", torch.float32)
        lap("model")
        state = None
        if self.stages and len(chosen) >= 2:
            from roguenerf.enhance.colour import neighbour_agreement
            from roguenerf.enhance.stages import ViewState

            seen, small_image = self._small_seen(positions, image, depth, K, world_from_cam, n_pose)
            agreement = neighbour_agreement(seen, small_image.shape[-2:], *self._agreement_test)
            state = ViewState(image=image, render=render, seen=seen, small_image=small_image, agreement=agreement,
                              test=self._agreement_test, note=note)
            lap("agreement")
            records = []
            for stage in self.stages:
                records.append(stage.apply(state))
                lap(stage.name)
            image, note = state.image, state.note
        records = records if state is not None else []
        detail = {r.name: r.detail for r in records}
        offset = detail.get("colour", {}).get("offset")
        kept = detail.get("trust", {}).get("kept")
        names = [self.scene.frames[i].name for i in chosen]
        return EnhanceResult(image=image, neighbours=names, seconds=time.perf_counter() - start, note=note,
                             aligned=aligned if chosen else ([] if self.align is not None else None),
                             colour_offset=offset, agreement=None if state is None else round(state.share, 4),
                             agreement_map=None if state is None else state.agreement[0],
                             trust=kept, stages=records, candidates=measured, timings=timings)

    def colour_match(self, positions: list[int], image: Tensor, depth: Tensor, K: Tensor,
                     world_from_cam: Tensor, poses: Tensor):
        """How far ``image`` (an enhanced view) is from the colour of the neighbours at training
        ``positions`` seen from ``poses`` (:func:`~roguenerf.enhance.colour.colour_match`), on
        copies no larger than :data:`ALIGN_SIDE` (the neighbours' are the pose fit's): a
        :class:`~roguenerf.enhance.colour.ColourMatch` whose field is at the small copy's size;
        None where there is no agreement to match, or colour matching is off."""
        from roguenerf.enhance.colour import colour_match

        if self.colour is None:
            return None
        seen, small = self._small_seen(positions, image, depth, K, world_from_cam, poses)
        return colour_match(small[None], seen, self.colour)

    def _small_seen(self, positions: list[int], image: Tensor, depth: Tensor, K: Tensor, world_from_cam: Tensor,
                    poses: Tensor) -> tuple[list[tuple[Tensor, Tensor]], Tensor]:
        """The neighbours at training ``positions`` (seen from ``poses``) reprojected into the
        view's copy no larger than :data:`ALIGN_SIDE`, as ``(colour, valid)`` pairs, and
        ``image``'s copy at that size."""
        from roguenerf.enhance.align import shrink
        from roguenerf.reprojection import reproject

        small, small_depth, small_K = shrink(image, depth, K, ALIGN_SIDE)
        leniency = getattr(self.model.config, "leniency", 0.25)
        pose = torch.as_tensor(world_from_cam).to(torch.float64)
        seen = []
        with torch.inference_mode():
            for j, p in enumerate(positions):
                photo, photo_depth, photo_K, _ = self._small_neighbour(p)
                r = reproject(photo[None], photo_depth[None], small_depth[None], photo_K.float(), small_K.float(),
                              poses[j].cpu().to(torch.float64), pose, leniency=leniency)
                seen.append((r.features, r.valid))
        return seen, small

    def _any_neighbour_sees(self, positions: list[int], depth_b: Tensor, K_b: Tensor, pose_b: Tensor) -> bool:
        """Whether any target pixel passes the reprojection test in any neighbour, checked on a
        regular subsample of about :data:`PROBE_PIXELS` target pixels (cheap at any size)."""
        from roguenerf.reprojection import reproject

        h, w = depth_b.shape[-2:]
        step = max(1, int((h * w / PROBE_PIXELS) ** 0.5))
        sub = depth_b[..., ::step, ::step]
        K_sub = K_b[0].clone()
        # Pixel u' of the subsample is pixel step * u' (centre step * u' + 0.5) of the image.
        K_sub[:2] /= step
        K_sub[0, 2] += 0.5 - 0.5 / step
        K_sub[1, 2] += 0.5 - 0.5 / step
        leniency = getattr(self.model.config, "leniency", 0.25)
        with torch.inference_mode():
            for p in positions:
                depth = self._depth(p)[None]
                probe = reproject(depth, depth, sub, self.train_K[p].to(depth), K_sub,
                                  self.train_poses[p].to(depth.device), pose_b[0], leniency=leniency)
                if bool(probe.valid.any()):
                    return True
        return False

    def enhance_view(self, index: int | str, *, progress=None) -> EnhanceResult:
        """Enhance the scene's own render of view ``index`` (scene index or name).

        A training view is never its own neighbour.
        """
        i = self.scene.index(index) if isinstance(index, str) else int(index)
        frame = self.scene.frames[i]
        return self.enhance(self.scene.render(i), self.scene.depth(i), frame.K, frame.world_from_cam,
                            exclude=i if frame.split == "train" else None, progress=progress)

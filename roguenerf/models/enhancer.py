"""The full RoGUENeRF enhancer (paper section 3, supplementary implementation details).

For a target render I_k with depth D_k and neighbours H_i (training photos, their conv_H
features cached per scene):

    I^f = conv_I(I_k)
    H_{i->k} = reproject(conv_H(H_i))                       3D alignment (use_alignment)
    H'_i = warp(H_{i->k}, flow(H_{i->k}, I^f))              non-rigid refinement (use_refinement)
    H^a_i = psi_cam_i * psi_pix_i * H'_i                     geometry-aware attention (use_attention)
    H_pool = max_i H^a_i                                     0 without neighbours
    out = I_k + Uformer(conv_merge([I^f, H_pool]))           global residual

With ``pool_spread`` (not in the paper), conv_merge also sees ``H_spread = max_i H^a_i -
min_i H^a_i``: how much the weighted neighbours disagree at each pixel (0 with one neighbour).

Scale invariance (a deviation from the paper, which feeds raw depths and absolute camera
positions): scenes come in arbitrary units, so the depths fed to the attention are divided by
the target's median known depth ``s`` (known: :mod:`roguenerf.geometry.depth`, so ``s`` lies in
``(DEPTH_EPS, MAX_DEPTH)``; then clamped to [0, MAX_RELATIVE_DEPTH]) and the camera
attention sees the neighbour's position relative to the target, ``(t_i - t_k) / s`` (clamped
to +-MAX_RELATIVE_DEPTH), instead of ``t_i, t_k``. Scaling a scene's units (depths and
translations together) therefore leaves the output unchanged.

Poses may be float64 and should be when cameras are far from the origin: relative poses
(reprojection) and relative positions (camera attention) are formed in float64 from the poses
as given, and only then cast to the features' dtype, so translating a whole scene (1e6 units)
leaves the output unchanged to float32 rounding.

Without gradients, neighbours are processed one at a time and max-pooled on the fly, so memory
does not grow with their number and the output is exactly invariant to their order. With
gradients (training) they go through refinement and attention as one batch of N * B, sharing
the target's work (``_fuse_batched``; autograd keeps every neighbour's activations either
way); ``reference_mode()`` keeps the per-neighbour loop, equal in output and gradients.

Dimension letters: B batch, N neighbours, F feature channels, H x W target size,
Hs x Ws neighbour size.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from roguenerf import ops
from roguenerf.errors import InputError
from roguenerf.geometry import euler_angles
from roguenerf.geometry.cameras import check_intrinsics, check_pose
from roguenerf.geometry.depth import DEPTH_EPS, MAX_DEPTH, known_depth, known_depth_mask, median_known_depth
from roguenerf.images import check_float_image
from roguenerf.models.config import _UFORMER_KEYS, EnhancerConfig, make_config
from roguenerf.models.flow import FLOW_STRIDE, FlowRefiner, flow_warp
from roguenerf.models.layers import (
    CameraAttention,
    ConvEncoder,
    PixelAttention,
    act,
    cat_channels_last,
    conv_act,
    he_init,
    zero_init,
)
from roguenerf.models.uformer import Uformer
from roguenerf.profiling import stage
from roguenerf.reprojection import reproject, sampling_source

MAX_RELATIVE_DEPTH = 10.0
"""Normalised depths and relative camera positions are clamped to this magnitude."""


@dataclass
class NeighbourBatch:
    """Neighbours of each target in a batch; N may be 0.

    features: ``(B, N, F, Hs, Ws)`` conv_H features of the neighbour *photos* (cached per scene);
        None when ``sources`` is given.
    depth: ``(B, N, 1, Hs, Ws)`` the neighbours' rendered z-depth; None when ``sources`` is given.
    K: ``(B, N, 3, 3)``; world_from_cam: ``(B, N, 4, 4)`` OpenCV.
    sources: optional list of N tensors ``(B, F + 2, Hs_j, Ws_j)``, neighbour j's
        :func:`~roguenerf.reprojection.sampling_source` (features, known depth, known mask),
        which already hold features and depth. Per-scene work that
        :class:`~roguenerf.inference.SceneEnhancer` caches, so that no request re-stacks the
        neighbour features; neighbours may then differ in size (crops of large photos, with
        K's principal point shifted by the crop offset).
    """

    features: Tensor | None
    depth: Tensor | None
    K: Tensor
    world_from_cam: Tensor
    sources: list[Tensor] | None = None

    def __len__(self) -> int:
        return len(self.sources) if self.sources is not None else self.K.shape[1]

    def feature_map(self, j: int) -> Tensor:
        """``(B, F, Hs, Ws)`` features of neighbour j (a view, no copy)."""
        if self.sources is not None:
            return self.sources[j][:, :-2]
        return self.features[:, j]

    def depth_map(self, j: int) -> Tensor:
        """``(B, 1, Hs, Ws)`` depth of neighbour j (with sources: the known depth, 0 where unknown)."""
        if self.sources is not None:
            return self.sources[j][:, -2:-1]
        return self.depth[:, j]


median_depth = median_known_depth
"""``(B, 1, H, W)`` z-depth -> ``(B,)`` median over known pixels (1.0 where none is known);
see :func:`roguenerf.geometry.depth.median_known_depth`."""


def _check(x, name: str, shape: tuple, *, image: bool = False) -> Tensor:
    """``shape`` entries: int = exact size, None = any size >= 1. ``image``: an RGB image in
    [0, 1] (integer dtypes are refused with the conversion rule, :mod:`roguenerf.images`)."""
    if image:
        check_float_image(x, name)
    if not isinstance(x, Tensor) or not x.is_floating_point():
        got = x.dtype if isinstance(x, Tensor) else type(x).__name__
        raise InputError(f"{name}: expected a floating-point tensor, got {got}")
    ok = x.ndim == len(shape) and all(s is None and n >= 1 or s == n for s, n in zip(shape, x.shape))
    if not ok:
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise InputError(f"{name}: expected shape {want}, got {tuple(x.shape)}")
    return x


class Enhancer(nn.Module):
    """RoGUENeRF enhancer built from an :class:`EnhancerConfig` (see the module docstring).

    Sub-modules a switch turns off are not built (``None``), so they hold no parameters.
    """

    def __init__(self, config: EnhancerConfig):
        super().__init__()
        self.config = cfg = config
        f = cfg.features
        self.conv_I = ConvEncoder(features=f)
        nb = cfg.use_neighbours
        self.conv_H = ConvEncoder(features=f) if nb else None
        self.flow = (FlowRefiner(features=f, hidden=cfg.flow_hidden, iters=cfg.flow_iters)
                     if nb and cfg.use_refinement else None)
        self.pixel_attention = (PixelAttention(features=f, hidden=cfg.attention_hidden)
                                if nb and cfg.use_attention else None)
        self.camera_attention = CameraAttention(hidden=cfg.attention_hidden) if nb and cfg.use_attention else None
        self.conv_merge = he_init(nn.Sequential(nn.Conv2d(self.pooled_maps * f + f, f, 3, padding=1), act()))
        if cfg.use_uformer:
            self.uformer = Uformer(cfg.uformer, in_channels=f, out_channels=3)
            self.to_rgb = None
        else:
            self.uformer = None
            self.to_rgb = zero_init(nn.Conv2d(f, 3, 3, padding=1))

    @property
    def pooled_maps(self) -> int:
        """Neighbour maps (F channels each) that conv_merge sees after I^f: 0 without a neighbour
        branch, 1 (H_pool), 2 with ``pool_spread`` (H_pool, H_spread); new ones come last."""
        if not self.config.use_neighbours:
            return 0
        return 2 if self.config.pool_spread else 1

    @property
    def tile_alignment(self) -> int:
        """Tile offsets that are multiples of this keep the padding / pooling grids aligned."""
        align = FLOW_STRIDE if self.flow is not None else 1
        if self.uformer is not None:
            align = math.lcm(align, self.config.uformer.size_multiple)
        return align

    def neighbour_source(self, features: Tensor, depth: Tensor) -> Tensor:
        """``(N, F, Hs, Ws)``, ``(N, 1, Hs, Ws)`` -> ``(N, F + 2, Hs, Ws)`` sampling sources for
        :attr:`NeighbourBatch.sources` (see :func:`~roguenerf.reprojection.sampling_source`)."""
        return sampling_source(features, depth)

    def encode_neighbours(self, photos: Tensor) -> Tensor:
        """conv_H: ``(N, 3, H, W)`` photos in [0,1] -> ``(N, F, H, W)``. Independent of the target."""
        _check(photos, "photos", (None, 3, None, None), image=True)
        if self.conv_H is None:
            raise InputError("encode_neighbours: this enhancer was built with use_neighbours=False "
                             "and has no neighbour encoder")
        return self.conv_H(photos)

    def depth_scale(self, depth: Tensor) -> Tensor:
        """``(B, 1, H, W)`` target depth -> ``(B,)`` scene scale s (median known depth, 1 if none)."""
        return median_depth(depth)

    def forward(self, render: Tensor, depth: Tensor, K: Tensor, world_from_cam: Tensor,
                neighbours: NeighbourBatch | None, *, depth_scale: Tensor | None = None) -> Tensor:
        """Enhance renders.

        Args:
            render: ``(B, 3, H, W)`` float in [0, 1]; depth ``(B, 1, H, W)`` z-depth (unknown where
            :func:`~roguenerf.geometry.depth.known_depth_mask` is False); K ``(B, 3, 3)``;
            world_from_cam ``(B, 4, 4)`` OpenCV (float64 keeps far-from-origin scenes exact);
            neighbours or None.
            depth_scale: ``(B,)`` scene scale s used to normalise depths and camera positions;
                default :meth:`depth_scale` of ``depth``. Tiling passes the whole image's scale
                so every tile is normalised alike.
        Returns:
            ``(B, 3, H, W)`` = render + Uformer(...) (global residual), any H x W.
        """
        _check(render, "render", (None, 3, None, None), image=True)
        b, _, h, w = render.shape
        _check(depth, "depth", (b, 1, h, w))
        with stage("encoders"):
            feats = self.conv_I(render)
        if self.conv_H is None:
            with stage("merge"):
                merged = conv_act(self.conv_merge, feats)
        else:
            pooled = None
            if neighbours is not None and len(neighbours) > 0:
                pooled = self._fuse(feats, depth, K, world_from_cam, neighbours, depth_scale)
            with stage("merge"):
                if pooled is None:
                    pooled = [torch.zeros_like(feats)] * self.pooled_maps
                parts = [feats, *pooled]
                # channels-last also in training: its convolutions are faster
                merged = conv_act(self.conv_merge, ops.cat_channels(parts, like=feats))
        with stage("uformer"):
            residual = self.uformer(merged) if self.uformer is not None else self.to_rgb(merged)
        return render + residual

    def _fuse(self, feats: Tensor, depth: Tensor, K: Tensor, world_from_cam: Tensor,
              nbrs: NeighbourBatch, depth_scale: Tensor | None) -> list[Tensor]:
        """Align, refine, weigh and max-pool the neighbours: ``[H_pool]``, or with ``pool_spread``
        ``[H_pool, H_spread]``, each ``(B, F, H, W)``."""
        K, world_from_cam, nbrs = self._checked_cameras(feats, K, world_from_cam, nbrs)
        b = feats.shape[0]
        scale = self.depth_scale(depth) if depth_scale is None else depth_scale.to(feats)
        if scale.shape != (b,) or not bool(known_depth_mask(scale).all()):
            raise InputError(f"depth_scale: expected ({b},) known depths (finite, in "
                             f"({DEPTH_EPS:g}, {MAX_DEPTH:g})), got {scale}")
        # Divide (never multiply by 1 / s): depth / s of known depths is finite, and the clamp
        # bounds it; 0 * (1 / s) could meet an overflowed reciprocal and give NaN.
        scale_b = scale[:, None, None, None]
        target_depth = (known_depth(depth) / scale_b).clamp(0, MAX_RELATIVE_DEPTH)
        camera_inputs = None
        if self.camera_attention is not None:
            camera_inputs = self._camera_inputs(world_from_cam, nbrs.world_from_cam, scale).to(feats.dtype)

        # Fast path (no gradient): work that depends only on the target is done once, every
        # full-resolution map is channels-last, and the pooling is in place. Same result.
        body = ops.pick(feats)
        fast = body.fast
        target_low = attention_term = None
        if fast and self.flow is not None:
            with stage("flow"):
                target_low = self.flow.encode_target(feats)
        if fast and self.pixel_attention is not None:
            with stage("attention"):
                attention_term = self.pixel_attention.target_term(feats, target_depth)

        if fast:
            return self._fuse_fast(feats, depth, K, world_from_cam, nbrs, scale_b, camera_inputs,
                                   target_low, attention_term)
        if body is ops.Body.TORCH and torch.is_grad_enabled():
            return self._fuse_batched(feats, depth, K, world_from_cam, nbrs, scale_b, target_depth, camera_inputs)
        return self._fuse_loop(feats, depth, K, world_from_cam, nbrs, scale_b, target_depth, camera_inputs)

    @staticmethod
    def _checked_cameras(feats: Tensor, K: Tensor, world_from_cam: Tensor,
                         nbrs: NeighbourBatch) -> tuple[Tensor, Tensor, NeighbourBatch]:
        """The neighbours' shapes checked, and the target's and neighbours' intrinsics and poses
        checked once for all (not again per neighbour in reproject, which would check the
        target's N times; check_pose may re-orthonormalise): ``K`` ``(B, 3, 3)``,
        ``world_from_cam`` ``(B, 4, 4)`` and the neighbours with checked ``K`` and poses."""
        b, f = feats.shape[:2]
        n = len(nbrs)
        if nbrs.sources is not None:
            for j, source in enumerate(nbrs.sources):
                _check(source, f"neighbours.sources[{j}]", (b, f + 2, None, None))
        else:
            _check(nbrs.features, "neighbours.features", (b, n, f, None, None))
            _check(nbrs.depth, "neighbours.depth", (b, n, 1, *nbrs.features.shape[-2:]))
        _check(nbrs.K, "neighbours.K", (b, n, 3, 3))
        _check(nbrs.world_from_cam, "neighbours.world_from_cam", (b, n, 4, 4))
        K = K.expand(b, 3, 3) if K.ndim == 2 else _check(K, "K", (b, 3, 3))
        world_from_cam = (world_from_cam.expand(b, 4, 4) if world_from_cam.ndim == 2
                          else _check(world_from_cam, "world_from_cam", (b, 4, 4)))
        K, nb_K = check_intrinsics(K, "K"), check_intrinsics(nbrs.K, "neighbours.K")
        world_from_cam = check_pose(world_from_cam, "world_from_cam")
        nb_poses = check_pose(nbrs.world_from_cam, "neighbours.world_from_cam")
        if nb_K is not nbrs.K or nb_poses is not nbrs.world_from_cam:
            nbrs = dataclasses.replace(nbrs, K=nb_K, world_from_cam=nb_poses)
        return K, world_from_cam, nbrs

    def _fuse_loop(self, feats: Tensor, depth: Tensor, K: Tensor, world_from_cam: Tensor,
                   nbrs: NeighbourBatch, scale_b: Tensor, target_depth: Tensor,
                   camera_inputs: Tensor | None) -> list[Tensor]:
        """:meth:`_fuse` one neighbour at a time, as the paper writes it (the reference, and
        without gradient off the fast path)."""
        _, f, h, w = feats.shape
        pooled = low = None
        spread = self.config.pool_spread
        for j in range(len(nbrs)):
            src, src_depth = nbrs.feature_map(j), nbrs.depth_map(j)
            source = nbrs.sources[j] if nbrs.sources is not None else None
            with stage("reprojection"):
                aligned, nb_depth, _ = self._align(src, src_depth, depth, nbrs.K[:, j], K,
                                                   nbrs.world_from_cam[:, j], world_from_cam, (h, w), source)
            if self.flow is not None:
                with stage("flow"):
                    flow = self.flow(aligned, feats)
                    warped = flow_warp(torch.cat([aligned, nb_depth], dim=1), flow)
                    aligned, nb_depth = warped[:, :f], warped[:, f:]
            if self.pixel_attention is not None:
                with stage("attention"):
                    nb_rel = (nb_depth / scale_b).clamp(0, MAX_RELATIVE_DEPTH)
                    psi_pix = self.pixel_attention(aligned, feats, nb_rel, target_depth)
                    psi_cam = self.camera_attention(camera_inputs[:, j])[:, :, None, None]
                    aligned = psi_cam * psi_pix * aligned
            with stage("fusion"):
                pooled = aligned if pooled is None else torch.maximum(pooled, aligned)
                if spread:
                    low = aligned if low is None else torch.minimum(low, aligned)
        with stage("fusion"):
            return [pooled, pooled - low] if spread else [pooled]

    def _fuse_batched(self, feats: Tensor, depth: Tensor, K: Tensor, world_from_cam: Tensor,
                      nbrs: NeighbourBatch, scale_b: Tensor, target_depth: Tensor,
                      camera_inputs: Tensor | None) -> Tensor:
        """:meth:`_fuse` for training (gradient recorded), same function and gradients: after
        the per-neighbour reprojection, the N neighbours of the B targets go through the flow
        refinement, the warp and the attention as one batch of N * B (neighbour-major), and the
        work that depends only on the target is done once: the flow network's target encoding
        (:meth:`FlowRefiner.forward` with a batch of N * B neighbours) and the target half of
        the pixel attention's first convolution (:meth:`PixelAttention.target_term`, shared
        by :meth:`PixelAttention.from_target_term`). The max-pool is the same chain of
        ``torch.maximum`` as the per-neighbour loop, so ties split their gradient alike.
        Memory grows with N (autograd keeps every neighbour's activations in either path)."""
        b, f, h, w = feats.shape
        n = len(nbrs)
        aligned, nb_depth = [], []
        for j in range(n):
            with stage("reprojection"):
                source = nbrs.sources[j] if nbrs.sources is not None else None
                a, d, _ = self._align(nbrs.feature_map(j), nbrs.depth_map(j), depth, nbrs.K[:, j], K,
                                      nbrs.world_from_cam[:, j], world_from_cam, (h, w), source)
                aligned.append(a)
                nb_depth.append(d)
        with stage("reprojection"):
            buf = torch.cat([torch.cat(aligned, dim=0), torch.cat(nb_depth, dim=0)], dim=1)  # (N*B, F+1, H, W)
        if self.flow is not None:
            with stage("flow"):
                buf = flow_warp(buf, self.flow(buf, feats))
        aligned = buf[:, :f]
        if self.pixel_attention is not None:
            with stage("attention"):
                nb_rel = (buf[:, f:].view(n, b, 1, h, w) / scale_b).clamp(0, MAX_RELATIVE_DEPTH)
                term = self.pixel_attention.target_term(feats, target_depth)
                parts = [aligned, nb_rel.view(n * b, 1, h, w)]
                psi_pix = self.pixel_attention.from_target_term(
                    ops.cat_channels(parts, like=feats), term)
                psi_cam = self.camera_attention(camera_inputs.transpose(0, 1).reshape(n * b, -1))
                aligned = psi_cam[:, :, None, None] * psi_pix * aligned
        with stage("fusion"):
            # unbind, not per[j]: one backward node that stacks the N gradients, where N
            # selects would each fill a zero tensor of all N * B neighbours and add them up.
            per = aligned.view(n, b, f, h, w).unbind(0)
            pooled = low = per[0]
            for j in range(1, n):
                pooled = torch.maximum(pooled, per[j])
                if self.config.pool_spread:
                    low = torch.minimum(low, per[j])
            return [pooled, pooled - low] if self.config.pool_spread else [pooled]

    def _fuse_fast(self, feats: Tensor, depth: Tensor, K: Tensor, world_from_cam: Tensor,
                   nbrs: NeighbourBatch, scale_b: Tensor, camera_inputs: Tensor | None,
                   target_low: Tensor | None, attention_term: Tensor | None) -> Tensor:
        """:meth:`_fuse` without gradient, same result: each neighbour's [H, D, ...] lives in one
        channels-last buffer that every stage reads whole and writes in place (no per-neighbour
        concatenation), and the 1/8-resolution flow network runs on all neighbours as one batch."""
        b, f, h, w = feats.shape
        n = len(nbrs)
        packed = []
        for j in range(n):
            with stage("reprojection"):
                source = nbrs.sources[j] if nbrs.sources is not None else None
                aligned, nb_depth, buf = self._align(nbrs.feature_map(j), nbrs.depth_map(j), depth, nbrs.K[:, j],
                                                     K, nbrs.world_from_cam[:, j], world_from_cam, (h, w), source)
                packed.append(buf if buf is not None else cat_channels_last([aligned, nb_depth]))
        flows = None
        if self.flow is not None:
            with stage("flow"):  # at 1/8 size: upsample_warp upsamples them
                flows = self.flow.batched(packed, target_low, h, w, upsample=False)
        pooled = low = None
        spread = self.config.pool_spread
        attend = self.pixel_attention is not None
        for j in range(n):
            buf = packed[j]
            packed[j] = None  # release each buffer as soon as it is used
            normalised = False
            if flows is not None:
                with stage("flow"):  # (the C kernel also normalises the depth channel)
                    buf, normalised = ops.upsample_warp(
                        buf, flows[j], depth_scale=scale_b.flatten() if attend else None, depth_channel=f,
                        depth_max=MAX_RELATIVE_DEPTH)
            if attend:
                with stage("attention"):
                    if not normalised:
                        buf[:, f:f + 1] = (buf[:, f:f + 1] / scale_b).clamp(0, MAX_RELATIVE_DEPTH)
                    camera = self.camera_attention(camera_inputs[:, j])
                pooled, low = ops.attend_pool(self.pixel_attention, buf, attention_term, camera, f, pooled, low,
                                              spread=spread)  # its own stages: attention, fusion
            else:
                with stage("fusion"):
                    pooled, low = ops.pool_neighbours(buf[:, :f], pooled, low, spread)
        if spread:
            with stage("fusion"):
                low = torch.sub(pooled, low, out=low)  # H_spread, written over the running min
            return [pooled, low]
        return [pooled]

    def _align(self, src: Tensor, src_depth: Tensor, depth: Tensor, src_K: Tensor, K: Tensor,
               world_from_src: Tensor, world_from_cam: Tensor, size: tuple[int, int],
               source: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor | None]:
        """One neighbour's features and depth in the target view: ``(B, F, H, W)``, ``(B, 1, H, W)``,
        and on the fast path the buffer they are views of (else None)."""
        if self.config.use_alignment:
            rp = reproject(src, src_depth, depth, src_K, K, world_from_src, world_from_cam,
                           leniency=self.config.leniency, source=source, validated=True)
            return rp.features, rp.depth, rp.packed
        aligned = F.interpolate(src, size=size, mode="bilinear", align_corners=False)
        nb_depth = F.interpolate(known_depth(src_depth), size=size, mode="bilinear", align_corners=False)
        return aligned, nb_depth, None

    @staticmethod
    def _camera_inputs(target: Tensor, neighbours: Tensor, scale: Tensor) -> Tensor:
        """``(B, 4, 4)``, ``(B, N, 4, 4)``, ``(B,)`` -> ``(B, N, 9)``: [euler(R_i), euler(R_k), (t_i - t_k) / s]."""
        n = neighbours.shape[1]
        euler_i = euler_angles(neighbours[..., :3, :3])
        euler_k = euler_angles(target[:, None, :3, :3]).expand(-1, n, -1)
        # float64: both positions may be 1e4 units from the origin while 1e-3 apart.
        rel = (neighbours[..., :3, 3].double() - target[:, None, :3, 3].double()) / scale.double()[:, None, None]
        rel = rel.clamp(-MAX_RELATIVE_DEPTH, MAX_RELATIVE_DEPTH).to(euler_i.dtype)
        return torch.cat([euler_i, euler_k, rel], dim=-1)


def build_enhancer(variant: str | EnhancerConfig = "nano", **overrides):
    """Build an :class:`~roguenerf.models.enhancer.Enhancer` from a variant name or config."""
    if isinstance(variant, EnhancerConfig):
        config = variant
        if overrides:
            d = config.to_dict()
            sub = {k: overrides.pop(k) for k in list(overrides) if k in _UFORMER_KEYS}
            d["uformer"].update(sub)
            d["uformer"].update(overrides.pop("uformer", None) or {})
            d.update(overrides)
            config = EnhancerConfig.from_dict(d)
    elif isinstance(variant, str):
        config = make_config(variant, **overrides)
    else:
        raise InputError(f"variant: expected a variant name or EnhancerConfig, got {type(variant).__name__}")
    return Enhancer(config)

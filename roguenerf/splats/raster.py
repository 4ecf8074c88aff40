"""A tile-based, differentiable 3D Gaussian splatting rasterizer in plain PyTorch (CPU or any device).

What it computes (the 3DGS image formation, Kerbl et al. 2023, as Inria's CUDA code does):

1. **Projection.** World covariances ``Σ = R S Sᵀ Rᵀ`` (quaternion ``R``, ``S = diag(exp(log_scales))``)
   are taken to the camera (``W = R_cwᵀ``) and projected with the pinhole's Jacobian at the centre
   (EWA splatting; the centre's ``x/z``, ``y/z`` clamped to 1.3 × the field of view as 3DGS and
   gsplat do: ``0.3 tan(fov/2)`` past each edge, ``tan(fov_x/2) = W / (2 fx)``):
   ``Σ' = J W Σ Wᵀ Jᵀ + 0.3 I`` (the 0.3 px² low-pass), formed in float64 with its determinant
   as a sum of squares (Cauchy-Binet), so a huge or long thin Gaussian keeps its footprint (scales
   above ``e^80`` count as ``e^80``: flat across any view). Centres with camera ``z <= near`` are
   culled. Colour is the SH seen from the camera centre, ``max(SH + 0.5, 0)``.
2. **Footprint.** A Gaussian reaches a pixel (centre at ``(u + 0.5, v + 0.5)``) when the pixel lies
   inside its 3σ ellipse (``dᵀ Σ'⁻¹ d <= 9``) and ``α = min(0.99, o · exp(-½ dᵀ Σ'⁻¹ d)) >= 1/255``.
   Every such pixel lies in the ellipse's bounding box, so binning Gaussians into tiles by that
   box loses nothing: the result does not depend on the tile size.
3. **Compositing.** Per pixel, front to back in the order of the centres' camera z:
   ``w_i = α_i T_i``, ``T_{i+1} = T_i (1 - α_i)``; the Gaussian that would bring ``T`` below
   1e-4 and all behind it are dropped (Inria's early stop). ``rgb = Σ w_i c_i + T · background``,
   ``opacity = Σ w_i``, ``depth = Σ w_i z_i / Σ w_i`` where ``opacity >= depth_threshold``, else
   0 (unknown depth, :mod:`roguenerf.geometry.depth`).

Work and memory: Gaussians are binned into square tiles (``tile`` px) by that box. Per tile they
are taken front to back in groups (``group`` Gaussians, ``chunk`` candidate pairs at most): the
candidate (pixel, Gaussian) pairs inside each box are tested, only those the rule keeps are
sorted (pixel, then depth) and composited, the transmittance a float64 running sum of
``log(1 - α)`` carried from group to group; a tile whose pixels are all below 1e-4 stops. So the
cost follows the splats' real footprints up to saturation, and memory one group's pairs.
Everything is differentiable (autograd) for fitting.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from roguenerf.errors import InputError
from roguenerf.geometry.cameras import as_world_from_cam
from roguenerf.splats.gaussians import Gaussians, quat_to_rotmat
from roguenerf.splats.sh import eval_sh

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
LOG_T_MIN = math.log(T_MIN)
LOW_PASS = 0.3
SIGMA_CUT = 3.0
FOV_MARGIN = 0.3
"""Off-screen centres: ``x/z`` clamped ``0.3 tan(fov_x/2)`` past the image's edges (1.3 × the field of view)."""
LOG_SCALE_MAX = 80.0
"""Scales above ``e^80`` are taken as ``e^80`` in the projection: already flat across any view (conic ~ 0)."""
EXTENT_MAX = 1e20
DEFAULT_DEPTH_THRESHOLD = 0.5
"""Expected depth is reported where the splats cover at least this share of the pixel."""


@dataclass
class Projected:
    """Gaussians projected into one camera (all ``(N, ...)``; rows with ``visible`` False are unused)."""

    means2d: Tensor
    """``(N, 2)`` pixel coordinates ``(u, v)`` of the centres (pixel-centre convention)."""
    conics: Tensor
    """``(N, 3)`` the inverse 2D covariance ``(a, b, c)``: ``dᵀ Σ'⁻¹ d = a dx² + 2 b dx dy + c dy²``."""
    depths: Tensor
    """``(N,)`` camera z of the centres."""
    opacities: Tensor
    """``(N,)`` in (0, 1)."""
    colours: Tensor
    """``(N, 3)``."""
    extents: Tensor
    """``(N, 2)`` half width and height (px) of the box around the footprint."""
    visible: Tensor
    """``(N,)`` bool: in front of the near plane, with a footprint on the image."""
    cov2d: Tensor
    """``(N, 3)`` the 2D covariance ``(Σ'xx, Σ'xy, Σ'yy)`` with the low-pass."""


def _check_camera(world_from_cam: Tensor, K: Tensor, height: int, width: int, near: float) -> tuple[Tensor, Tensor]:
    world_from_cam = torch.as_tensor(world_from_cam)
    K = torch.as_tensor(K)
    if world_from_cam.shape not in ((4, 4), (3, 4)):
        raise InputError(f"world_from_cam: expected shape (4, 4) or (3, 4), got {tuple(world_from_cam.shape)}")
    if K.shape != (3, 3):
        raise InputError(f"K: expected shape (3, 3), got {tuple(K.shape)}")
    if int(height) < 1 or int(width) < 1:
        raise InputError(f"height, width: expected >= 1, got {height}x{width}")
    if not torch.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(f"K: expected finite intrinsics with focal lengths > 0, got {K.tolist()}")
    # A reflection would mirror the image, a scaled rotation scale the depth: refused, as every entry does.
    world_from_cam = as_world_from_cam(world_from_cam)
    try:
        near_ok = math.isfinite(float(near)) and float(near) >= 0
    except (TypeError, ValueError):
        near_ok = False
    if not near_ok:
        raise InputError(f"near: expected a finite distance >= 0 (centres at camera z <= near are culled), "
                         f"got {near!r}")
    return world_from_cam.to(torch.float64), K.to(torch.float64)


def _check_background(background) -> Tensor:
    try:
        bg = torch.as_tensor(background).reshape(-1)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise InputError(f"background: expected 3 finite values (RGB), got {background!r} ({exc})") from None
    if bg.numel() != 3 or bg.dtype == torch.bool or bg.is_complex() or not torch.isfinite(bg.detach()).all():
        raise InputError(f"background: expected 3 finite values (RGB), got {bg.detach().tolist()}")
    return bg


def project(gaussians: Gaussians, world_from_cam: Tensor, K: Tensor, height: int, width: int, *,
            near: float = 0.01, sh_degree: int | None = None) -> Projected:
    """Project ``gaussians`` into the OpenCV camera ``world_from_cam`` ``(4, 4)`` with intrinsics ``K``."""
    world_from_cam, K = _check_camera(world_from_cam, K, height, width, near)
    g = gaussians
    g.check_finite("gaussians")
    dtype = g.means.dtype
    rot = world_from_cam[:3, :3]
    origin = world_from_cam[:3, 3]
    # Camera coordinates in float64 first (scenes far from the origin), then the working dtype.
    cam64 = (g.means.to(torch.float64) - origin.to(g.means.device)) @ rot.to(g.means.device)
    cam = cam64.to(dtype)
    x, y, z = cam.unbind(-1)
    fx, fy, cx, cy = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    in_front = z > near
    zs = torch.where(in_front, z, torch.ones_like(z))
    # 3DGS and gsplat: the centre's x/z, y/z clamped 0.3 tan(fov/2) past the image's edges
    # (1.3 tan(fov/2) with a centred principal point), tan(fov_x/2) = W / (2 fx).
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    lim_x_pos, lim_x_neg = (width - cx) / fx + FOV_MARGIN * tan_fovx, cx / fx + FOV_MARGIN * tan_fovx
    lim_y_pos, lim_y_neg = (height - cy) / fy + FOV_MARGIN * tan_fovy, cy / fy + FOV_MARGIN * tan_fovy
    lim_x_pos, lim_x_neg = max(lim_x_pos, 0.0), max(lim_x_neg, 0.0)
    lim_y_pos, lim_y_neg = max(lim_y_pos, 0.0), max(lim_y_neg, 0.0)
    # The 2D covariance in float64, its determinant without cancellation (below): a Gaussian
    # e^50 wide (or a long thin one) keeps its footprint instead of overflowing float32.
    x64, y64, z64 = cam64.unbind(-1)
    zs64 = torch.where(in_front, z64, torch.ones_like(z64))
    tx = zs64 * (x64 / zs64).clamp(-lim_x_neg, lim_x_pos)
    ty = zs64 * (y64 / zs64).clamp(-lim_y_neg, lim_y_pos)
    zero = torch.zeros_like(zs64)
    J = torch.stack([fx / zs64, zero, -fx * tx / (zs64 * zs64), zero, fy / zs64, -fy * ty / (zs64 * zs64)],
                    -1).reshape(-1, 2, 3)
    R = quat_to_rotmat(g.quats.to(torch.float64))
    W = rot.T.to(device=g.means.device)  # camera_from_world rotation
    A = J @ (W @ R)  # (N, 2, 3): Σ' = A S² Aᵀ + 0.3 I
    scales = torch.exp(g.log_scales.to(torch.float64).clamp(max=LOG_SCALE_MAX))
    T = A * scales[:, None, :]
    cov = T @ T.transpose(1, 2)
    cxx = cov[:, 0, 0] + LOW_PASS
    cxy = cov[:, 0, 1]
    cyy = cov[:, 1, 1] + LOW_PASS
    # det(T Tᵀ + c I) = det(T Tᵀ) + c tr(T Tᵀ) + c², det(T Tᵀ) the sum of the squared 2x2 minors
    # of T (Cauchy-Binet), each s_i s_j times a minor of A: every term >= 0, no cancellation.
    minors = torch.stack([A[:, 0, i] * A[:, 1, j] - A[:, 0, j] * A[:, 1, i] for i, j in ((0, 1), (0, 2), (1, 2))],
                         -1)
    pairs = torch.stack([scales[:, 0] * scales[:, 1], scales[:, 0] * scales[:, 2], scales[:, 1] * scales[:, 2]], -1)
    det = ((minors * pairs) ** 2).sum(-1) + LOW_PASS * (cov[:, 0, 0] + cov[:, 1, 1]) + LOW_PASS * LOW_PASS
    ok = in_front & (det > 0)
    det_safe = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([cyy / det_safe, -cxy / det_safe, cxx / det_safe], -1).to(dtype)
    means2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], -1)
    opac = torch.sigmoid(g.opacity)
    # Beyond this many σ, α < 1/255 (so no pixel there is drawn): the box may shrink to it.
    reach = torch.sqrt(torch.clamp(2 * torch.log(torch.clamp(opac.detach() * 255.0, min=1.0)), min=0.0))
    reach = torch.clamp(reach, max=SIGMA_CUT)
    ok = ok & (opac.detach() >= ALPHA_MIN)
    ext = torch.stack([reach * torch.sqrt(cxx.detach().clamp_min(0)),
                       reach * torch.sqrt(cyy.detach().clamp_min(0))], -1).clamp(max=EXTENT_MAX).to(dtype)
    m2 = means2d.detach()
    on_image = (m2[:, 0] + ext[:, 0] > 0) & (m2[:, 0] - ext[:, 0] < width) & \
               (m2[:, 1] + ext[:, 1] > 0) & (m2[:, 1] - ext[:, 1] < height)
    visible = ok & on_image & torch.isfinite(m2).all(-1)
    dirs = g.means - origin.to(dtype=dtype, device=g.means.device)
    colours = eval_sh(g.sh, dirs, sh_degree)
    return Projected(means2d=means2d, conics=conics, depths=z, opacities=opac, colours=colours,
                     extents=ext, visible=visible,
                     cov2d=torch.stack([cxx, cxy, cyy], -1).clamp(max=torch.finfo(dtype).max).to(dtype))


def _bin(proj: Projected, height: int, width: int, tile: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(visible index, per-pair Gaussian (into the visible list), per-tile start, per-tile count)."""
    vis = torch.nonzero(proj.visible).squeeze(1)
    tiles_x, tiles_y = math.ceil(width / tile), math.ceil(height / tile)
    n_tiles = tiles_x * tiles_y
    device = proj.means2d.device
    if vis.numel() == 0:
        empty = torch.zeros(0, dtype=torch.long, device=device)
        return vis, empty, torch.zeros(n_tiles, dtype=torch.long, device=device), \
            torch.zeros(n_tiles, dtype=torch.long, device=device)
    m = proj.means2d.detach()[vis].to(torch.float64)
    e = proj.extents[vis].to(torch.float64) + 1e-3  # conservative: a pixel on the box's edge is kept
    # Pixel j's centre is j + 0.5; it lies in the box when m - e <= j + 0.5 <= m + e.
    x0 = torch.floor((m[:, 0] - e[:, 0] - 0.5) / tile).clamp(0, tiles_x - 1).long()
    x1 = torch.floor((m[:, 0] + e[:, 0] - 0.5) / tile).clamp(0, tiles_x - 1).long()
    y0 = torch.floor((m[:, 1] - e[:, 1] - 0.5) / tile).clamp(0, tiles_y - 1).long()
    y1 = torch.floor((m[:, 1] + e[:, 1] - 0.5) / tile).clamp(0, tiles_y - 1).long()
    wx, wy = x1 - x0 + 1, y1 - y0 + 1
    counts = wx * wy
    order = torch.argsort(proj.depths.detach()[vis], stable=True)
    rank = torch.empty_like(order)
    rank[order] = torch.arange(order.numel(), device=device)
    gid = torch.repeat_interleave(torch.arange(vis.numel(), device=device), counts)
    first = torch.cumsum(counts, 0) - counts
    local = torch.arange(gid.numel(), device=device) - first[gid]
    tile_id = (y0[gid] + local // wx[gid]) * tiles_x + x0[gid] + local % wx[gid]
    key = tile_id * vis.numel() + rank[gid]
    sort = torch.argsort(key)
    pair_gid = gid[sort]
    per_tile = torch.bincount(tile_id, minlength=n_tiles)
    start = torch.cumsum(per_tile, 0) - per_tile
    return vis, pair_gid, start, per_tile


def _footprint(f: Tensor, px: Tensor, py: Tensor) -> tuple[Tensor, Tensor]:
    """α of rows ``f`` (u, v, a, b, c, opacity, ...) at integer pixels ``(px, py)``, and where it counts."""
    dx = (px.to(f.dtype) + 0.5) - f[:, 0]
    dy = (py.to(f.dtype) + 0.5) - f[:, 1]
    maha = f[:, 2] * dx * dx + 2 * f[:, 3] * dx * dy + f[:, 4] * dy * dy
    alpha = (f[:, 5] * torch.exp(-0.5 * maha)).clamp(max=ALPHA_MAX)
    return alpha, (maha <= SIGMA_CUT * SIGMA_CUT) & (alpha >= ALPHA_MIN)


def _render_tile(feat: Tensor, gids: Tensor, ext: Tensor, x0: int, y0: int, tile: int,
                 chunk: int, group: int, width: int, height: int) -> Tensor:
    """One tile: ``(tile², 5)`` = rgb, Σ w z, Σ w per pixel. ``gids`` (into ``feat``) are in depth order.

    The Gaussians are taken front to back in groups (at most ``group`` of them and ``chunk``
    candidate pairs); each group's pairs inside the boxes are tested, the kept ones sorted by
    (pixel, depth) and composited onto the transmittance the earlier groups left (a float64 log,
    per pixel); once every pixel of the tile is below 1e-4 the rest cannot count and is skipped.
    The candidates are tested on a detached copy of the tile's rows (one gather per group), and
    only the kept pairs are gathered from ``feat`` with autograd: the cost follows the kept pairs.
    """
    dtype, tp = feat.dtype, tile * tile
    rows = feat.detach()[gids, :6].contiguous()  # u, v, a, b, c, opacity of the tile's Gaussians
    m = rows[:, :2].to(torch.float64)
    e = ext[gids].to(torch.float64)
    # Pixel j's centre is j + 0.5: the box [m - e, m + e] holds centres j in [ceil(m-e-0.5), floor(m+e-0.5)].
    xl = torch.ceil(m[:, 0] - e[:, 0] - 0.5 - 1e-6).clamp(min=x0).long()
    xh = torch.floor(m[:, 0] + e[:, 0] - 0.5 + 1e-6).clamp(max=min(x0 + tile, width) - 1).long()
    yl = torch.ceil(m[:, 1] - e[:, 1] - 0.5 - 1e-6).clamp(min=y0).long()
    yh = torch.floor(m[:, 1] + e[:, 1] - 0.5 + 1e-6).clamp(max=min(y0 + tile, height) - 1).long()
    w, h = (xh - xl + 1).clamp_min(0), (yh - yl + 1).clamp_min(0)
    n = w * h
    ends = torch.cumsum(n, 0)
    first = ends - n  # where each Gaussian's candidates start
    inside = ((torch.arange(tp) // tile + y0) < height) & ((torch.arange(tp) % tile + x0) < width)
    out = torch.zeros(tp, 5, dtype=dtype)
    log_t = torch.zeros(tp, dtype=torch.float64)  # transmittance left by the groups so far
    g0, total = 0, gids.numel()
    while g0 < total:
        base = int(ends[g0 - 1]) if g0 else 0
        g1 = min(max(g0 + 1, int(torch.searchsorted(ends, base + chunk, right=True))), g0 + group, total)
        counts = n[g0:g1]
        local = torch.repeat_interleave(torch.arange(g0, g1), counts)
        k = torch.arange(base, base + local.numel()) - first[local]
        wl = w[local]
        q = torch.div(k, wl, rounding_mode="floor")
        px, py = xl[local] + (k - q * wl), yl[local] + q
        keep = _footprint(rows[local], px, py)[1]
        local, pix = local[keep], (py[keep] - y0) * tile + (px[keep] - x0)
        g0 = g1
        if local.numel() == 0:
            continue
        # The pairs are in depth order (``gids`` is): a stable sort by pixel keeps it within a pixel.
        order = torch.argsort(pix, stable=True)
        gid, pix = gids[local[order]], pix[order]
        f = feat[gid]
        alpha, _ = _footprint(f, pix % tile + x0, pix // tile + y0)
        alpha64 = alpha.to(torch.float64)
        # Transmittance before each pair: what earlier groups left times the product of (1 - α)
        # over the pixel's earlier pairs in this group (a running sum of logs over the group,
        # minus its value where the pixel's run starts).
        la = torch.log1p(-alpha64)
        excl = torch.cumsum(la, 0) - la
        runs = torch.bincount(pix, minlength=tp)
        starts = torch.cumsum(runs, 0) - runs
        before = torch.exp(log_t[pix] + excl - excl[starts[pix]])
        after = before * (1.0 - alpha64)
        wgt = torch.where(after >= T_MIN, alpha64 * before, torch.zeros_like(before)).to(dtype)
        vals = torch.cat([wgt[:, None] * f[:, 7:10], (wgt * f[:, 6])[:, None], wgt[:, None]], dim=1)
        out = out.index_add(0, pix, vals)
        log_t = log_t.index_add(0, pix, la)
        if float(log_t.detach()[inside].max()) < LOG_T_MIN:
            break
    return out


def render(gaussians: Gaussians, world_from_cam: Tensor, K: Tensor, height: int, width: int, *,
           background: Tensor | tuple[float, float, float] | None = None, near: float = 0.01,
           sh_degree: int | None = None, depth_threshold: float = DEFAULT_DEPTH_THRESHOLD, tile: int = 32,
           chunk: int = 1 << 22, group: int = 1024, progress: bool | Callable[[int, int], None] = False,
           return_info: bool = False):
    """Render ``gaussians`` from an OpenCV camera.

    Args:
        world_from_cam: ``(4, 4)`` (or ``(3, 4)``) OpenCV camera-to-world.
        K: ``(3, 3)`` intrinsics, pixel-centre convention.
        background: RGB behind the splats (default black).
        near: centres with camera z at most this are culled.
        sh_degree: SH degree to evaluate (default: all the Gaussians hold).
        depth_threshold: depth is reported where opacity >= this, else 0 (unknown).
        tile, chunk, group: tile side (px); a tile's Gaussians are composited front to back in
            groups of at most ``group`` Gaussians and ``chunk`` candidate (pixel, Gaussian) pairs
            (memory bound); a tile stops once all its pixels are saturated.
        progress: True for a tqdm bar over the tiles, or ``callback(done, total)``.
        return_info: also return a dict with ``means2d`` (``(N, 2)``, its gradient retained when
            it needs one: the view-space gradient that densification reads), ``visible``,
            ``extents`` and ``projected``.
    Returns:
        ``rgb`` ``(3, H, W)``, ``depth`` ``(1, H, W)`` (z, 0 where unknown), ``opacity`` ``(1, H, W)``
        (and ``info`` when asked).
    Raises:
        InputError: a pose that is not a rigid camera-to-world matrix (a reflection would mirror
            the image, a scaled rotation scale the depth: checked as :func:`as_world_from_cam`),
            non-finite ``K`` or a focal length <= 0, splats holding NaN or inf, ``near`` not a
            finite distance >= 0, a ``background`` that is not 3 finite values.
    """
    if tile < 1 or chunk < 1 or group < 1:
        raise InputError(f"tile, chunk, group: expected >= 1, got {tile}, {chunk}, {group}")
    if not (0.0 <= depth_threshold <= 1.0):
        raise InputError(f"depth_threshold: expected a share in [0, 1], got {depth_threshold}")
    height, width = int(height), int(width)
    bg = None if background is None else _check_background(background)
    proj = project(gaussians, world_from_cam, K, height, width, near=near, sh_degree=sh_degree)
    if proj.means2d.requires_grad:
        proj.means2d.retain_grad()
    device, dtype = proj.means2d.device, proj.means2d.dtype
    if device.type != "cpu":
        raise InputError("render: the rasterizer runs on the CPU (gsplat renders on a GPU)")
    bg = torch.zeros(3, dtype=dtype) if bg is None else bg.to(dtype)
    vis, pair_gid, start, count = _bin(proj, height, width, tile)
    tiles_x, tiles_y = math.ceil(width / tile), math.ceil(height / tile)
    n_tiles, tp = tiles_x * tiles_y, tile * tile
    # Per visible Gaussian: u, v, a, b, c, opacity, z, r, g, b.
    feat = torch.cat([proj.means2d[vis], proj.conics[vis], proj.opacities[vis, None], proj.depths[vis, None],
                      proj.colours[vis]], dim=1)
    ext = proj.extents[vis]
    busy = torch.nonzero(count > 0).squeeze(1).tolist()
    bar = None
    if progress is True:
        from tqdm import tqdm

        bar = tqdm(total=len(busy), desc="rasterizing", unit="tile", leave=False, dynamic_ncols=True)
    outputs = []
    for n, t in enumerate(busy):
        y0, x0 = (t // tiles_x) * tile, (t % tiles_x) * tile
        gids = pair_gid[int(start[t]):int(start[t] + count[t])]
        outputs.append(_render_tile(feat, gids, ext, x0, y0, tile, chunk, group, width, height))
        if bar is not None:
            bar.update(1)
        elif callable(progress):
            progress(n + 1, len(busy))
    if bar is not None:
        bar.close()
    full = torch.zeros(n_tiles, tp, 5, dtype=dtype)
    if outputs:
        full = full.index_copy(0, torch.tensor(busy, dtype=torch.long), torch.stack(outputs))
    full = full.reshape(tiles_y, tiles_x, tile, tile, 5).permute(4, 0, 2, 1, 3)
    full = full.reshape(5, tiles_y * tile, tiles_x * tile)[:, :height, :width]
    opacity = full[4:5]
    rgb = full[:3] + (1.0 - opacity) * bg[:, None, None]
    covered = opacity >= max(depth_threshold, 1e-12)
    depth = torch.where(covered, full[3:4] / torch.where(covered, opacity, torch.ones_like(opacity)),
                        torch.zeros_like(opacity))
    if return_info:
        info = {"means2d": proj.means2d, "visible": proj.visible, "extents": proj.extents, "projected": proj}
        return rgb, depth, opacity, info
    return rgb, depth, opacity

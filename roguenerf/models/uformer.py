"""Uformer (Wang et al., CVPR 2022), the official architecture taking feature maps of any size.

Input projection (3x3 conv + leaky ReLU), 4 encoder stages of LeWin blocks each followed by a
4x4 stride-2 conv, a bottleneck stage, 4 decoder stages each preceded by a 2x2 stride-2
transposed conv whose output is concatenated with the encoder skip, and a 3x3 output
projection. A LeWin block is window self-attention with a learned relative position bias
(every second block on windows shifted by half a window) followed by LeFF (linear, depthwise
3x3 conv, linear; GELU). Changes from the official code: the input has ``in_channels``
(64 in RoGUENeRF) instead of RGB, the input is padded to a multiple of 16 x win_size and cropped
back (any H x W), the output projection is zero-initialised (the module starts as exactly 0,
so the enhancer starts as the identity), and the global residual is added by the caller.
Parameter counts equal the official T / S / B models' (5.23 M, 20.63 M, 50.88 M) for RGB input.

Dimension letters: B batch, H x W image (tokens) size, C channels, n heads, d head channels,
w window side, N windows, L = w * w tokens per window.
"""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import Tensor, nn

from roguenerf import ops
from roguenerf.models.config import UformerConfig
from roguenerf.models.layers import conv_act


def pad_to_multiple(x: Tensor, multiple: int) -> Tensor:
    """Pad ``(B, C, H, W)`` at the bottom/right by edge replication to a multiple of ``multiple``."""
    h, w = x.shape[-2:]
    ph, pw = -h % multiple, -w % multiple
    if ph or pw:
        x = F.pad(x, (0, pw, 0, ph), mode="replicate")
    return x


class DropPath(nn.Module):
    """Stochastic depth: zero whole residual branches per sample during training."""

    def __init__(self, p: float = 0.0):
        super().__init__()
        self.p = p

    def forward(self, x: Tensor) -> Tensor:
        if self.p == 0.0 or not self.training:
            return x
        keep = x.new_empty((x.shape[0],) + (1,) * (x.ndim - 1)).bernoulli_(1.0 - self.p)
        return x * keep / (1.0 - self.p)


class WindowAttention(nn.Module):
    """Multi-head self-attention inside windows with a relative position bias.

    ``(N*B, L, C) -> (N*B, L, C)``; ``mask`` ``(N, L, L)`` additive (0 or -100) or None.
    """

    def __init__(self, *, dim: int, heads: int, win_size: int, fused: bool = True):
        super().__init__()
        self.heads = heads
        self.win_size = win_size
        self.scale = (dim // heads) ** -0.5
        self.fused = fused
        self.relative_position_bias_table = nn.Parameter(torch.zeros((2 * win_size - 1) ** 2, heads))
        nn.init.trunc_normal_(self.relative_position_bias_table, std=0.02)
        coords = torch.stack(torch.meshgrid(torch.arange(win_size), torch.arange(win_size), indexing="ij"))
        coords = coords.flatten(1)
        rel = (coords[:, :, None] - coords[:, None, :]) + (win_size - 1)
        self.register_buffer("relative_position_index", rel[0] * (2 * win_size - 1) + rel[1], persistent=False)
        self.to_qkv = nn.Linear(dim, 3 * dim)
        self.to_out = nn.Linear(dim, dim)

    def bias(self) -> Tensor:
        """``(n, L, L)`` relative position bias."""
        b = self.relative_position_bias_table[self.relative_position_index]
        return rearrange(b, "i j n -> n i j")

    def forward(self, x: Tensor, mask: Tensor | None = None) -> Tensor:
        return ops.window_attention(self, x, mask)

    def _cached_bias(self, mask: Tensor | None) -> tuple[Tensor, Tensor | None, Tensor | None]:
        """``(n, L, L)`` bias; with a mask also the windows it touches ``(E,)`` and their bias + mask
        ``(E, n, L, L)``. Recomputed only when the bias table or the mask changes (no-grad use)."""
        table = self.relative_position_bias_table
        key = (table._version, table.data_ptr(), table.device)
        cached = getattr(self, "_bias_cache", None)
        # The cache holds the mask itself, so ``is`` cannot match a new mask at a reused address.
        if cached is None or cached[0] != key or cached[1] is not mask:
            bias = self.bias()
            edges = edge_bias = None
            if mask is not None:
                edges = (mask != 0).flatten(1).any(dim=1).nonzero().flatten()
                edge_bias = bias[None] + mask[edges][:, None]
            cached = (key, mask, (bias, edges, edge_bias))
            self._bias_cache = cached
        return cached[2]


class LeFF(nn.Module):
    """Locally-enhanced feed-forward: ``(B, H, W, C) -> (B, H, W, C)``."""

    def __init__(self, *, dim: int, hidden: int):
        super().__init__()
        self.linear1 = nn.Sequential(nn.Linear(dim, hidden), nn.GELU())
        self.dwconv = nn.Sequential(nn.Conv2d(hidden, hidden, 3, padding=1, groups=hidden), nn.GELU())
        self.linear2 = nn.Linear(hidden, dim)

    def forward(self, x: Tensor, residual: Tensor | None = None) -> Tensor:
        """``residual`` (fast path): returned as ``residual + leff(x)``, the sum fused into the
        last linear, or the whole block one fused kernel (:func:`roguenerf.ops.uformer.leff`)."""
        return ops.leff(self, x, residual)


def _shift_mask(h: int, w: int, win: int, shift: int, device) -> Tensor:
    """``(N, L, L)`` additive mask keeping attention inside regions that were contiguous before the roll.

    Cached per size (read-only: callers must not modify it); never an inference tensor.
    """
    with torch.inference_mode(False), torch.no_grad():
        return _make_shift_mask(h, w, win, shift, str(device))


@functools.lru_cache(maxsize=64)
def _make_shift_mask(h: int, w: int, win: int, shift: int, device: str) -> Tensor:
    region = torch.zeros(h, w, device=device)
    label = 0
    for hs in (slice(0, -win), slice(-win, -shift), slice(-shift, None)):
        for ws in (slice(0, -win), slice(-win, -shift), slice(-shift, None)):
            region[hs, ws] = label
            label += 1
    windows = rearrange(region, "(nh wh) (nw ww) -> (nh nw) (wh ww)", wh=win, ww=win)
    diff = windows[:, None, :] - windows[:, :, None]
    return torch.zeros_like(diff).masked_fill(diff != 0, -100.0)


class LeWinBlock(nn.Module):
    """LayerNorm -> (shifted) window attention -> residual; LayerNorm -> LeFF -> residual.

    ``(B, H, W, C) -> (B, H, W, C)``; H and W must be multiples of ``win_size``.
    """

    def __init__(self, *, dim: int, heads: int, win_size: int, shift: bool, mlp_ratio: float,
                 drop_path: float = 0.0, modulator: bool = False):
        super().__init__()
        self.win_size = win_size
        self.shift = shift
        self.modulator = nn.Embedding(win_size * win_size, dim) if modulator else None
        self.norm1 = nn.LayerNorm(dim)
        self.attn = WindowAttention(dim=dim, heads=heads, win_size=win_size)
        self.drop_path = DropPath(drop_path)
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = LeFF(dim=dim, hidden=int(dim * mlp_ratio))

    def forward(self, x: Tensor) -> Tensor:
        _, h, w, _ = x.shape
        win = self.win_size
        # As in the official code, a single window needs no shift.
        shift = win // 2 if self.shift and min(h, w) > win else 0
        mask = _shift_mask(h, w, win, shift, x.device) if shift else None
        return ops.lewin_block(self, x, shift, mask)


class Stage(nn.Sequential):
    """``depth`` LeWin blocks, every second one shifted: ``(B, H, W, C) -> (B, H, W, C)``."""

    def __init__(self, *, dim: int, depth: int, heads: int, cfg: UformerConfig, drop_paths: list[float],
                 modulator: bool = False):
        super().__init__(*[
            LeWinBlock(dim=dim, heads=heads, win_size=cfg.win_size, shift=cfg.shift_windows and i % 2 == 1,
                       mlp_ratio=cfg.mlp_ratio, drop_path=drop_paths[i], modulator=modulator)
            for i in range(depth)
        ])


class Uformer(nn.Module):
    """``(B, in_channels, H, W) -> (B, out_channels, H, W)`` for any H x W.

    The output is a residual (zero at initialisation); the caller adds it to the image.
    """

    def __init__(self, config: UformerConfig, *, in_channels: int = 64, out_channels: int = 3):
        super().__init__()
        self.config = cfg = config
        e = cfg.embed_dim
        dims = cfg.stage_dims()
        # Official schedule: linear over the encoder blocks, the maximum in the bottleneck,
        # the encoder's rates reversed in the decoder.
        enc = torch.linspace(0, cfg.drop_path_rate, sum(cfg.depths[:4])).tolist()
        dec = enc[::-1] + [0.0] * max(0, sum(cfg.depths[5:]) - len(enc))
        starts = [sum(cfg.depths[:s]) for s in range(5)]
        enc_rates = [enc[starts[s]:starts[s] + cfg.depths[s]] for s in range(4)]
        enc_rates.append([cfg.drop_path_rate] * cfg.depths[4])
        dstarts = [sum(cfg.depths[5:s]) for s in range(5, 9)]
        dec_rates = [dec[dstarts[i]:dstarts[i] + cfg.depths[5 + i]] for i in range(4)]
        self.input_proj = nn.Sequential(nn.Conv2d(in_channels, e, 3, padding=1), nn.LeakyReLU(0.01))
        self.encoders = nn.ModuleList()
        self.downsamples = nn.ModuleList()
        for s in range(4):
            self.encoders.append(Stage(dim=dims[s], depth=cfg.depths[s], heads=cfg.num_heads[s], cfg=cfg,
                                       drop_paths=enc_rates[s]))
            self.downsamples.append(nn.Conv2d(dims[s], dims[s + 1], 4, stride=2, padding=1))
        self.bottleneck = Stage(dim=dims[4], depth=cfg.depths[4], heads=cfg.num_heads[4], cfg=cfg,
                                drop_paths=enc_rates[4])
        self.upsamples = nn.ModuleList()
        self.decoders = nn.ModuleList()
        up_in = dims[4]
        for i, s in enumerate(range(5, 9)):
            skip = dims[3 - i]
            self.upsamples.append(nn.ConvTranspose2d(up_in, skip, 2, stride=2))
            self.decoders.append(Stage(dim=2 * skip, depth=cfg.depths[s], heads=cfg.num_heads[s], cfg=cfg,
                                       drop_paths=dec_rates[i], modulator=cfg.modulator))
            up_in = 2 * skip
        self.output_proj = nn.Conv2d(2 * e, out_channels, 3, padding=1)
        self.apply(_init_weights)
        nn.init.zeros_(self.output_proj.weight)
        nn.init.zeros_(self.output_proj.bias)

    def forward(self, x: Tensor) -> Tensor:
        h, w = x.shape[-2:]
        x = pad_to_multiple(x, self.config.size_multiple)
        # Channels-last on the fast path: the (B, H, W, C) token view is then free.
        y = conv_act(self.input_proj, x).permute(0, 2, 3, 1)
        skips = []
        for encoder, down in zip(self.encoders, self.downsamples):
            y = encoder(y)
            skips.append(y)
            y = down(y.permute(0, 3, 1, 2)).permute(0, 2, 3, 1)
        y = self.bottleneck(y)
        for up, decoder, skip in zip(self.upsamples, self.decoders, reversed(skips)):
            y = up(y.permute(0, 3, 1, 2)).permute(0, 2, 3, 1)
            y = decoder(torch.cat([y, skip], dim=-1))
        y = y.permute(0, 3, 1, 2)
        y = ops.conv3x3(y, self.output_proj)  # the C kernel for 3 channels: 2 ms less
        return y[..., :h, :w]


def _init_weights(m: nn.Module) -> None:
    """Official Uformer init: truncated normal (std 0.02) linears, unit LayerNorms."""
    if isinstance(m, nn.Linear):
        nn.init.trunc_normal_(m.weight, std=0.02)
        if m.bias is not None:
            nn.init.zeros_(m.bias)
    elif isinstance(m, nn.LayerNorm):
        nn.init.ones_(m.weight)
        nn.init.zeros_(m.bias)

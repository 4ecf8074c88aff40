"""The Uformer's operations with several bodies: window attention, a LeWin block and its LeFF.

Each takes the module whose weights it uses (:class:`roguenerf.models.uformer.WindowAttention`,
``LeWinBlock``, ``LeFF``) and picks its body once (:func:`roguenerf.ops.backend.pick`): the
fused C kernels, torch's fast path (oneDNN, fused attention with the bias broadcast), torch
with gradient (scaled-dot-product attention) or the plain reference.

Dimension letters: B batch, H x W tokens, C channels, n heads, d head channels, w window side,
N windows, L = w * w tokens per window.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import Tensor, nn

from roguenerf import native
from roguenerf.ops.backend import Body, as_contiguous, pick
from roguenerf.ops.fused import conv2d, linear, linear_add


def window_attention(attn: nn.Module, x: Tensor, mask: Tensor | None = None) -> Tensor:
    """``attn`` (a ``WindowAttention``) on ``x`` ``(N*B, L, C)`` with ``mask`` ``(N, L, L)``
    additive (0 or -100) or None -> ``(N*B, L, C)``."""
    qkv = linear(x, attn.to_qkv)
    body = pick(x) if attn.fused else Body.REFERENCE
    if body is Body.NATIVE and native.window_attention_supported(x.shape[1], x.shape[-1] // attn.heads):
        out = native.window_attention(as_contiguous(qkv), attn._cached_bias(None)[0], as_contiguous(mask), attn.heads,
                                      attn.scale)
        return linear(out, attn.to_out)
    q, k, v = rearrange(qkv, "b l (three n d) -> three b n l d", three=3, n=attn.heads)
    if body.fast:
        out = _attention_fast(attn, q, k, v, mask)
    else:
        bias = attn.bias()[None]
        if mask is not None:
            num_windows = mask.shape[0]
            bias = rearrange(bias + mask[:, None], "nw n i j -> 1 nw n i j")
            bias = bias.expand(x.shape[0] // num_windows, -1, -1, -1, -1).reshape(-1, *bias.shape[2:])
        if body is Body.TORCH:
            out = F.scaled_dot_product_attention(q, k, v, attn_mask=bias.to(q.dtype), scale=attn.scale)
        else:
            scores = (q * attn.scale) @ k.transpose(-2, -1) + bias
            out = scores.softmax(dim=-1) @ v
    return linear(rearrange(out, "b n l d -> b l (n d)"), attn.to_out)


def _attention_fast(attn: nn.Module, q: Tensor, k: Tensor, v: Tensor, mask: Tensor | None) -> Tensor:
    """Fused attention with the bias broadcast over all windows; with a shift mask, only the
    windows the mask touches (the last row and column of windows) are redone with it.
    Elsewhere the mask is exactly 0, so the result equals the plain path. No gradient."""
    bias, edges, edge_bias = attn._cached_bias(mask)
    out = F.scaled_dot_product_attention(q, k, v, attn_mask=bias[None], scale=attn.scale)
    if mask is not None and edges.numel():
        num_windows = mask.shape[0]
        images = q.shape[0] // num_windows
        idx = (torch.arange(images, device=q.device)[:, None] * num_windows + edges[None]).flatten()
        eb = edge_bias.repeat(images, 1, 1, 1) if images > 1 else edge_bias
        out[idx] = F.scaled_dot_product_attention(q[idx], k[idx], v[idx], attn_mask=eb, scale=attn.scale)
    return out


def leff(module: nn.Module, x: Tensor, residual: Tensor | None = None) -> Tensor:
    """``module`` (a ``LeFF``: ``linear2(gelu(dwconv(gelu(linear1(x)))))``) on ``x``
    ``(B, H, W, C)``; with ``residual``, ``residual + leff(x)``, the sum fused into the last
    linear or the whole block one C kernel (:func:`roguenerf.native.leff`)."""
    if pick(x) is Body.NATIVE and native.leff_supported(x.shape[-1], module.linear1[0].out_features):
        return native.leff(as_contiguous(x), as_contiguous(residual), module)
    x = linear(x, module.linear1[0], "gelu")
    # (B, H, W, C) permuted is a channels-last (B, C, H, W): no copy either way.
    x = conv2d(x.permute(0, 3, 1, 2), module.dwconv[0], "gelu").permute(0, 2, 3, 1)
    if residual is not None:
        return linear_add(x, module.linear2, residual)
    return linear(x, module.linear2)


def lewin_block(block: nn.Module, x: Tensor, shift: int, mask: Tensor | None) -> Tensor:
    """``block`` (a ``LeWinBlock``) on ``x`` ``(B, H, W, C)``, windows rolled by ``shift``
    (``mask`` its ``(N, L, L)`` shift mask, or None): LayerNorm -> window attention ->
    residual; LayerNorm -> LeFF -> residual."""
    _, h, w, _ = x.shape
    win = block.win_size
    if (pick(x) is Body.NATIVE and block.modulator is None and not (block.training and block.drop_path.p)
            and h % win == 0 and w % win == 0):  # (else the torch body names the error)
        x, normed = _attention_half_native(block, x, win, shift, mask)
        return block.mlp(normed, residual=x)
    return _lewin_block_torch(block, x, win, shift, mask)


def _attention_half_native(block: nn.Module, x: Tensor, win: int, shift: int,
                           mask: Tensor | None) -> tuple[Tensor, Tensor]:
    """The attention half (``x + attention`` and the next LayerNorm of it) in one pass window
    by window, else the norms, roll, window (un)partition and residual in two fused passes
    around the attention. Same function."""
    x, mask = as_contiguous(x), as_contiguous(mask)
    if block.attn.fused and native.lewin_attention_supported(win, x.shape[-1], block.attn.heads):
        return native.lewin_attention(x, block.norm1, block.attn, mask, block.norm2, shift)
    y = block.attn(native.ln_partition(x, block.norm1, win, shift), mask)
    return native.merge_ln(x, as_contiguous(y), block.norm2, win, shift)


def _lewin_block_torch(block: nn.Module, x: Tensor, win: int, shift: int, mask: Tensor | None) -> Tensor:
    _, h, w, _ = x.shape
    y = block.norm1(x)
    if shift:
        y = torch.roll(y, shifts=(-shift, -shift), dims=(1, 2))
    y = rearrange(y, "b (nh wh) (nw ww) c -> (b nh nw) (wh ww) c", wh=win, ww=win)
    if block.modulator is not None:
        y = y + block.modulator.weight
    y = block.attn(y, mask)
    y = rearrange(y, "(b nh nw) (wh ww) c -> b (nh wh) (nw ww) c", nh=h // win, nw=w // win, wh=win)
    if shift:
        y = torch.roll(y, shifts=(shift, shift), dims=(1, 2))
    x = x + block.drop_path(y)
    return x + block.drop_path(block.mlp(block.norm2(x)))

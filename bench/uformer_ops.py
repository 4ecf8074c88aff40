"""Op-by-op time of one full-resolution Uformer LeWin block (the stage that limits the forward).

    python -m bench.uformer_ops --output bench/results/uformer_ops.csv [--variant T]
                                [--size 512x512] [--stage dec3] [--repeats 5]

Times, in isolation and on the inference fast path (``torch.inference_mode``, oneDNN fused
kernels, ``roguenerf.runtime.configure``), each operation of the first block of one Uformer
stage (default: T's last decoder stage, 32 channels at full resolution) on a random input of
its shape: layer norm, window partition copy, shift roll, qkv linear, fused window attention
(``scaled_dot_product_attention`` with the relative position bias), output linear, LeFF's
linear + GELU, depthwise 3x3 conv + GELU and output linear, residual add. Best of
``--repeats`` after one warm-up. Reports milliseconds, FLOPs (2 per multiply-add) and GFLOP/s
per op, and the matmul peak measured in the same run. Writes CSV (date, machine, commit) and
a PNG bar chart.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch
import torch.nn.functional as F
from einops import rearrange

from bench.common import beside, stamp, write_csv
from bench.stages import matmul_peak
from roguenerf import runtime
from roguenerf.models import build_enhancer
from roguenerf.ops import fused


def best_ms(fn, repeats: int) -> float:
    fn()
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best * 1e3


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--output", required=True, type=Path)
    p.add_argument("--variant", default="T")
    p.add_argument("--size", default="512x512", help="HxW of the full-resolution input")
    p.add_argument("--stage", default="dec3", help="enc0..enc3, bottleneck, dec0..dec3")
    p.add_argument("--repeats", type=int, default=5)
    args = p.parse_args(argv)
    applied = runtime.configure()
    torch.manual_seed(0)
    uf = build_enhancer(args.variant).eval().uformer
    stages = {f"enc{i}": s for i, s in enumerate(uf.encoders)}
    stages["bottleneck"] = uf.bottleneck
    stages.update({f"dec{i}": s for i, s in enumerate(uf.decoders)})
    if args.stage not in stages:
        p.error(f"--stage: expected one of {sorted(stages)}")
    level = {"enc0": 0, "enc1": 1, "enc2": 2, "enc3": 3, "bottleneck": 4, "dec0": 3, "dec1": 2, "dec2": 1,
             "dec3": 0}[args.stage]
    blk = stages[args.stage][0]
    h, w = (int(v) // 2**level for v in args.size.lower().split("x"))
    c = blk.norm1.normalized_shape[0]
    heads, win = blk.attn.heads, blk.win_size
    hidden = blk.mlp.linear1[0].out_features
    tokens = h * w
    peak = matmul_peak()
    x = torch.randn(1, h, w, c)
    rows = []
    with torch.inference_mode():
        xw = rearrange(x, "b (nh wh) (nw ww) c -> (b nh nw) (wh ww) c", wh=win, ww=win)
        qkv = fused.linear(xw, blk.attn.to_qkv)
        q, k, v = rearrange(qkv, "b l (three n d) -> three b n l d", three=3, n=heads)
        bias = blk.attn.bias()[None]
        attn = F.scaled_dot_product_attention(q, k, v, attn_mask=bias, scale=blk.attn.scale)
        attn = rearrange(attn, "b n l d -> b l (n d)")
        hid = fused.linear(x, blk.mlp.linear1[0], "gelu")
        hid_cf = hid.permute(0, 3, 1, 2)
        L = win * win
        ops = [
            ("layer norm", lambda: blk.norm1(x), 0),
            ("window partition (copy)",
             lambda: rearrange(x, "b (nh wh) (nw ww) c -> (b nh nw) (wh ww) c", wh=win, ww=win).contiguous(), 0),
            ("shift roll", lambda: torch.roll(x, (-(win // 2), -(win // 2)), (1, 2)), 0),
            ("qkv linear", lambda: fused.linear(xw, blk.attn.to_qkv), 2 * tokens * c * 3 * c),
            ("window attention (fused)",
             lambda: F.scaled_dot_product_attention(q, k, v, attn_mask=bias, scale=blk.attn.scale),
             2 * 2 * tokens * L * c),
            ("output linear", lambda: fused.linear(attn, blk.attn.to_out), 2 * tokens * c * c),
            ("LeFF linear + GELU", lambda: fused.linear(x, blk.mlp.linear1[0], "gelu"), 2 * tokens * c * hidden),
            ("LeFF depthwise 3x3 + GELU", lambda: fused.conv2d(hid_cf, blk.mlp.dwconv[0], "gelu"),
             2 * tokens * hidden * 9),
            ("LeFF output linear", lambda: fused.linear(hid, blk.mlp.linear2), 2 * tokens * hidden * c),
            ("residual add", lambda: x + x, 0),
        ]
        meta = stamp()
        for name, fn, flops in ops:
            ms = best_ms(fn, args.repeats)
            rows.append({**meta, "variant": args.variant, "stage": args.stage, "height": h, "width": w,
                         "channels": c, "heads": heads, "window": win, "op": name, "ms": round(ms, 2),
                         "gflop": round(flops / 1e9, 3), "gflops_per_s": round(flops / ms / 1e6, 1),
                         "peak_gflops": round(peak, 1), "threads": applied["threads"]})
            print(f"{name:28s} {ms:7.2f} ms  {flops / 1e9:6.2f} GFLOP  {flops / ms / 1e6:7.1f} GFLOP/s", flush=True)
    print(f"one block, ops above: {sum(r['ms'] for r in rows):.1f} ms; matmul peak {peak:.0f} GFLOP/s")
    write_csv(beside(args.output, ".csv"), rows)
    plot(rows, beside(args.output, ".png"))
    print(f"wrote {beside(args.output, '.csv')} and {beside(args.output, '.png')}")


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4))
    ax.barh(range(len(rows)), [r["ms"] for r in rows], color="tab:purple")
    ax.set_yticks(range(len(rows)), [f"{r['op']} ({r['gflops_per_s']:.0f} GFLOP/s)" if r["gflop"] else r["op"]
                                     for r in rows], fontsize=7)
    ax.invert_yaxis()
    ax.set_xlabel("milliseconds (best of repeats)")
    r0 = rows[0]
    ax.set_title(f"{r0['variant']} {r0['stage']} block: {r0['width']}x{r0['height']}x{r0['channels']}, "
                 f"{r0['heads']} heads, window {r0['window']} - peak {r0['peak_gflops']:.0f} GFLOP/s\n"
                 f"{r0['date']} - {r0['commit']} - {r0['machine']}", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    main()

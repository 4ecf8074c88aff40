"""CPU render time and memory of the 3DGS rasterizer (``roguenerf.splats.render``).

Random Gaussians (SH degree 3, sizes and opacities like a trained scene's: a few pixels across,
most nearly opaque) in front of one camera at 504x378; each size runs in a fresh process so its
peak resident memory is its own. Writes ``bench/results/splats_render.csv`` (date, machine,
commit on every row).

    python -m bench.splats_render [--sizes 100000,1000000] [--threads 1] [--repeat 2]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

from bench.common import REPO, RESULTS, stamp, write_csv

WIDTH, HEIGHT = 504, 378


def one(n: int, threads: int, repeat: int) -> dict:
    import torch

    from roguenerf.splats import Gaussians, logit, render

    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(0)
    means = torch.randn(n, 3, generator=g) * torch.tensor([2.0, 1.5, 1.0]) + torch.tensor([0.0, 0.0, 6.0])
    gaussians = Gaussians(
        means=means, sh=torch.randn(n, 16, 3, generator=g) * 0.3,
        opacity=logit(torch.rand(n, generator=g) * 0.5 + 0.49),
        # Trained scenes' splats: sigma of about 0.3 to 3 px at this distance and focal length.
        log_scales=torch.log(torch.rand(n, 3, generator=g) * 0.04 + 0.004), quats=torch.randn(n, 4, generator=g))
    K = torch.tensor([[400.0, 0, WIDTH / 2], [0, 400.0, HEIGHT / 2], [0, 0, 1]], dtype=torch.float64)
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        rgb, depth, acc = render(gaussians, torch.eye(4, dtype=torch.float64), K, HEIGHT, WIDTH)
        times.append(time.perf_counter() - t0)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {"gaussians": n, "width": WIDTH, "height": HEIGHT, "threads": threads, "seconds": round(min(times), 2),
            "seconds_all": " ".join(f"{t:.2f}" for t in times), "peak_rss_mb": round(peak / 1024),
            "render_rss_mb": round((peak - base) / 1024), "covered": round(float((acc > 0.5).float().mean()), 3)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="100000,1000000")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        print(json.dumps(one(args.one, args.threads, args.repeat)))
        return
    rows = []
    for n in (int(s) for s in args.sizes.split(",")):
        out = subprocess.run([sys.executable, "-m", "bench.splats_render", "--one", str(n),
                              "--threads", str(args.threads), "--repeat", str(args.repeat)],
                             capture_output=True, text=True, check=True, cwd=REPO)
        row = {**stamp(), **json.loads(out.stdout.strip().splitlines()[-1])}
        print(row, flush=True)
        rows.append(row)
    write_csv(RESULTS / "splats_render.csv", rows)


if __name__ == "__main__":
    main()

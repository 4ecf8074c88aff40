"""GPU check of the shipped inference (pose refinement, colour, trust, a near third neighbour):
every test view of a scene on the CPU and on CUDA, images compared, seconds per view.

Here, a scene folder copied into an ignored folder that the device tool carries (with the kornia
wheels of scripts/gpu_pretrain.sh in .whl/):
    S=runs/kinds/pairs/ollie/hash_s2_400steps_1024rays_48samples
    mkdir -p .gpucheck && cp -r $S/images $S/renders $S/depths $S/acc $S/transforms.json .gpucheck/
There (carry .gpucheck and .whl):
    python3 -m pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl
    PYTHONPATH=/tmp/site:$PWD ROGUENERF_THREADS=8 python3 scripts/gpu_inference_check.py .gpucheck
"""

import sys
import time
from pathlib import Path

import torch

from roguenerf.checkpoint import default_checkpoint_path, load_checkpoint
from roguenerf.data.readers import load_scene
from roguenerf.inference import SceneEnhancer


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(-10 * torch.log10(((a - b) ** 2).mean().clamp_min(1e-12)))


def main(folder: str) -> None:
    scene = load_scene(Path(folder))
    if not torch.cuda.is_available():
        raise SystemExit("no CUDA device")
    print(torch.__version__, torch.cuda.get_device_name(), flush=True)
    views = scene.indices("test")
    out = {}
    for dev in ("cpu", "cuda"):
        enhancer = SceneEnhancer(scene, load_checkpoint(default_checkpoint_path())[0], device=dev)
        enhancer.enhance_view(views[0])  # warm-up: encodes the neighbours, loads the kernels
        torch.cuda.synchronize()
        start = time.perf_counter()
        results = [enhancer.enhance_view(i) for i in views]
        torch.cuda.synchronize()
        out[dev] = (results, (time.perf_counter() - start) / len(views))
    for i, c, g in zip(views, out["cpu"][0], out["cuda"][0], strict=True):
        photo, render = scene.photo(i), scene.render(i)
        base = psnr(render, photo)
        print(f"{scene.frames[i].name} neighbours {c.neighbours} {g.neighbours} trust {c.trust} {g.trust} "
              f"gain cpu {psnr(c.image, photo) - base:+.3f} cuda {psnr(g.image, photo) - base:+.3f} "
              f"max |cpu-cuda| {float((c.image - g.image).abs().max()):.4f}", flush=True)
    print(f"seconds per view: cpu {out['cpu'][1]:.3f}, cuda {out['cuda'][1]:.3f}")


if __name__ == "__main__":
    main(sys.argv[1])

"""GPU check of the shipped inference (pose refinement, colour, trust, a near third neighbour):
every test view of a scene on the CPU and on CUDA, images compared, seconds per view.

Here, a scene folder copied into an ignored folder that the device tool carries (with the kornia
wheels of scripts/gpu_pretrain.sh in .whl/):
    mkdir -p .gpucheck && cp -r runs/kinds/pairs/ollie/hash_s2_400steps_1024rays_48samples/{images,renders,depths,acc,transforms.json} .gpucheck/
There (carry .gpucheck and .whl):
    python3 -m pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl
    PYTHONPATH=/tmp/site:$PWD ROGUENERF_THREADS=8 python3 scripts/gpu_inference_check.py .gpucheck
"""
import sys, time
from pathlib import Path
import torch
from roguenerf.checkpoint import default_checkpoint_path, load_checkpoint
from roguenerf.data.readers import load_scene
from roguenerf.inference import SceneEnhancer

scene = load_scene(Path(sys.argv[1]))
model, _ = load_checkpoint(default_checkpoint_path())
print(torch.__version__, torch.cuda.get_device_name() if torch.cuda.is_available() else "no cuda", flush=True)
out = {}
for dev in ("cpu", "cuda"):
    enh = SceneEnhancer(scene, load_checkpoint(default_checkpoint_path())[0], device=dev)
    enh.enhance_view(scene.indices("test")[0])  # warm-up (encodes, kernels)
    if dev == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    res = [enh.enhance_view(i) for i in scene.indices("test")]
    if dev == "cuda":
        torch.cuda.synchronize()
    out[dev] = (res, (time.perf_counter() - t0) / len(res))
def psnr(a, b):
    return float(-10 * torch.log10(((a - b) ** 2).mean().clamp_min(1e-12)))
for i, (c, g) in zip(scene.indices("test"), zip(out["cpu"][0], out["cuda"][0])):
    photo, render = scene.photo(i), scene.render(i)
    print(scene.frames[i].name, "neighbours", c.neighbours, g.neighbours, "trust", c.trust, g.trust,
          "gain cpu %+.3f cuda %+.3f" % (psnr(c.image, photo) - psnr(render, photo), psnr(g.image, photo) - psnr(render, photo)),
          "max |cpu-cuda| %.4f" % float((c.image - g.image).abs().max()), flush=True)
print("seconds per view: cpu %.3f, cuda %.3f" % (out["cpu"][1], out["cuda"][1]))

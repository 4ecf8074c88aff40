"""Does TorchInductor's C++ backend (``torch.compile``) beat the hand-tuned fast path at inference?

    python -m bench.inductor --output bench/results/inductor.csv [--variant micro] [--size 378x504]
                             [--repeats 7]

Issue 12 asks for the whole enhancement 2x faster without changing its outputs, and
``bench/stages.py`` found the remaining time in many small element-wise passes that PyTorch's
eager CPU operators cannot fuse. Inductor is the well-kept way to fuse them, so this measures
it on ``bench/stages.py``'s inputs (5 neighbours with cached sampling sources,
``torch.inference_mode``, random weights, torch's threads), one configuration per row:

  eager fast           the shipped fast path (oneDNN fused linears, channels-last, shared target work)
  eager reference      the plain path (``reference_mode()``)
  compiled uformer     the fast path with the Uformer replaced by ``torch.compile`` of its plain
                       path (the fast path's direct oneDNN calls do not lower in Inductor)
  compiled whole       ``torch.compile`` of the whole plain path (graph breaks where the model
                       checks its inputs)
  ... + freezing       the same with ``torch._inductor.config.freezing`` (weights as constants,
                       prepacked for oneDNN: Inductor's advice for CPU inference)
  onnxruntime uformer  the fast path with the Uformer exported to ONNX (its plain path, opset 18)
                       and run by ONNX Runtime's CPU provider with all graph optimisations
                       (LayerNorm / GELU / attention fusions), torch's thread count; skipped
                       unless ``onnxruntime`` and ``onnx`` are installed (not project dependencies)

Columns: median seconds of ``--repeats`` runs after the first call, the first call's seconds
(the compile), the speed-up over ``eager fast`` and the max |difference| from its output.
Writes the CSV (date, machine, commit on every row), a JSON next to it and a PNG bar plot.
Needs a C++ compiler (``g++``) for the compiled rows; without one they are skipped with the reason.
``--configs`` picks rows by name (the compiled ones take minutes each); ``eager fast`` always runs.
"""

from __future__ import annotations

import argparse
import contextlib
import shutil
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import torch

from bench.common import RESULTS, beside, stamp, write_csv, write_json
from bench.stages import make_inputs, randomise_zero_layers
from roguenerf import runtime
from roguenerf.fastpath import reference_mode
from roguenerf.models import build_enhancer

CONFIGS = ("eager fast", "eager reference", "compiled uformer", "compiled whole", "compiled uformer + freezing",
           "compiled whole + freezing", "onnxruntime uformer")
"""Row names, in the order they run (``--configs``)."""


class _InReferenceMode(torch.nn.Module):
    """Runs ``module`` (compiled) with the plain operators, which Inductor can lower."""

    def __init__(self, module):
        super().__init__()
        self.module = module

    def forward(self, *args, **kwargs):
        with reference_mode():
            return self.module(*args, **kwargs)


class _OnnxRuntime(torch.nn.Module):
    """Runs an exported module's ONNX graph with ONNX Runtime (CPU, float32, fixed input shape)."""

    def __init__(self, session):
        super().__init__()
        self.session = session

    def forward(self, x):
        y = self.session.run(None, {"x": x.contiguous().numpy()})[0]
        return torch.from_numpy(y)


def _onnxruntime_session(module, example: torch.Tensor, directory: str):
    """ONNX Runtime session of ``module`` (its plain path) for inputs shaped like ``example``."""
    import onnxruntime

    path = str(Path(directory) / "module.onnx")
    with torch.inference_mode(False), torch.no_grad(), reference_mode():
        torch.onnx.export(module, (torch.zeros(example.shape),), path, opset_version=18,
                          input_names=["x"], output_names=["y"], dynamo=False)
    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = torch.get_num_threads()
    options.inter_op_num_threads = 1
    options.graph_optimization_level = onnxruntime.GraphOptimizationLevel.ORT_ENABLE_ALL
    return onnxruntime.InferenceSession(path, options, providers=["CPUExecutionProvider"])


def _time(fn, repeats: int) -> tuple[float, float, torch.Tensor]:
    t = time.perf_counter()
    out = fn()
    first = time.perf_counter() - t
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), first, out


def measure(variant: str, h: int, w: int, repeats: int, only: set[str] | None = None) -> list[dict]:
    runtime.configure()
    torch.manual_seed(0)
    model = build_enhancer(variant).eval()
    randomise_zero_layers(model)
    uformer = model.uformer
    rows = []
    with torch.inference_mode():
        inputs = make_inputs(model, h, w)
        # Each config returns _time's (median seconds, first call's seconds, output).
        configs: list[tuple[str, Callable[[], tuple[float, float, torch.Tensor]]]] = [
            ("eager fast", lambda: _time(lambda: model(*inputs), repeats))]

        def reference():
            with reference_mode():
                return _time(lambda: model(*inputs), repeats)
        configs.append(("eager reference", reference))
        compiler = shutil.which("g++") or shutil.which("c++")
        for freezing in (False, True):
            suffix = " + freezing" if freezing else ""

            def compiled_uformer(freezing=freezing):
                torch._dynamo.reset()
                model.uformer = _InReferenceMode(torch.compile(uformer, dynamic=False))
                try:
                    with _freezing(freezing):
                        return _time(lambda: model(*inputs), repeats)
                finally:
                    model.uformer = uformer

            def compiled_whole(freezing=freezing):
                torch._dynamo.reset()
                compiled = _InReferenceMode(torch.compile(model, dynamic=False))
                with _freezing(freezing):
                    return _time(lambda: compiled(*inputs), repeats)
            configs.append((f"compiled uformer{suffix}", compiled_uformer))
            configs.append((f"compiled whole{suffix}", compiled_whole))

        def onnxruntime_uformer():
            f = model.config.features
            with tempfile.TemporaryDirectory() as tmp:
                session = _onnxruntime_session(uformer, torch.zeros(1, f, h, w), tmp)
            model.uformer = _OnnxRuntime(session)
            try:
                return _time(lambda: model(*inputs), repeats)
            finally:
                model.uformer = uformer
        configs.append(("onnxruntime uformer", onnxruntime_uformer))

        assert [name for name, _ in configs] == list(CONFIGS)
        base = None
        for name, fn in configs:
            if only is not None and name != "eager fast" and name not in only:
                continue
            row = dict(**stamp(), variant=variant, height=h, width=w, neighbours=5, config=name)
            if name.startswith("compiled") and compiler is None:
                rows.append(dict(row, skipped="no C++ compiler (g++) on PATH"))
                continue
            if name.startswith("onnxruntime") and not _importable("onnxruntime", "onnx"):
                rows.append(dict(row, skipped="onnxruntime and onnx are not installed"))
                continue
            try:
                seconds, first, out = fn()
            except Exception as exc:  # a lowering failure is a result here, not a crash
                rows.append(dict(row, skipped=f"{type(exc).__name__}: {str(exc).splitlines()[0][:200]}"))
                continue
            if base is None:
                base = (seconds, out)
            rows.append(dict(row, seconds=round(seconds, 4), first_call_seconds=round(first, 2),
                             speedup_vs_eager_fast=round(base[0] / seconds, 3),
                             max_abs_diff=float((out - base[1]).abs().max())))
            print({k: v for k, v in rows[-1].items() if k not in ("date", "machine")}, flush=True)
    return rows


def _importable(*names: str) -> bool:
    import importlib.util
    return all(importlib.util.find_spec(n) is not None for n in names)


@contextlib.contextmanager
def _freezing(on: bool):
    import torch._inductor.config as inductor_config
    before = inductor_config.freezing
    inductor_config.freezing = on
    try:
        yield
    finally:
        inductor_config.freezing = before


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    done = [r for r in rows if "seconds" in r]
    fig, ax = plt.subplots(figsize=(9, 3.8))
    ax.barh([r["config"] for r in done], [r["seconds"] for r in done])
    for i, r in enumerate(done):
        ax.text(r["seconds"], i, f" {r['seconds']:.3f} s ({r['speedup_vs_eager_fast']:.2f}x)", va="center")
    ax.invert_yaxis()
    ax.set_xlabel("seconds per enhancement (median)")
    r0 = rows[0]
    ax.set_title(f"{r0['variant']} {r0['height']}x{r0['width']}, 5 neighbours, inference\n"
                 f"{r0['machine']} | {r0['commit']} | {r0['date'][:10]}", fontsize=7)
    ax.set_xlim(0, max(r["seconds"] for r in done) * 1.5)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--variant", default="micro")
    p.add_argument("--size", default="378x504", help="HxW")
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--output", type=Path, default=RESULTS / "inductor.csv")
    p.add_argument("--configs", default=None,
                   help="comma-separated row names to run besides 'eager fast' (default: all)")
    args = p.parse_args(argv)
    h, w = (int(v) for v in args.size.split("x"))
    only = None if args.configs is None else {c.strip() for c in args.configs.split(",") if c.strip()}
    unknown = sorted((only or set()) - set(CONFIGS))
    if unknown:
        p.error(f"--configs: unknown {', '.join(map(repr, unknown))}; expected some of {', '.join(CONFIGS)}")
    rows = measure(args.variant, h, w, args.repeats, only)
    write_csv(beside(args.output, ".csv"), rows)
    write_json(beside(args.output, ".json"), rows)
    plot(rows, beside(args.output, ".png"))
    print(f"wrote {beside(args.output, '.csv')}, .json and .png")


if __name__ == "__main__":
    main()

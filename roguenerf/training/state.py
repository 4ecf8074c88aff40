"""Resumable training state: model + Adam state + step + RNG states, one safetensors file.

Everything needed to continue lives in one file, written atomically (temp file, fsync,
rename), so an interruption at any moment leaves either the previous or the new state, never
a mix. Tensors go in the safetensors body; step, timings and JSON-able settings in its
metadata. Never pickle.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch
from torch import nn

from roguenerf.errors import CheckpointError

STATE_FORMAT = "roguenerf-train-state"
STATE_VERSION = "1"


def atomic_save_tensors(path: Path, tensors: dict[str, torch.Tensor], metadata: dict[str, str]) -> Path:
    from safetensors.torch import save

    from roguenerf.imageio import atomic_write

    data = save({k: v.detach().to("cpu").contiguous().clone() for k, v in tensors.items()}, metadata=metadata)
    atomic_write(path, data)
    return path


def save_state(path: Path, *, model: nn.Module, optimizer: torch.optim.Optimizer, generator: torch.Generator,
               step: int, elapsed_s: float, info: dict) -> Path:
    """Write the resumable state. ``info`` is JSON-able (model config, plan, before-metrics ...)."""
    tensors: dict[str, torch.Tensor] = {f"model.{k}": v for k, v in model.state_dict().items()}
    optim = optimizer.state_dict()
    for index, slots in optim["state"].items():
        for name, value in slots.items():
            tensors[f"optim.{index}.{name}"] = torch.as_tensor(value)
    tensors["rng.torch"] = torch.get_rng_state()
    tensors["rng.sampler"] = generator.get_state()
    metadata = {
        "format": STATE_FORMAT,
        "format_version": STATE_VERSION,
        "step": str(int(step)),
        "elapsed_s": repr(float(elapsed_s)),
        "param_groups": json.dumps(optim["param_groups"]),
        "info": json.dumps(info),
    }
    return atomic_save_tensors(path, tensors, metadata)


def load_state(path: Path) -> dict:
    """Read a state file: ``{"step", "elapsed_s", "info", "model", "optim", "rng_torch", "rng_sampler"}``."""
    from safetensors import safe_open

    path = Path(path)
    try:
        with safe_open(str(path), framework="pt") as fh:
            meta = fh.metadata() or {}
            tensors = {k: fh.get_tensor(k) for k in fh.keys()}
    except Exception as exc:  # noqa: BLE001 - any decoding fault is the file's
        raise CheckpointError(f"{path}: not a readable training state ({exc})") from None
    if meta.get("format") != STATE_FORMAT:
        raise CheckpointError(f"{path}: expected format {STATE_FORMAT!r}, got {meta.get('format')!r}")
    if meta.get("format_version") != STATE_VERSION:
        raise CheckpointError(f"{path}: expected format_version {STATE_VERSION}, got {meta.get('format_version')!r}")
    model = {k[len("model."):]: v for k, v in tensors.items() if k.startswith("model.")}
    optim_state: dict[int, dict] = {}
    for key, value in tensors.items():
        if key.startswith("optim."):
            _, index, name = key.split(".", 2)
            optim_state.setdefault(int(index), {})[name] = value
    return {
        "step": int(meta["step"]),
        "elapsed_s": float(meta["elapsed_s"]),
        "info": json.loads(meta["info"]),
        "model": model,
        "optim": {"state": optim_state, "param_groups": json.loads(meta["param_groups"])},
        "rng_torch": tensors["rng.torch"],
        "rng_sampler": tensors["rng.sampler"],
    }

"""Enhancer checkpoints: one safetensors file, never a pickle.

The ``.safetensors`` file holds the weights; its string metadata holds ``format``
(``"roguenerf-enhancer"``), ``format_version`` (``"1"``), ``config`` (the
:class:`~roguenerf.models.config.EnhancerConfig` as JSON) and ``meta`` (optional training
summary, JSON). A sidecar ``NAME.json`` repeats config and meta for people to read; loading
needs only the ``.safetensors``.

Loading reads the file's bytes once (bounded by ``max_bytes``), checks the safetensors
framing itself before handing the bytes to ``safetensors`` (a pickle or ``torch.save`` zip is
named as such and never unpickled), then checks format, version, config, tensor names,
shapes and finiteness, each with a message that says what is wrong.
"""

from __future__ import annotations

import dataclasses
import json
import os
import struct
from pathlib import Path

import torch
from torch import nn

from roguenerf.errors import CheckpointError, InputError
from roguenerf.imageio import atomic_write

FORMAT = "roguenerf-enhancer"
FORMAT_VERSION = "1"
DEFAULT_MAX_BYTES = 2 * 1024**3
"""Largest checkpoint read when ``max_bytes`` is None (the B variant is ~0.2 GB)."""
MAX_HEADER_BYTES = 100 * 1024 * 1024
"""safetensors' own limit on the JSON header."""
MODEL_FILE = "model.safetensors"
"""The finished checkpoint in the folder a training run writes (``finetune`` / ``pretrain --output``)."""
TRAIN_STATE_FILE = "train_state.safetensors"
"""Beside it, the resume state of a training run (``roguenerf.training.STATE_FILE``)."""


def default_checkpoint_path(*, must_exist: bool = True) -> Path:
    """``roguenerf/weights/default.safetensors``: the pre-trained enhancer shipped with the package.

    Raises CheckpointError (saying how to create it) when it does not exist, unless
    ``must_exist`` is False (e.g. to write it).
    """
    path = Path(__file__).resolve().parent / "weights" / "default.safetensors"
    if must_exist and not path.is_file():
        raise CheckpointError(
            f"no default checkpoint at {path}: pre-train one with `roguenerf pretrain` and copy its "
            f"model.safetensors to that path, or pass a checkpoint explicitly"
        )
    return path


def resolve_checkpoint(path: str | os.PathLike) -> Path:
    """The checkpoint file ``path`` means: the file itself, or in a folder a training run wrote
    (``roguenerf finetune`` / ``pretrain --output``) its finished :data:`MODEL_FILE` (else the
    folder's one ``.safetensors``).

    Raises InputError naming the path when it does not exist, and for a folder that holds no
    finished checkpoint (only an unfinished run's resume state, or none or several files).
    """
    path = Path(path)
    if path.is_dir():
        return _checkpoint_in(path)
    if not path.is_file():
        raise InputError(f"checkpoint {path} does not exist")
    return path


def _checkpoint_in(folder: Path) -> Path:
    model = folder / MODEL_FILE
    if model.is_file():
        return model
    if (folder / TRAIN_STATE_FILE).is_file():
        raise InputError(f"checkpoint folder {folder} holds no finished checkpoint ({MODEL_FILE}), only the "
                         f"resume state of an unfinished run ({TRAIN_STATE_FILE}): run the same fine-tune again "
                         "to finish it")
    found = sorted(p.name for p in folder.glob("*.safetensors"))
    if len(found) == 1:
        return folder / found[0]
    raise InputError(f"checkpoint folder {folder} holds no checkpoint: expected {MODEL_FILE} (what "
                     "`roguenerf finetune --output` writes)"
                     + (f"; it holds {', '.join(found)}: pass one of them" if found else ""))


def save_checkpoint(path: str | os.PathLike, model: nn.Module, *, meta: dict | None = None) -> Path:
    """Save ``model`` (an Enhancer with a ``config``) atomically as safetensors + sidecar JSON.

    Args:
        path: the ``.safetensors`` file to write (parent folders are created).
        model: an :class:`~roguenerf.models.enhancer.Enhancer`.
        meta: JSON-able training summary stored with the weights.
    Returns:
        ``path``.
    """
    from safetensors.torch import save

    path = Path(path)
    config = getattr(model, "config", None)
    if config is None or not hasattr(config, "to_dict"):
        raise InputError(f"model: expected an Enhancer with a .config, got {type(model).__name__}")
    try:
        config_json = json.dumps(config.to_dict(), sort_keys=True)
        meta_json = json.dumps(meta if meta is not None else {}, sort_keys=True, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise InputError(f"meta: expected a JSON-able dict with finite numbers ({exc})") from None
    tensors = {}
    for name, tensor in model.state_dict().items():
        if tensor.is_floating_point() and not torch.isfinite(tensor).all():
            raise CheckpointError(f"refusing to save: tensor {name!r} contains NaN or inf")
        # clone: safetensors refuses tensors that share storage (views, tied weights)
        tensors[name] = tensor.detach().to("cpu").contiguous().clone()
    metadata = {"format": FORMAT, "format_version": FORMAT_VERSION, "config": config_json, "meta": meta_json}
    atomic_write(path, save(tensors, metadata=metadata), make_parents=True)
    sidecar = {"format": FORMAT, "format_version": FORMAT_VERSION, "config": json.loads(config_json),
               "meta": json.loads(meta_json), "weights": path.name}
    atomic_write(path.with_suffix(".json"), json.dumps(sidecar, indent=1, sort_keys=True).encode("utf-8"))
    return path


def _sniff(data: bytes) -> str | None:
    """Name of a known non-safetensors format, from its first bytes."""
    if data[:1] == b"\x80" and len(data) > 1 and data[1] <= 5:
        return "a Python pickle (e.g. torch.save); pickles are never loaded"
    if data[:4] == b"PK\x03\x04":
        return "a zip archive (e.g. torch.save); pickles are never loaded"
    if data[:6] == b"\x93NUMPY":
        return "a .npy array"
    if data[:4] == b"\x89HDF":
        return "an HDF5 file"
    return None


def read_safetensors_header(data: bytes, source: str) -> dict:
    """Parse and check the framing of safetensors ``data``: header length, JSON, offsets."""
    if len(data) < 8:
        raise CheckpointError(f"{source}: not a safetensors file ({len(data)} bytes, need at least 8)")
    (header_len,) = struct.unpack("<Q", data[:8])
    if header_len > len(data) - 8 or header_len > MAX_HEADER_BYTES or header_len < 2:
        known = _sniff(data)
        if known:
            raise CheckpointError(f"{source}: not a safetensors file but {known}")
        raise CheckpointError(
            f"{source}: not a safetensors file: header length {header_len} does not fit a file of {len(data)} bytes"
        )
    try:
        header = json.loads(data[8 : 8 + header_len].decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CheckpointError(f"{source}: not a safetensors file: header is not JSON ({exc})") from None
    if not isinstance(header, dict):
        raise CheckpointError(f"{source}: not a safetensors file: header is not a JSON object")
    return header


def load_checkpoint(path: str | os.PathLike, *, max_bytes: int | None = None, device="cpu"):
    """Load an enhancer saved by :func:`save_checkpoint`.

    Args:
        path: the ``.safetensors`` file.
        max_bytes: refuse larger files (default :data:`DEFAULT_MAX_BYTES`).
        device: where to put the model.
    Returns:
        ``(model, meta)``: the Enhancer in eval mode and the saved training summary (dict).
    Raises:
        CheckpointError: anything wrong, with what was expected and what was found.
    """
    from safetensors import SafetensorError
    from safetensors.torch import load

    from roguenerf.models.config import EnhancerConfig
    from roguenerf.models.enhancer import build_enhancer

    path = Path(path)
    limit = DEFAULT_MAX_BYTES if max_bytes is None else int(max_bytes)
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise CheckpointError(f"{path}: checkpoint file not found") from None
    except OSError as exc:
        raise CheckpointError(f"{path}: cannot read checkpoint ({exc})") from None
    if not path.is_file():
        raise CheckpointError(f"{path}: expected a .safetensors file, got a directory or special file")
    if size > limit:
        raise CheckpointError(f"{path}: checkpoint is {size} bytes, more than the allowed {limit} bytes")
    with open(path, "rb") as f:
        data = f.read(limit + 1)
    if len(data) > limit:
        raise CheckpointError(f"{path}: checkpoint is more than the allowed {limit} bytes")
    source = str(path)

    header = read_safetensors_header(data, source)
    metadata = header.get("__metadata__") or {}
    if metadata.get("format") != FORMAT:
        raise CheckpointError(
            f"{source}: not a RoGUENeRF enhancer checkpoint: metadata format is "
            f"{metadata.get('format')!r}, expected {FORMAT!r}"
        )
    version = metadata.get("format_version")
    if version != FORMAT_VERSION:
        raise CheckpointError(
            f"{source}: checkpoint format_version {version!r} is not supported by this library "
            f"(expected {FORMAT_VERSION!r}); upgrade roguenerf or re-save the checkpoint"
        )
    try:
        config_dict = json.loads(metadata.get("config", ""))
        meta = json.loads(metadata.get("meta") or "{}")
    except json.JSONDecodeError as exc:
        raise CheckpointError(f"{source}: metadata 'config' or 'meta' is not valid JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise CheckpointError(f"{source}: metadata 'meta' must be a JSON object, got {type(meta).__name__}")
    try:
        config = EnhancerConfig.from_dict(config_dict)
    except InputError as exc:
        raise CheckpointError(f"{source}: invalid config: {exc}") from None

    try:
        tensors = load(data)
    except SafetensorError as exc:
        raise CheckpointError(f"{source}: corrupt safetensors data ({exc})") from None
    model = build_enhancer(config)
    expected = model.state_dict()
    missing = sorted(set(expected) - set(tensors))
    unexpected = sorted(set(tensors) - set(expected))
    if missing or unexpected:
        parts = []
        if missing:
            parts.append(f"missing keys {missing}")
        if unexpected:
            parts.append(f"unexpected keys {unexpected}")
        raise CheckpointError(f"{source}: weights do not match the {config.variant!r} config: " + "; ".join(parts))
    for name, want in expected.items():
        got = tensors[name]
        if tuple(got.shape) != tuple(want.shape):
            raise CheckpointError(
                f"{source}: tensor {name!r} has shape {tuple(got.shape)}, the config expects {tuple(want.shape)}"
            )
        if got.is_floating_point() != want.is_floating_point():
            raise CheckpointError(f"{source}: tensor {name!r} has dtype {got.dtype}, expected {want.dtype}")
        if got.is_floating_point() and not torch.isfinite(got).all():
            raise CheckpointError(f"{source}: tensor {name!r} contains NaN or inf")
    model.load_state_dict({k: v.to(expected[k].dtype) for k, v in tensors.items()}, strict=True)
    return model.to(device).eval(), meta


def blend_state(start: dict, tuned: dict, a: float) -> dict:
    """``start + a (tuned - start)`` for every floating-point tensor of two state dicts of one
    architecture (a = 0: the start, 1: the tuned weights); other tensors from ``tuned``."""
    if start.keys() != tuned.keys():
        raise InputError("blend: the two checkpoints have different weights (another architecture)")
    for k, v in tuned.items():
        if start[k].shape != v.shape:
            raise InputError(f"blend: weight {k} has shape {tuple(start[k].shape)} in one checkpoint and "
                             f"{tuple(v.shape)} in the other (another architecture)")
    return {k: torch.lerp(start[k].to(v.dtype), v, a) if v.is_floating_point() else v.clone()
            for k, v in tuned.items()}


def blend_checkpoints(start: str | os.PathLike, tuned: str | os.PathLike, weight: float, output: str | os.PathLike
                      ) -> Path:
    """Weight-space ensembling (WiSE-FT, Wortsman et al. 2022): write ``start + weight (tuned -
    start)`` to ``output``, with ``tuned``'s configuration and metadata plus a ``blend`` entry
    naming both and the weight. ``weight`` in [0, 1]."""
    weight = float(weight)
    if not 0.0 <= weight <= 1.0:
        raise InputError(f"blend weight: expected a number in [0, 1], got {weight}")
    start_model, start_meta = load_checkpoint(start)
    model, meta = load_checkpoint(tuned)
    # The default neighbour count is a run-time default, not a weight's shape: a start trained
    # with 2 neighbours blends with its continuation trained with 5 (the blend keeps ``tuned``'s).
    if dataclasses.replace(start_model.config, num_neighbours=model.config.num_neighbours) != model.config:
        raise InputError("blend: the two checkpoints have different model configurations")
    model.load_state_dict(blend_state(start_model.state_dict(), model.state_dict(), weight))
    meta = dict(meta or {})
    meta["blend"] = {"start": Path(start).name, "tuned": Path(tuned).name, "weight": weight,
                     "start_training": (start_meta or {}).get("training")}
    return save_checkpoint(output, model, meta=meta)

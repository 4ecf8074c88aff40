"""The one Scene type every loader returns (STUB: the contract)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from torch import Tensor


@dataclass
class Frame:
    name: str
    """Unique view name (file stem, e.g. ``train_r_0``)."""
    world_from_cam: Tensor
    """``(4, 4)`` float64 OpenCV camera-to-world."""
    K: Tensor
    """``(3, 3)`` float64, pixel-centre convention."""
    width: int
    height: int
    split: str
    """"train" or "test"."""
    image_path: Path | None = None
    render_path: Path | None = None
    depth_path: Path | None = None
    depth_scale: float = 1.0
    """Multiply stored depth by this to get pose units (nerfstudio mm PNG: 0.001 * scale)."""
    depth_type: str = "z"
    """"z" or "ray" (converted to z on load)."""


@dataclass
class Scene:
    root: Path
    frames: list[Frame]
    meta: dict = field(default_factory=dict)

    # Loaders (cached): photo(i) -> (3,H,W) float32 [0,1]; render(i) -> (3,H,W); depth(i) -> (1,H,W) float32 z.
    # indices(split) -> list[int]; index(name) -> int; poses() -> (M,4,4); intrinsics() -> (M,3,3)

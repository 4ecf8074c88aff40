"""The paper's loss: L1 + 1e-3 * L1 between VGG-19 features (section 3.7).

ImageNet VGG-19 weights cannot be downloaded here, so :class:`VGG19Features` loads
torchvision's ``vgg19`` state dict from a local file when the user has one; otherwise the
loss is L1 alone and says so (``loss_kind``).
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor, nn

from roguenerf.errors import InputError

PERCEPTUAL_WEIGHT = 1e-3
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

# torchvision's vgg19 "features" layout ("M" = max-pool); indices of the Sequential match its
# state-dict keys (features.0.weight, features.2.weight, ...).
VGG19_LAYOUT = (64, 64, "M", 128, 128, "M", 256, 256, 256, 256, "M", 512, 512, 512, 512, "M",
                512, 512, 512, 512, "M")
VGG19_RELU5_4 = 36
"""Layers kept: everything up to and including relu5_4 (torchvision index 35)."""


def _vgg19_layers() -> nn.Sequential:
    layers: list[nn.Module] = []
    channels = 3
    for item in VGG19_LAYOUT:
        if item == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers += [nn.Conv2d(channels, item, 3, padding=1), nn.ReLU(inplace=False)]
            channels = item
    return nn.Sequential(*layers[:VGG19_RELU5_4])


def load_vgg19_state(path: Path | str) -> dict[str, Tensor]:
    """Read a torchvision vgg19 state dict from ``.safetensors`` or ``.pth`` (weights only, no pickle code)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"vgg_weights: file {path} does not exist")
    try:
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            state = load_file(str(path))
        else:
            state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any decoding fault is the file's
        raise InputError(f"vgg_weights: cannot read {path} as a VGG-19 state dict ({exc})") from None
    if not isinstance(state, dict):
        raise InputError(f"vgg_weights: {path} holds a {type(state).__name__}, expected a state dict")
    return state


class VGG19Features(nn.Module):
    """Frozen VGG-19 feature extractor up to relu5_4.

    Input ``(B, 3, H, W)`` RGB in [0, 1] (normalised with ImageNet statistics inside);
    output ``(B, 512, H/16, W/16)``.
    """

    def __init__(self, state: dict[str, Tensor]):
        super().__init__()
        self.features = _vgg19_layers()
        wanted = self.features.state_dict()
        loaded = {}
        for key, expected in wanted.items():
            value = state.get(f"features.{key}", state.get(key))
            if value is None:
                raise InputError(f"vgg_weights: key features.{key} is missing; expected torchvision's vgg19 state dict")
            if tuple(value.shape) != tuple(expected.shape):
                raise InputError(f"vgg_weights: features.{key} has shape {tuple(value.shape)}, "
                                 f"expected {tuple(expected.shape)}")
            loaded[key] = value.to(torch.float32)
        self.features.load_state_dict(loaded)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        self.requires_grad_(False)
        self.eval()

    @classmethod
    def from_file(cls, path: Path | str) -> VGG19Features:
        return cls(load_vgg19_state(path))

    def forward(self, image: Tensor) -> Tensor:
        return self.features((image - self.mean) / self.std)


class EnhancerLoss(nn.Module):
    """``L = |out - gt|_1 + 1e-3 |vgg(out) - vgg(gt)|_1`` (means), or L1 alone without VGG weights."""

    def __init__(self, vgg: VGG19Features | None = None, perceptual_weight: float = PERCEPTUAL_WEIGHT):
        super().__init__()
        self.vgg = vgg
        self.perceptual_weight = perceptual_weight

    @property
    def kind(self) -> str:
        return "l1+vgg19" if self.vgg is not None else "l1"

    def forward(self, output: Tensor, target: Tensor) -> Tensor:
        """``output``, ``target``: ``(B, 3, H, W)``; returns a scalar."""
        loss = (output - target).abs().mean()
        if self.vgg is not None:
            loss = loss + self.perceptual_weight * (self.vgg(output) - self.vgg(target)).abs().mean()
        return loss


def build_loss(vgg_weights: Path | str | None, device: torch.device | str = "cpu") -> EnhancerLoss:
    vgg = VGG19Features.from_file(vgg_weights).to(device) if vgg_weights else None
    return EnhancerLoss(vgg)

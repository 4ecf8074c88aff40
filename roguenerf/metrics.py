"""Image-quality metrics, one value per image.

* :func:`psnr`: per image, ``10 log10(max^2 / MSE)`` with the MSE over that image's
  channels and pixels. (``kornia.metrics.psnr`` pools the MSE over the whole batch, which is
  not the mean of per-view PSNRs that papers and the lego README report.)
* :func:`ssim`: ``kornia.metrics.ssim(a, b, window_size=11).mean()`` per image (Gaussian
  window, sigma 1.5, "same" reflect padding): the definition of the lego README's table.
  Any size >= 1x1 works: on an image whose shorter side ``m`` is under 6 pixels the window
  shrinks to ``min(window_size, 2 m - 1)`` taps (the largest odd window the reflect padding
  allows; sigma stays 1.5), so 1x1 images compare single pixels (window 1: the luminance
  term). Images of 6 x 6 and more are unaffected.
* :func:`flip`: NVIDIA's LDR-FLIP (Andersson et al. 2020, package ``flip-evaluator``): the mean
  of its per-pixel error map, the error a viewer sees when flipping between the two images
  (0 identical, 1 the largest; lower is better). No learned weights; the package's viewing
  condition (about 67 pixels per degree) unless ``ppd`` is given.
* :func:`lpips`: LPIPS (AlexNet variant, Zhang et al. 2018) from **local** weights only.
  Nothing is downloaded: without a weights file, :func:`lpips_available` is False and
  :func:`lpips` raises :class:`LPIPSUnavailableError` saying what file to supply.

All take floating-point ``(B, C, H, W)`` (or one ``(C, H, W)`` image) in [0, max_val], H, W >= 1,
and return ``(B,)``. Integer and bool images raise :class:`~roguenerf.errors.InputError`
with the conversion (:mod:`roguenerf.images`).
"""

from __future__ import annotations

import os
from pathlib import Path

import kornia
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from roguenerf.errors import InputError
from roguenerf.images import check_float_image

LPIPS_WEIGHTS_ENV = "ROGUENERF_LPIPS_WEIGHTS"
"""Environment variable naming a default LPIPS weights file."""


def _pair(a: Tensor, b: Tensor, name: str) -> tuple[Tensor, Tensor]:
    if not isinstance(a, Tensor) or not isinstance(b, Tensor):
        raise InputError(f"{name}: expected two tensors, got {type(a).__name__} and {type(b).__name__}")
    if a.ndim == 3:
        a, b = a[None], b[None] if b.ndim == 3 else b
    if a.ndim != 4 or a.shape != b.shape:
        raise InputError(f"{name}: expected two (B, C, H, W) tensors of the same shape, "
                         f"got {tuple(a.shape)} and {tuple(b.shape)}")
    if 0 in a.shape:
        raise InputError(f"{name}: expected non-empty images (B, C, H, W >= 1), got size {tuple(a.shape)}")
    check_float_image(a, f"{name}: first image")
    check_float_image(b, f"{name}: second image")
    return a, b


def psnr(a: Tensor, b: Tensor, *, max_val: float = 1.0) -> Tensor:
    """Peak signal-to-noise ratio of each image pair, in dB.

    Args:
        a, b: ``(B, C, H, W)`` (or ``(C, H, W)``) in [0, max_val].
    Returns:
        ``(B,)``; ``inf`` for identical images.
    """
    a, b = _pair(a, b, "psnr")
    mse = (a - b).pow(2).flatten(1).mean(dim=1)
    return 10.0 * torch.log10(max_val**2 / mse)


def ssim_window(window_size: int, height: int, width: int) -> int:
    """The window :func:`ssim` uses on an ``height x width`` image: ``min(window_size, 2 m - 1)``
    with ``m = min(height, width)``, the largest odd window whose reflect padding
    (``window // 2`` pixels) fits inside the image."""
    return min(window_size, 2 * min(height, width) - 1)


def ssim(a: Tensor, b: Tensor, *, window_size: int = 11, max_val: float = 1.0) -> Tensor:
    """Structural similarity of each image pair: mean of kornia's SSIM map per image.

    Args:
        a, b: ``(B, C, H, W)`` (or ``(C, H, W)``) in [0, max_val], any H, W >= 1.
        window_size: odd number of Gaussian taps (sigma 1.5); on images smaller than the window
            it shrinks to :func:`ssim_window` (``min(window_size, 2 min(H, W) - 1)``).
    Returns:
        ``(B,)``.
    """
    a, b = _pair(a, b, "ssim")
    if isinstance(window_size, bool) or not isinstance(window_size, int) or window_size < 1 or window_size % 2 == 0:
        raise InputError(f"ssim: window_size must be an odd integer >= 1, got {window_size!r}")
    window = ssim_window(window_size, a.shape[-2], a.shape[-1])
    return kornia.metrics.ssim(a, b, window_size=window, max_val=max_val).flatten(1).mean(dim=1)


# -- FLIP ---------------------------------------------------------------------------------

class FLIPUnavailableError(InputError):
    """The ``flip-evaluator`` package is not installed."""


def _flip_module():
    try:
        import flip_evaluator
    except ImportError:
        raise FLIPUnavailableError(
            "FLIP is unavailable: the flip-evaluator package is not installed "
            "(pip install flip-evaluator, a dependency of roguenerf)") from None
    return flip_evaluator


def flip_available() -> bool:
    """True when the ``flip-evaluator`` package can be imported."""
    try:
        _flip_module()
    except FLIPUnavailableError:
        return False
    return True


def flip(a: Tensor, b: Tensor, *, ppd: float | None = None) -> Tensor:
    """Mean LDR-FLIP error of each image pair (lower is better): ``a`` the test image (a render,
    an enhanced render), ``b`` the reference (the photo). Not symmetric.

    Args:
        a, b: ``(B, 3, H, W)`` (or ``(3, H, W)``) sRGB in [0, 1]; values outside are clamped.
        ppd: viewing condition in pixels per degree of visual angle; None: the package's default
            (about 67: a 0.7 m wide 4K monitor seen from 0.7 m).
    Returns:
        ``(B,)`` float32 in [0, 1]; 0 for identical images. Raises
        :class:`FLIPUnavailableError` without the ``flip-evaluator`` package.
    """
    a, b = _pair(a, b, "flip")
    if a.shape[1] != 3:
        raise InputError(f"flip: expected RGB images (B, 3, H, W), got {tuple(a.shape)}")
    if ppd is not None and not (isinstance(ppd, (int, float)) and not isinstance(ppd, bool)
                                and 0 < ppd < float("inf")):
        raise InputError(f"flip: ppd must be a positive number of pixels per degree, got {ppd!r}")
    parameters = {} if ppd is None else {"ppd": float(ppd)}
    module = _flip_module()

    def hwc(x: Tensor) -> np.ndarray:
        return np.ascontiguousarray(x.detach().to("cpu", torch.float32).clamp(0, 1).permute(1, 2, 0).numpy())

    out = []
    for test, ref in zip(a, b, strict=True):
        _, mean, _ = module.evaluate(hwc(ref), hwc(test), "LDR", applyMagma=False, computeMeanError=True,
                                     parameters=parameters)
        out.append(float(mean))
    return torch.tensor(out, dtype=torch.float32)


# -- LPIPS --------------------------------------------------------------------------------


class LPIPSUnavailableError(InputError):
    """No local LPIPS weights were given (they are never downloaded)."""


_ALEX_CONVS = ((3, 64, 11, 4, 2), (64, 192, 5, 1, 2), (192, 384, 3, 1, 1), (384, 256, 3, 1, 1), (256, 256, 3, 1, 1))
_ALEX_INDEX = (0, 3, 6, 8, 10)
"""Positions of the convolutions in torchvision's ``alexnet().features`` (state-dict keys)."""


class _LPIPSAlex(nn.Module):
    """LPIPS v0.1, AlexNet backbone: the layout of the ``lpips`` package and torchvision keys."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1))
        self.convs = nn.ModuleList(nn.Conv2d(i, o, k, stride=s, padding=p) for i, o, k, s, p in _ALEX_CONVS)
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in (64, 192, 384, 256, 256))

    def features(self, x: Tensor) -> list[Tensor]:
        x = (x - self.shift) / self.scale
        taps = []
        for n, conv in enumerate(self.convs):
            if n in (1, 2):
                x = F.max_pool2d(x, 3, 2)
            x = F.relu(conv(x))
            taps.append(x)
        return taps

    def forward(self, a: Tensor, b: Tensor) -> Tensor:
        total = a.new_zeros(a.shape[0])
        for fa, fb, lin in zip(self.features(a), self.features(b), self.lins):
            na = fa / (fa.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            nb = fb / (fb.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            total = total + lin((na - nb).pow(2)).mean(dim=(1, 2, 3))
        return total

    def load_weights(self, state: dict[str, Tensor], source: str) -> None:
        mapping = {}
        for n, idx in enumerate(_ALEX_INDEX):
            mapping[f"convs.{n}.weight"] = (f"features.{idx}.weight", f"net.slice{n + 1}.{idx}.weight")
            mapping[f"convs.{n}.bias"] = (f"features.{idx}.bias", f"net.slice{n + 1}.{idx}.bias")
            mapping[f"lins.{n}.weight"] = (f"lin{n}.model.1.weight", f"lins.{n}.model.1.weight")
        own = self.state_dict()
        loaded = {}
        missing = []
        for key, aliases in mapping.items():
            found = next((state[a] for a in aliases if a in state), None)
            if found is None:
                missing.append(aliases[0])
                continue
            if tuple(found.shape) != tuple(own[key].shape):
                raise InputError(f"{source}: LPIPS tensor {aliases[0]} has shape {tuple(found.shape)}, "
                                 f"expected {tuple(own[key].shape)}")
            loaded[key] = found.float()
        if missing:
            raise InputError(
                f"{source}: LPIPS weights incomplete, missing {missing} (expected torchvision alexnet "
                "'features.*' and lpips 'lin*.model.1.weight' tensors)"
            )
        self.load_state_dict({**own, **loaded})


_LPIPS_CACHE: dict[tuple[str, ...], _LPIPSAlex] = {}


def _weights_files(weights) -> tuple[str, ...]:
    if weights is None:
        env = os.environ.get(LPIPS_WEIGHTS_ENV)
        if not env:
            return ()
        weights = env.split(os.pathsep)
    if isinstance(weights, (str, os.PathLike)):
        weights = [weights]
    return tuple(str(Path(w)) for w in weights)


def lpips_available(weights=None) -> bool:
    """True when LPIPS weights are at hand (``weights`` files, or ``$ROGUENERF_LPIPS_WEIGHTS``)."""
    files = _weights_files(weights)
    return bool(files) and all(Path(f).is_file() for f in files)


def _read_state(path: str) -> dict[str, Tensor]:
    if path.endswith(".safetensors"):
        from safetensors import SafetensorError
        from safetensors.torch import load_file

        try:
            return load_file(path)
        except (SafetensorError, OSError) as exc:
            raise InputError(f"{path}: not a readable safetensors file ({exc})") from None
    try:
        # weights_only: the restricted unpickler that builds tensors and never runs code
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any failure of a foreign file is an input error
        raise InputError(f"{path}: cannot read LPIPS weights ({exc})") from None
    if not isinstance(state, dict):
        raise InputError(f"{path}: expected a state dict, got {type(state).__name__}")
    return state


def load_lpips(weights=None) -> nn.Module:
    """The LPIPS (AlexNet) network with weights from local files (never downloaded).

    Args:
        weights: a file or list of files (``.safetensors``, or torchvision / ``lpips``
            ``.pth`` state dicts, read with ``weights_only=True``) together holding the
            AlexNet ``features.*`` tensors and the ``lin{0..4}.model.1.weight`` tensors;
            None reads ``$ROGUENERF_LPIPS_WEIGHTS`` (paths separated by ``os.pathsep``).
    """
    files = _weights_files(weights)
    if not files:
        raise LPIPSUnavailableError(
            "LPIPS is unavailable: no weights given and weights are never downloaded. Pass "
            "weights=[alexnet.pth, lpips_alex.pth] (torchvision AlexNet + lpips linear layers) or "
            f"set ${LPIPS_WEIGHTS_ENV}"
        )
    for f in files:
        if not Path(f).is_file():
            raise LPIPSUnavailableError(f"LPIPS is unavailable: weights file {f} not found")
    if files not in _LPIPS_CACHE:
        state: dict[str, Tensor] = {}
        for f in files:
            state.update(_read_state(f))
        net = _LPIPSAlex()
        net.load_weights(state, ", ".join(files))
        _LPIPS_CACHE[files] = net.eval().requires_grad_(False)
    return _LPIPS_CACHE[files]


def lpips(a: Tensor, b: Tensor, *, weights=None) -> Tensor:
    """LPIPS distance of each image pair (lower is closer).

    Args:
        a, b: ``(B, 3, H, W)`` (or ``(3, H, W)``) in [0, 1].
        weights: see :func:`load_lpips`.
    Returns:
        ``(B,)``. Raises :class:`LPIPSUnavailableError` without local weights.
    """
    a, b = _pair(a, b, "lpips")
    if a.shape[1] != 3:
        raise InputError(f"lpips: expected RGB images (B, 3, H, W), got {tuple(a.shape)}")
    net = load_lpips(weights).to(a.device)
    with torch.no_grad():
        return net(a.float() * 2 - 1, b.float() * 2 - 1)

"""The one image-dtype rule of the library: images are floating-point tensors in [0, 1].

Every entry point that takes an image tensor (``SceneEnhancer.enhance``, ``Enhancer.forward``
and ``encode_neighbours``, ``metrics.psnr`` / ``ssim`` / ``lpips``, ``write_scene_folder``,
``Degradation``, ``imageio.encode_png`` / ``write_png``) calls :func:`check_float_image`. Integer
and bool tensors (``uint8`` 0-255 as PIL / NumPy give them, ``int16``, masks) are **refused** with an
:class:`~roguenerf.errors.InputError` that names the argument, its dtype and the conversion:
they are never clamped or rescaled silently (clamping 0-255 to [0, 1] turned every pixel white).

Image *files* are converted by one documented rule instead, in
:func:`roguenerf.imageio.read_image` (8-bit ``/ 255``, 16-bit ``/ 65535``, bilevel 0/1): that is
what the CLI, the scene readers and the service's ``/enhance`` use, so an 8-bit, 16-bit or
1-bit PNG render gives the same result as the float image it encodes.
"""

from __future__ import annotations

from torch import Tensor

from roguenerf.errors import InputError


def conversion_hint(dtype) -> str:
    """How to turn an image of ``dtype`` (torch or NumPy) into a float image in [0, 1]."""
    name = str(dtype).removeprefix("torch.")
    if name == "bool":
        return "x.float() (False -> 0, True -> 1)"
    if name == "uint8":
        return "x.float() / 255"
    if name in ("int16", "uint16", "int32", "uint32", "int64", "uint64"):
        return "x.float() / 65535 for 16-bit images (x.float() / 255 for 8-bit values)"
    return "x.float() divided by the format's maximum value"


def float_image_error(name: str, dtype) -> InputError:
    """The :class:`InputError` for an image of non-float ``dtype`` (torch or NumPy)."""
    return InputError(
        f"{name}: expected a floating-point image with values in [0, 1], got dtype {dtype}; "
        f"convert it to float in [0, 1] first, e.g. {conversion_hint(dtype)} "
        "(integer images are refused, never clamped)"
    )


def check_float_image(x, name: str) -> Tensor:
    """Return ``x`` when it is a floating-point tensor; otherwise raise :class:`InputError`.

    The message names ``name``, the dtype and the conversion to float in [0, 1]. Shape and
    value checks stay with the caller.
    """
    if not isinstance(x, Tensor):
        raise InputError(f"{name}: expected a float torch.Tensor with values in [0, 1], got {type(x).__name__}")
    if not x.is_floating_point():
        raise float_image_error(name, x.dtype)
    return x

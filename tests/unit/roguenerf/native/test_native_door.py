"""The checked door to the C kernels (``roguenerf.native._call``).

Every kernel's Python wrapper is called with a float64 tensor and with a non-contiguous tensor
(a stepped view, neither row-major nor channels-last) in each argument it reads as given: the
call raises ``NativeArgumentError`` (an ``InputError``) naming the kernel, the argument, what
was expected and what came, and no kernel runs. The same calls in a child process show that
the process survives them (a kernel reading the wrong memory could kill it), and the good
inputs of every case do run, so the door does not refuse everything.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch
from torch import nn

from roguenerf import native
from roguenerf.errors import InputError
from roguenerf.models.layers import PixelAttention
from roguenerf.models.uformer import LeFF, WindowAttention
from roguenerf.native import NativeArgumentError
from tests.model_helpers import KernelCalls

ROOT = Path(__file__).resolve().parents[4]
CL = "channels-last"


def _t(*shape: int, cl: bool = False) -> torch.Tensor:
    x = torch.rand(*shape, generator=torch.Generator().manual_seed(sum(shape)))
    return x.contiguous(memory_format=torch.channels_last) if cl else x


def _strided(x: torch.Tensor) -> torch.Tensor:
    """``x``'s values in a view with every second element of the last dimension: same shape,
    neither contiguous nor channels-last."""
    wide = torch.zeros(*x.shape[:-1], 2 * x.shape[-1], dtype=x.dtype)
    wide[..., ::2] = x
    view = wide[..., ::2]
    assert not view.is_contiguous() and not view.is_contiguous(memory_format=torch.channels_last)
    return view


_PA = PixelAttention(features=16, hidden=8)
_LN8 = nn.LayerNorm(8)
_LN16 = nn.LayerNorm(16)
_ATTN = WindowAttention(dim=16, heads=2, win_size=4)
_LEFF = LeFF(dim=8, hidden=32)
_BIAS = torch.rand(2, 16, 16)
_WEIGHT = torch.rand(8, 5, 3, 3)

# kernel -> (call with the tensors as keywords, the good tensors, the layout each is read in)
KERNELS = {
    "reproject": (
        lambda **a: native.reproject(**a, eps=1e-6, max_depth=1e10, leniency=0.25),
        lambda: dict(depth=_t(1, 1, 6, 8), rows=_t(1, 3, 6), cols=_t(1, 3, 8), offset=_t(1, 3),
                     source=_t(1, 5, 6, 8, cl=True)),
        {"source": CL}),
    "flow_warp": (
        lambda **a: native.flow_warp(**a, depth_channel=16, depth_max=10.0),
        lambda: dict(x=_t(2, 18, 16, 16, cl=True), flow_low=_t(2, 2, 2, 2), depth_scale=_t(2) + 0.5),
        {"x": CL}),
    "pool8": (
        lambda **a: native.pool8(**a, channels=16),
        lambda: dict(x=_t(2, 18, 16, 24, cl=True)),
        {"x": CL}),
    "attend_pool": (
        lambda **a: native.attend_pool(conv=_PA.net[2], slope=0.01, features=16, pooled=None, low=None, spread=True,
                                       **a),
        lambda: dict(hidden=_t(2, 8, 5, 7, cl=True), term=_t(2, 8, 5, 7, cl=True), camera=_t(2, 1),
                     buf=_t(2, 18, 5, 7, cl=True)),
        {"hidden": CL, "term": CL, "buf": CL}),
    "ln_partition": (
        lambda **a: native.ln_partition(**a, norm=_LN8, win=4, shift=2),
        lambda: dict(x=_t(1, 8, 8, 8)),
        {}),
    "merge_ln": (
        lambda **a: native.merge_ln(**a, norm=_LN8, win=4, shift=2),
        lambda: dict(x=_t(1, 8, 8, 8), tokens=_t(4, 16, 8)),
        {}),
    "window_attention": (
        lambda **a: native.window_attention(**a, bias=_BIAS, heads=2, scale=0.25),
        lambda: dict(qkv=_t(8, 16, 48), mask=_t(4, 16, 16)),
        {}),
    "lewin_attention": (
        lambda **a: native.lewin_attention(**a, norm1=_LN16, attn=_ATTN, norm2=_LN16, shift=2),
        lambda: dict(x=_t(1, 8, 8, 16), mask=_t(4, 16, 16)),
        {}),
    "leff": (
        lambda **a: native.leff(**a, module=_LEFF),
        lambda: dict(x=_t(1, 5, 7, 8), residual=_t(1, 5, 7, 8)),
        {}),
    "conv3x3": (
        lambda **a: native.conv3x3(**a, weight=_WEIGHT),
        lambda: dict(x=_t(1, 5, 6, 7, cl=True), bias=_t(8)),
        {"x": CL}),
}

# Arguments a wrapper packs itself (a copy in the kernel's layout): only their dtype is checked.
PACKED = {("conv3x3", "bias")}

CASES = [(kernel, name, fault) for kernel, (_, good, _) in KERNELS.items() for name in good()
         for fault in ("float64", "strided") if not (fault == "strided" and (kernel, name) in PACKED)]


def _broken(kernel: str, name: str, fault: str) -> tuple[dict, str]:
    """The good tensors of ``kernel`` with ``name`` broken by ``fault``, and the message part
    the error must carry."""
    call, good, layouts = KERNELS[kernel]
    args = good()
    if fault == "float64":
        args[name] = args[name].double()
        return args, "expected dtype torch.float32, got torch.float64"
    args[name] = _strided(args[name])
    return args, f"expected a {layouts.get(name, 'contiguous')} tensor"


@pytest.mark.parametrize("kernel, name, fault", CASES)
def test_a_wrong_tensor_is_refused_before_the_kernel_runs(kernel, name, fault):
    args, expected = _broken(kernel, name, fault)
    with torch.inference_mode(), KernelCalls() as calls, pytest.raises(NativeArgumentError) as info:
        KERNELS[kernel][0](**args)
    message = str(info.value)
    assert isinstance(info.value, InputError)
    assert f"roguenerf.native.rg_{kernel}" in message or f"roguenerf.native.{kernel}" in message, message
    assert f"argument {name!r}" in message and expected in message, message
    assert calls.names == []


@pytest.mark.parametrize("kernel", list(KERNELS))
def test_the_good_tensors_pass_the_door(kernel):
    """Control: each case's unbroken inputs run the kernel (where its sizes are supported)."""
    call, good, _ = KERNELS[kernel]
    if kernel == "leff" and not native.leff_supported(8, 32):  # 4-lane builds: refused by size, by name
        with pytest.raises(NativeArgumentError, match="a supported channel count"):
            call(**good())
        return
    with torch.inference_mode(), KernelCalls() as calls:
        call(**good())
    assert calls.names == [kernel]


def test_shape_and_device_faults_name_what_was_expected():
    good = KERNELS["reproject"][1]()
    with pytest.raises(NativeArgumentError, match=r"argument 'rows': expected shape \(1, 3, 6\), got \(1, 3, 5\)"):
        native.reproject(**{**good, "rows": _t(1, 3, 5)}, eps=1e-6, max_depth=1e10, leniency=0.25)
    meta = torch.empty(1, 3, device="meta")
    with pytest.raises(NativeArgumentError, match="argument 'offset': expected a CPU tensor, got device meta"):
        native.reproject(**{**good, "offset": meta}, eps=1e-6, max_depth=1e10, leniency=0.25)
    with pytest.raises(NativeArgumentError, match=r"pool8: expected channels within the input channels"):
        native.pool8(_t(1, 4, 8, 8, cl=True), 5)
    with pytest.raises(NativeArgumentError, match="rg_pool8: argument 1 must be a tensor, got int"):
        native._call("rg_pool8", native._arg("x", _t(1, 4, 8, 8, cl=True), (1, 4, 8, 8), layout="channels_last"),
                     0, 1, 8, 8, 4, 4, 1)


def run_all() -> int:
    """Every refused call in this process (for the child-process test); returns their count."""
    for kernel, name, fault in CASES:
        args, _ = _broken(kernel, name, fault)
        try:
            with torch.inference_mode():
                KERNELS[kernel][0](**args)
        except NativeArgumentError:
            continue
        raise AssertionError(f"{kernel} accepted {name} ({fault})")
    return len(CASES)


def test_the_process_survives_every_refused_call():
    code = "from tests.unit.roguenerf.native.test_native_door import run_all\nprint('refused', run_all())"
    run = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.split()[-2:] == ["refused", str(len(CASES))]

"""Fused C kernels for the CPU inference fast path, compiled on first use.

Much of the fast path's time went to chains of cheap steps, each a pass over memory in torch
(``bench/stages.py``). ``kernels.c`` does each chain in one pass:

* the reprojection: projection, 4-tap sampling, visibility test and masking
  (:mod:`roguenerf.reprojection`);
* the flow's 1/8 average pool, and its upsampling + warp + depth normalisation
  (:mod:`roguenerf.models.flow`, the enhancer);
* the pixel attention's first convolution (17 -> 8 channels, reading the packed buffer in
  place), then the rest of it, the weighting and the max / min pooling;
* the LeWin block's attention half window by window in one pass (LayerNorm, roll, window
  partition, the qkv linear, the 4 x 4 window attention, the output linear, merge, residual and
  the next LayerNorm; for channel counts it does not take, LayerNorm + roll + partition, the
  window attention and merge + roll + residual + LayerNorm as three kernels), its
  feed-forward (LeFF: linear, GELU, depthwise 3 x 3 convolution, GELU, linear, residual) with
  the hidden maps kept in cache (:mod:`roguenerf.models.uformer`); and the Uformer's 3 x 3
  output projection.

The kernels use vectors of the CPU's own width (:func:`vector_width`: 16 float lanes with
AVX-512, 8 with AVX, 4 without): GCC compiles comparisons of wider vectors lane by lane, which
once made the 16-lane kernels slower than torch on AVX2 machines.

Where a decision depends on rounding (the projection's inside and visibility tests) the kernels
do the torch fast path's float32 operations in its order, unfused; the attention and the LeFF
may fuse multiply-adds, as oneDNN does, and the LeFF's GELU evaluates erf by a rational
approximation (error below 1e-7, as oneDNN's own is an approximation). The callers use a kernel
only where the torch fast path would run (no gradient, float32, CPU; never in
``reference_mode()`` or :func:`disabled`; :mod:`roguenerf.ops` chooses). Results agree with the
plain implementation to float32 rounding (``tests/unit/roguenerf/native/test_native.py``).

Every kernel is called through one door, :func:`_call`: before the ctypes call it checks each
tensor argument's dtype (float32), device (CPU), layout (row-major, or channels-last where the
kernel reads NHWC buffers) and shape against what the kernel reads, and that tensors stand
where the signature table has pointers; a mismatch raises :class:`NativeArgumentError` (an
:class:`~roguenerf.errors.InputError`) naming the kernel, the argument, what was expected and
what came, instead of letting the kernel read or write the wrong memory. The wrappers do not
copy the caller's tensors into shape: :mod:`roguenerf.ops` prepares the layouts.

Nothing is shipped pre-built: the first call compiles ``kernels.c`` with the system C compiler
(``$CC``, else ``cc``/``gcc``/``clang``; -O3, -march=native and OpenMP where the compiler has
them) into ``$ROGUENERF_NATIVE_CACHE`` (default ``~/.cache/roguenerf/native``), named by a hash
of the source, the compiler, the flags and this CPU, written atomically (concurrent processes
are safe). It takes about 3 s on this project's 2-core machine (the service starts it at
start-up). Without a compiler, or when the build fails, a warning is logged once and the torch
fast path runs instead (same results, slower). ``ROGUENERF_NATIVE=0`` turns the kernels off.

Dimension letters: B batch, (H, W) target size, (Hs, Ws) neighbour size, Cs channels of a
sampling source or packed buffer (features, depth, mask), F feature channels, (h, w) = 1/8 size.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import logging
import os
import platform
import shutil
import subprocess
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from roguenerf import profiling
from roguenerf.errors import InputError
from roguenerf.fastpath import fast_enabled, switched, thread_switch

log = logging.getLogger(__name__)

SOURCE = Path(__file__).with_name("kernels.c")
BASE_FLAGS = ["-O3", "-std=gnu11", "-fPIC", "-shared", "-ffp-contract=off", "-fno-math-errno"]
FLAG_SETS = (["-march=native", "-fopenmp"], ["-fopenmp"], ["-march=native"], [])
"""Tried in order: a compiler without OpenMP (Apple clang) or without -march=native still
builds the kernels (single-threaded without OpenMP)."""

_i64, _f32, _int, _p = ctypes.c_int64, ctypes.c_float, ctypes.c_int, ctypes.c_void_p
_SIGNATURES = {
    "rg_reproject": (None, [_p, _p, _p, _p, _p, _p, _p, _i64, _i64, _i64, _i64, _i64, _i64,
                            _f32, _f32, _f32, _int]),
    "rg_flow_warp": (_i64, [_p, _p, _p, _i64, _i64, _i64, _i64, _i64, _i64, _p, _i64, _f32, _int]),
    "rg_pool8": (None, [_p, _p, _i64, _i64, _i64, _i64, _i64, _int]),
    "rg_ln_partition": (None, [_p, _p, _p, _p, _f32, _i64, _i64, _i64, _i64, _i64, _i64, _int]),
    "rg_merge_ln": (None, [_p, _p, _p, _p, _p, _p, _f32, _i64, _i64, _i64, _i64, _i64, _i64, _int]),
    "rg_window_attention16": (None, [_p, _p, _p, _p, _i64, _i64, _i64, _i64, _f32, _int]),
    "rg_attend_pool": (_int, [_p, _p, _p, _f32, _f32, _p, _p, _p, _p, _i64, _i64, _i64, _i64, _i64, _i64,
                              _int, _int]),
    "rg_vector_width": (_int, []),
    "rg_conv3x3": (None, [_p, _p, _p, _p, _i64, _i64, _i64, _i64, _i64, _i64, _int]),
    "rg_leff": (_int, [_p, _p, _p, _p, _p, _p, _p, _p, _p, _i64, _i64, _i64, _i64, _i64, _int]),
    "rg_gauss_newton": (None, [_p, _p, _p, _p, _p, _p, _f32, _i64, _p, _int]),
    "rg_lewin_attention": (_int, [_p, _p, _p, _p, _p, _f32, _p, _p, _p, _p, _p, _p, _p, _p, _f32,
                                  _i64, _i64, _i64, _i64, _i64, _i64, _f32, _int]),
}


def cache_dir() -> Path:
    from roguenerf.runtime import user_cache_dir

    return user_cache_dir("native", "ROGUENERF_NATIVE_CACHE")


def compiler() -> str | None:
    """The C compiler to use: ``$CC``, else the first of cc, gcc, clang on PATH (None: none)."""
    for name in (os.environ.get("CC"), "cc", "gcc", "clang"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def _cpu_id() -> str:
    """What -march=native depends on: the CPU's model and feature flags (Linux), else the platform."""
    try:
        info = Path("/proc/cpuinfo").read_text()
        lines = [ln for ln in info.splitlines() if ln.startswith(("model name", "flags", "Features"))]
        return "\n".join(sorted(set(lines)))
    except OSError:
        return platform.processor() + platform.machine()


def _build(cc: str) -> Path | None:
    source = SOURCE.read_bytes()
    try:
        version = subprocess.run([cc, "--version"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError) as exc:
        log.warning("roguenerf.native: %s does not run (%s); using the torch fast path", cc, exc)
        return None
    errors = []
    cpu = _cpu_id().encode()
    for extra in FLAG_SETS:
        flags = BASE_FLAGS + extra
        key = hashlib.sha256(b"\0".join([source, version.encode(), " ".join(flags).encode(), cpu])).hexdigest()[:16]
        target = cache_dir() / f"kernels-{key}.so"
        if target.exists():
            return target
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(suffix=".so", dir=target.parent)
        os.close(fd)
        try:
            run = subprocess.run([cc, *flags, str(SOURCE), "-o", tmp, "-lm"], capture_output=True,
                                 text=True, timeout=300)
            if run.returncode == 0:
                os.replace(tmp, target)  # atomic: a concurrent build writes the same bytes
                return target
            errors.append(f"{' '.join(extra) or 'plain'}: {run.stderr.strip()[-500:]}")
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
    log.warning("roguenerf.native: %s could not build the kernels:\n%s", cc, "\n".join(errors))
    return None


@functools.lru_cache(maxsize=1)
def library() -> ctypes.CDLL | None:
    """The compiled kernels (built on the first call), or None: turned off, no compiler, or the
    build failed (logged once)."""
    if os.environ.get("ROGUENERF_NATIVE", "1").strip().lower() in ("0", "false", "no", "off"):
        return None
    cc = compiler()
    if cc is None:
        log.warning("roguenerf.native: no C compiler found (set CC or install gcc); "
                    "using the slower torch fast path")
        return None
    try:
        path = _build(cc)
        if path is None:
            return None
        lib = ctypes.CDLL(str(path))
        for name, (restype, argtypes) in _SIGNATURES.items():
            fn = getattr(lib, name)
            fn.restype, fn.argtypes = restype, argtypes
        return lib
    except OSError as exc:  # unwritable cache, a library that does not load
        log.warning("roguenerf.native: kernels unavailable (%s); using the torch fast path", exc)
        return None


on_call: Callable[[str, int], None] | None = None
"""If set, called after every kernel with its name and the bytes of the tensors it read and
wrote (``bench/stages.py`` adds them to its per-stage byte counts)."""


def disabled(off: bool = True):
    """Inside: the kernels are not used in this thread (the torch fast path runs). Nestable."""
    return thread_switch("native_off", off)


def is_disabled() -> bool:
    """Inside :func:`disabled` in this thread."""
    return switched("native_off")


def enabled(x: Tensor) -> bool:
    """The kernels apply to ``x``: the torch fast path would run (not reference mode, no
    gradient, float32 CPU), they are not :func:`disabled`, and they are built."""
    return fast_enabled(x) and not is_disabled() and library() is not None


def _account(name: str, *tensors: Tensor | None) -> None:
    if on_call is not None:
        on_call(name, sum(t.numel() * t.element_size() for t in tensors if t is not None))


def _threads() -> int:
    return max(1, torch.get_num_threads())


class NativeArgumentError(InputError):
    """A tensor (or size) handed to a C kernel is not what the kernel reads: wrong dtype, not on
    the CPU, not in the expected memory layout, or of the wrong shape. Raised by :func:`_call`
    before the kernel runs, instead of letting it read or write the wrong memory."""


@dataclass(frozen=True)
class _Arg:
    """A tensor argument of a kernel, with what the kernel expects of it (see :func:`_arg`)."""

    name: str
    tensor: Tensor | None
    shape: tuple[int | None, ...]
    layout: str
    optional: bool


def _arg(name: str, tensor: Tensor | None, shape: tuple[int | None, ...], *, layout: str = "contiguous",
         optional: bool = False) -> _Arg:
    """A float32 CPU tensor argument for :func:`_call`: ``shape`` its sizes (None: any),
    ``layout`` "contiguous" (row-major) or "channels_last" (a 4-D NHWC buffer), ``optional``: it
    may be None (a NULL pointer)."""
    return _Arg(name, tensor, tuple(shape), layout, optional)


def _pointer(kernel: str, arg: _Arg) -> int | None:
    """``arg``'s data pointer, after checking its dtype, device, shape and layout."""
    x, where = arg.tensor, f"roguenerf.native.{kernel}: argument {arg.name!r}"
    if x is None:
        if arg.optional:
            return None
        raise NativeArgumentError(f"{where}: expected a tensor, got None")
    if not isinstance(x, Tensor):
        raise NativeArgumentError(f"{where}: expected a tensor, got {type(x).__name__}")
    if x.dtype != torch.float32:
        raise NativeArgumentError(f"{where}: expected dtype torch.float32, got {x.dtype}")
    if x.device.type != "cpu":
        raise NativeArgumentError(f"{where}: expected a CPU tensor, got device {x.device}")
    if x.ndim != len(arg.shape) or any(want is not None and got != want
                                       for got, want in zip(x.shape, arg.shape, strict=True)):
        want = "(" + ", ".join("*" if d is None else str(d) for d in arg.shape) + ")"
        raise NativeArgumentError(f"{where}: expected shape {want}, got {tuple(x.shape)}")
    if arg.layout == "channels_last":
        ok = x.ndim == 4 and x.is_contiguous(memory_format=torch.channels_last)
    else:
        ok = x.is_contiguous()
    if not ok:
        raise NativeArgumentError(f"{where}: expected a {arg.layout.replace('_', '-')} tensor, got shape "
                                  f"{tuple(x.shape)} with strides {x.stride()}")
    return x.data_ptr()


def _call(kernel: str, *args):
    """The one door to the kernels: ``library().<kernel>(*args)`` after checking every tensor
    argument (given as :func:`_arg`; each becomes its data pointer) and that tensors stand
    exactly where the kernel's signature has pointers. Raises :class:`NativeArgumentError`
    before the call on any mismatch."""
    _, argtypes = _SIGNATURES[kernel]
    if len(args) != len(argtypes):
        raise NativeArgumentError(f"roguenerf.native.{kernel}: expected {len(argtypes)} arguments, got {len(args)}")
    values = []
    for i, (value, kind) in enumerate(zip(args, argtypes, strict=True)):
        if (kind is _p) != isinstance(value, _Arg):
            raise NativeArgumentError(f"roguenerf.native.{kernel}: argument {i} must be "
                                      f"{'a tensor' if kind is _p else 'a number'}, got {type(value).__name__}")
        values.append(_pointer(kernel, value) if kind is _p else value)
    return getattr(library(), kernel)(*values)


def _sizes(kernel: str, **checks: bool) -> None:
    """Raise :class:`NativeArgumentError` naming the first of ``checks`` (a size relation the
    kernel relies on, by name) that is False."""
    for name, ok in checks.items():
        if not ok:
            raise NativeArgumentError(f"roguenerf.native.{kernel}: expected {name.replace('_', ' ')}")


def _norm_args(prefix: str, norm: torch.nn.LayerNorm, c: int) -> tuple[_Arg, _Arg]:
    return (_arg(f"{prefix}.weight", norm.weight.detach(), (c,)), _arg(f"{prefix}.bias", norm.bias.detach(), (c,)))


def reproject(depth: Tensor, rows: Tensor, cols: Tensor, offset: Tensor, source: Tensor, *,
              eps: float, max_depth: float, leniency: float) -> tuple[Tensor, Tensor]:
    """One neighbour into B targets: ``depth`` ``(B, 1, H, W)``, the projection's per-row
    ``(B, 3, H)`` and per-column ``(B, 3, W)`` terms and ``offset`` ``(B, 3)`` (float32,
    contiguous, from :func:`roguenerf.ops.reproject.projection_terms`), ``source``
    ``(B, Cs, Hs, Ws)`` channels-last -> the packed ``(B, Cs, H, W)`` channels-last buffer
    [features * valid, depth, valid] and ``coords`` ``(B, H, W, 2)``."""
    b, cs, hs, ws = source.shape
    h, w = depth.shape[-2:]
    out = torch.empty(b, cs, h, w, memory_format=torch.channels_last)
    coords = torch.empty(b, h, w, 2)
    _call("rg_reproject", _arg("depth", depth, (b, 1, h, w)), _arg("rows", rows, (b, 3, h)),
          _arg("cols", cols, (b, 3, w)), _arg("offset", offset, (b, 3)),
          _arg("source", source, (b, cs, hs, ws), layout="channels_last"),
          _arg("out", out, (b, cs, h, w), layout="channels_last"), _arg("coords", coords, (b, h, w, 2)),
          b, h, w, hs, ws, cs, eps, max_depth, 1.0 + leniency, _threads())  # ctypes rounds it to float32, as torch
    _account("reproject", depth, source, out, coords)
    return out, coords


def flow_warp(x: Tensor, flow_low: Tensor, *, depth_scale: Tensor | None = None, depth_channel: int = 0,
              depth_max: float = 0.0) -> Tensor | None:
    """``flow_warp(x, upsample_flow(flow_low, H, W))`` in one pass: ``x`` ``(B, Cs, H, W)``
    channels-last, ``flow_low`` ``(B, 2, h, w)`` -> ``(B, Cs, H, W)`` channels-last. With
    ``depth_scale`` ``(B,)``, channel ``depth_channel`` of the result is then
    ``clamp(v / scale, 0, depth_max)``. None where a sample coordinate is not finite (the
    caller takes the torch path)."""
    b, cs, h, w = x.shape
    _sizes("flow_warp", depth_channel_within_the_channels=depth_scale is None or 0 <= depth_channel < cs)
    out = torch.empty(b, cs, h, w, memory_format=torch.channels_last)
    bad = _call("rg_flow_warp", _arg("x", x, (b, cs, h, w), layout="channels_last"),
                _arg("flow_low", flow_low, (b, 2, None, None)), _arg("out", out, (b, cs, h, w), layout="channels_last"),
                b, h, w, cs, flow_low.shape[-2], flow_low.shape[-1],
                _arg("depth_scale", depth_scale, (b,), optional=True), depth_channel, depth_max, _threads())
    _account("flow_warp", x, flow_low, out)
    return None if bad else out


def pool8(x: Tensor, channels: int) -> Tensor:
    """Edge-padded 8 x 8 average pool of the first ``channels`` channels: ``(B, Cs, H, W)``
    channels-last -> ``(B, channels, ceil(H / 8), ceil(W / 8))`` channels-last."""
    b, cs, h, w = x.shape
    _sizes("pool8", channels_within_the_input_channels=0 < channels <= cs)
    out = torch.empty(b, channels, -(-h // 8), -(-w // 8), memory_format=torch.channels_last)
    _call("rg_pool8", _arg("x", x, (b, cs, h, w), layout="channels_last"),
          _arg("out", out, (b, channels, None, None), layout="channels_last"), b, h, w, cs, channels, _threads())
    _account("pool8", x[:, :channels], out)
    return out


def attend_pool(hidden: Tensor, term: Tensor, conv: torch.nn.Conv2d, slope: float, camera: Tensor,
                buf: Tensor, features: int, pooled: Tensor | None, low: Tensor | None, *,
                spread: bool) -> tuple[Tensor, Tensor | None]:
    """The pixel attention after its first convolution, the weighting and the pooling, for one
    neighbour: ``psi = camera * sigmoid(conv(leaky_relu(hidden + term, slope)))``,
    ``a = buf[:, :features] * psi``, then ``pooled = max(pooled, a)`` and (``spread``)
    ``low = min(low, a)``, in place; ``pooled`` None starts both at ``a``.

    ``hidden``, ``term`` ``(B, Hd, H, W)`` channels-last; ``conv`` a 3 x 3 convolution Hd -> 1
    (zero padding); ``camera`` ``(B, 1)``; ``buf`` ``(B, Cs, H, W)`` channels-last. Returns
    ``(pooled, low)`` ``(B, features, H, W)`` channels-last (low None without ``spread``)."""
    b, hd, h, w = hidden.shape
    cs = buf.shape[1]
    _sizes("attend_pool", features_within_the_buffer_channels=0 < features <= cs,
           a_running_min_with_spread=pooled is None or (low is not None) == spread)
    weight = conv.weight.detach().reshape(hd, 9).contiguous()
    camera = camera.detach().reshape(b)
    first = pooled is None
    if first:
        pooled = torch.empty(b, features, h, w, memory_format=torch.channels_last)
        low = torch.empty(b, features, h, w, memory_format=torch.channels_last) if spread else None
    cl = "channels_last"
    if _call("rg_attend_pool", _arg("hidden", hidden, (b, hd, h, w), layout=cl),
             _arg("term", term, (b, hd, h, w), layout=cl), _arg("weight", weight, (hd, 9)),
             float(conv.bias.detach()[0]), slope, _arg("camera", camera, (b,)),
             _arg("buf", buf, (b, cs, h, w), layout=cl), _arg("pooled", pooled, (b, features, h, w), layout=cl),
             _arg("low", low, (b, features, h, w), layout=cl, optional=True),
             b, h, w, hd, cs, features, int(first), _threads()):
        raise MemoryError("roguenerf.native.attend_pool: out of memory for its row buffers")
    _account("attend_pool", hidden, term, buf[:, :features], pooled, low, *(() if first else (pooled, low)))
    profiling.add_flops(2 * 9 * hd * b * h * w)  # the Hd -> 1 convolution, as torch would count it
    return pooled, low


def ln_partition(x: Tensor, norm: torch.nn.LayerNorm, win: int, shift: int) -> Tensor:
    """A LeWin block's attention input: ``x`` ``(B, H, W, C)`` contiguous (H, W multiples of
    ``win``) -> windows of ``roll(norm(x), (-shift, -shift))``, ``(B * H/win * W/win, win * win, C)``."""
    b, h, w, c = x.shape
    _sizes("ln_partition", image_sides_multiples_of_the_window=win > 0 and h % win == 0 and w % win == 0)
    out = torch.empty(b * (h // win) * (w // win), win * win, c)
    _call("rg_ln_partition", _arg("x", x, (b, h, w, c)), _arg("out", out, tuple(out.shape)),
          *_norm_args("norm", norm, c), norm.eps, b, h, w, c, win, shift, _threads())
    _account("ln_partition", x, out)
    return out


def merge_ln(x: Tensor, tokens: Tensor, norm: torch.nn.LayerNorm, win: int, shift: int) -> tuple[Tensor, Tensor]:
    """The attention's windows back into the image with the residual, and the next LayerNorm:
    ``x + roll(merge(tokens), (shift, shift))`` and ``norm`` of it, both ``(B, H, W, C)``
    (``x``, ``tokens`` contiguous)."""
    b, h, w, c = x.shape
    _sizes("merge_ln", image_sides_multiples_of_the_window=win > 0 and h % win == 0 and w % win == 0)
    out, normed = torch.empty_like(x, memory_format=torch.contiguous_format), torch.empty(b, h, w, c)
    windows = b * (h // win) * (w // win)
    _call("rg_merge_ln", _arg("x", x, (b, h, w, c)), _arg("tokens", tokens, (windows, win * win, c)),
          _arg("out", out, (b, h, w, c)), _arg("normed", normed, (b, h, w, c)), *_norm_args("norm", norm, c),
          norm.eps, b, h, w, c, win, shift, _threads())
    _account("merge_ln", x, tokens, out, normed)
    return out, normed


def window_attention_supported(tokens: int, head_channels: int) -> bool:
    """:func:`window_attention` handles 4 x 4 windows with up to 64 channels per head."""
    return tokens == 16 and head_channels <= 64


def window_attention(qkv: Tensor, bias: Tensor, mask: Tensor | None, heads: int, scale: float) -> Tensor:
    """``softmax(scale * q k^T + bias [+ mask]) v`` per 16-token window and head: ``qkv``
    ``(WB, 16, 3 C)`` contiguous (channels q, k, v, each heads x d), ``bias`` ``(heads, 16, 16)``,
    ``mask`` ``(nW, 16, 16)`` contiguous (window ``w`` uses ``mask[w % nW]``) or None ->
    ``(WB, 16, C)`` (heads x d)."""
    wb, _, c3 = qkv.shape
    c = c3 // 3
    if mask is not None and wb % mask.shape[0]:
        raise NativeArgumentError(f"roguenerf.native.window_attention: {wb} windows are not a whole number of "
                                  f"images of {mask.shape[0]}")
    _sizes("window_attention", channels_three_times_heads_times_d=c3 == 3 * c and heads > 0 and c % heads == 0)
    bias_t = bias.detach().transpose(-1, -2).contiguous()  # the kernel's scores are transposed
    out = torch.empty(wb, 16, c)
    nw = mask.shape[0] if mask is not None else 1
    _call("rg_window_attention16", _arg("qkv", qkv, (wb, 16, 3 * c)), _arg("bias", bias_t, (heads, 16, 16)),
          _arg("mask", mask, (nw, 16, 16), optional=True), _arg("out", out, (wb, 16, c)),
          wb, nw, heads, c // heads, scale, _threads())
    _account("window_attention", qkv, out)
    profiling.add_flops(4 * wb * 16 * 16 * c)  # q k^T and p v, as torch counts attention
    return out


def lewin_attention_supported(win: int, channels: int, heads: int) -> bool:
    """:func:`lewin_attention` handles 4 x 4 windows, ``channels`` a multiple of 8 and up to 64
    channels per head."""
    return win == 4 and channels % 8 == 0 and channels % heads == 0 and channels // heads <= 64


def lewin_attention(x: Tensor, norm1: torch.nn.LayerNorm, attn: torch.nn.Module, mask: Tensor | None,
                    norm2: torch.nn.LayerNorm, shift: int) -> tuple[Tensor, Tensor]:
    """A LeWin block's attention half in one pass, window by window: ``x`` ``(B, H, W, C)``
    contiguous -> ``x + roll(merge(attn(partition(roll(norm1(x), -shift)), mask)), shift)`` and
    ``norm2`` of it (what :func:`ln_partition`, the attention's linears, :func:`window_attention`
    and :func:`merge_ln` compute in five passes). ``attn`` a
    :class:`roguenerf.models.uformer.WindowAttention` with 4 x 4 windows; ``mask`` ``(H/4 * W/4,
    16, 16)`` contiguous or None; see :func:`lewin_attention_supported`."""
    b, h, w, c = x.shape
    if mask is not None and mask.shape[0] != (h // 4) * (w // 4):
        raise NativeArgumentError(f"roguenerf.native.lewin_attention: a mask of {mask.shape[0]} windows for a "
                                  f"{h} x {w} image")
    _sizes("lewin_attention", image_sides_multiples_of_4=h % 4 == 0 and w % 4 == 0,
           a_supported_window_and_channel_count=lewin_attention_supported(attn.win_size, c, attn.heads))
    qkv, out, table = attn.to_qkv, attn.to_out, attn.relative_position_bias_table
    wqkv, bqkv, wout, bout, bias_t = _packed(attn, (qkv.weight, qkv.bias, out.weight, out.bias, table), lambda: (
        qkv.weight.t().contiguous(), qkv.bias.contiguous(), out.weight.t().contiguous(), out.bias.contiguous(),
        attn.bias().transpose(-1, -2).contiguous()))  # the kernel's scores are transposed
    x_out, normed = torch.empty(b, h, w, c), torch.empty(b, h, w, c)
    if _call("rg_lewin_attention", _arg("x", x, (b, h, w, c)), _arg("x_out", x_out, (b, h, w, c)),
             _arg("normed", normed, (b, h, w, c)), *_norm_args("norm1", norm1, c), norm1.eps,
             _arg("wqkv", wqkv, (c, 3 * c)), _arg("bqkv", bqkv, (3 * c,)), _arg("bias", bias_t, (attn.heads, 16, 16)),
             _arg("mask", mask, ((h // 4) * (w // 4), 16, 16), optional=True), _arg("wout", wout, (c, c)),
             _arg("bout", bout, (c,)), *_norm_args("norm2", norm2, c), norm2.eps,
             b, h, w, c, attn.heads, shift, attn.scale, _threads()):
        raise MemoryError("roguenerf.native.lewin_attention: out of memory for its window buffers")
    _account("lewin_attention", x, x_out, normed)
    profiling.add_flops(b * h * w * (8 * c * c + 4 * 16 * c))  # the two linears (3C + C outputs) and the attention
    return x_out, normed


def gauss_newton(points: Tensor, sampled: Tensor, render: Tensor, use: Tensor, pose: Tensor, K: Tensor,
                 c: float) -> tuple[Tensor, Tensor]:
    """The summed normal equations of a pose fit's Gauss-Newton step
    (:func:`roguenerf.ops.gauss_newton.normal_equations`): ``points`` ``(N, 3)``, ``sampled``
    ``(9, N)``, ``render`` ``(3, N)``, ``use`` ``(N,)`` (0 or 1), ``pose`` ``(3, 4)``, ``K``
    ``(3, 3)`` -> ``A`` ``(6, 6)`` and ``b`` ``(6,)`` float64 (summed in double, handed back
    through float32)."""
    n = points.shape[0]
    out = torch.empty(42)
    _call("rg_gauss_newton", _arg("points", points, (n, 3)), _arg("sampled", sampled, (9, n)),
          _arg("render", render, (3, n)), _arg("use", use, (n,)), _arg("pose", pose, (3, 4)), _arg("K", K, (3, 3)),
          float(c), n, _arg("out", out, (42,)), _threads())
    _account("gauss_newton", points, sampled, render, use)
    return out[:36].reshape(6, 6).double(), out[36:].double()


def vector_width() -> int:
    """Float lanes per vector the kernels were compiled for: 16 with AVX-512, 8 with AVX, else 4."""
    return _call("rg_vector_width")


def leff_supported(channels: int, hidden: int) -> bool:
    """:func:`leff` handles ``channels`` a multiple of 8 and ``hidden`` of :func:`vector_width`,
    and is used where it measured faster than oneDNN (``bench/stages.py``): at every Uformer
    level with 16-lane vectors, at up to 16 channels with 8-lane ones; not with 4-lane ones (a
    build without -march=native, while oneDNN picks the CPU's own vectors at run time)."""
    lanes = vector_width()
    return channels % 8 == 0 and hidden % lanes == 0 and (lanes == 16 or (lanes == 8 and channels <= 16))


def _column_tiles(weight_t: Tensor, widths: tuple[int, ...]) -> Tensor:
    """``(K, N)`` -> its column tiles (greedy widths) one after another, each ``(K, width)``
    row-major: the layout ``rg_leff`` reads."""
    n, tiles, start = weight_t.shape[1], [], 0
    while start < n:
        width = next(w for w in widths if start + w <= n)
        tiles.append(weight_t[:, start:start + width].reshape(-1))
        start += width
    return torch.cat(tiles).contiguous()


def _packed(module: torch.nn.Module, params: tuple[Tensor, ...], pack: Callable[[], tuple[Tensor, ...]]):
    """``pack()``: ``params`` in a kernel's layout, cached on ``module`` until one of them changes
    (weights made in inference mode have no version counter: packed on every call)."""
    inference = any(p.is_inference() for p in params)
    key = None if inference else tuple((p._version, p.data_ptr()) for p in params)
    cached = getattr(module, "_native_weights", None)
    if inference or cached is None or cached[0] != key:
        with torch.no_grad():
            cached = (key, pack())
        module._native_weights = cached
    return cached[1]


def _leff_weights(module: torch.nn.Module) -> tuple[Tensor, ...]:
    """The LeFF's weights in ``rg_leff``'s layout."""
    up, dw, down = module.linear1[0], module.dwconv[0], module.linear2
    lanes, hidden = vector_width(), up.out_features
    return _packed(module, (up.weight, up.bias, dw.weight, dw.bias, down.weight, down.bias), lambda: (
        _column_tiles(up.weight.t(), (2 * lanes, lanes)), up.bias.contiguous(),
        dw.weight.reshape(hidden, 9).t().contiguous(), dw.bias.contiguous(),
        _column_tiles(down.weight.t(), (32, 16, 8) if lanes == 16 else (16, 8)), down.bias.contiguous()))


def leff(x: Tensor, residual: Tensor | None, module: torch.nn.Module) -> Tensor:
    """``residual + module(x)`` for a :class:`roguenerf.models.uformer.LeFF` ``module``
    (``linear2(gelu(dwconv(gelu(linear1(x)))))``), ``x`` and ``residual`` ``(B, H, W, C)``
    contiguous, in one pass; see :func:`leff_supported` for the shapes it takes."""
    b, h, w, c = x.shape
    hidden = module.linear1[0].out_features
    x_arg, residual_arg = _arg("x", x, (b, h, w, c)), _arg("residual", residual, (b, h, w, c), optional=True)
    for arg in (x_arg, residual_arg):  # the caller's tensors checked first, then the sizes
        _pointer("rg_leff", arg)
    _sizes("leff", a_supported_channel_count=leff_supported(c, hidden) and module.linear2.out_features == c)
    w1, b1, wdw, bdw, w2, b2 = _leff_weights(module)
    out = torch.empty(b, h, w, c)
    if _call("rg_leff", x_arg, residual_arg, _arg("out", out, (b, h, w, c)), _arg("w1", w1, (c * hidden,)),
             _arg("b1", b1, (hidden,)),
             _arg("wdw", wdw, (9, hidden)), _arg("bdw", bdw, (hidden,)), _arg("w2", w2, (hidden * c,)),
             _arg("b2", b2, (c,)), b, h, w, c, hidden, _threads()):
        raise MemoryError("roguenerf.native.leff: out of memory for its row buffers")
    _account("leff", x, residual, out)
    profiling.add_flops(2 * b * h * w * hidden * (2 * c + 9))  # the two linears and the 3 x 3 depthwise conv
    return out


def conv3x3_supported(conv: torch.nn.Conv2d) -> bool:
    """:func:`conv3x3` computes ``conv``: 3 x 3, stride 1, zero padding 1, no groups or dilation."""
    return (tuple(conv.kernel_size) == (3, 3) and tuple(conv.stride) == (1, 1) and conv.padding == (1, 1)
            and tuple(conv.dilation) == (1, 1) and conv.groups == 1 and conv.padding_mode == "zeros")


def conv3x3(x: Tensor, weight: Tensor, bias: Tensor | None = None) -> Tensor:
    """``conv2d(x[:, :Cin], weight, bias, padding=1)`` for ``x`` ``(B, Cs, H, W)`` channels-last
    with ``Cs >= Cin`` and ``weight`` ``(Co, Cin, 3, 3)`` -> ``(B, Co, H, W)`` channels-last: the
    channels of ``x`` past ``Cin`` are skipped without a copy. The kernel works in blocks of 8
    output channels: other counts are computed with zero weights up to the next multiple of 8
    and returned as a view of the first ``Co`` (the Uformer's 3-channel output)."""
    b, cs, h, w = x.shape
    co, cin = weight.shape[:2]
    if cin > cs or tuple(weight.shape[2:]) != (3, 3):
        raise NativeArgumentError(f"roguenerf.native.conv3x3: weight {tuple(weight.shape)} does not fit input "
                                  f"{tuple(x.shape)}")
    weight = weight.detach()
    bias = bias.detach() if bias is not None else None
    padded = -(-co // 8) * 8
    if padded != co:
        weight = torch.cat([weight, weight.new_zeros(padded - co, *weight.shape[1:])])
        bias = torch.cat([bias, bias.new_zeros(padded - co)]) if bias is not None else None
    packed = weight.permute(2, 3, 1, 0).contiguous()  # (3, 3, Cin, Co)
    bias = bias.contiguous() if bias is not None else None
    out = torch.empty(b, padded, h, w, memory_format=torch.channels_last)
    _call("rg_conv3x3", _arg("x", x, (b, cs, h, w), layout="channels_last"),
          _arg("weight", packed, (3, 3, cin, padded)),
          _arg("bias", bias, (padded,), optional=True), _arg("out", out, (b, padded, h, w), layout="channels_last"),
          b, h, w, cs, cin, padded, _threads())
    _account("conv3x3", x[:, :cin], out)
    profiling.add_flops(2 * 9 * cin * co * b * h * w)
    return out[:, :co] if padded != co else out

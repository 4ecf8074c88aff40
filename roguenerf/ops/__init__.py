"""One dispatch point per operation: each operation that has several bodies (a fused C kernel
of :mod:`roguenerf.native`, torch's fast path, the plain reference) is one function here, and
chooses its body with :func:`~roguenerf.ops.backend.pick` on every call: NATIVE where the
kernels are built and allowed, else FAST, else TORCH (with gradient) or REFERENCE (inside
:func:`~roguenerf.fastpath.reference_mode`). Model and geometry code call these functions; the
reference bodies are the ground truth of ``tests/unit/roguenerf/native/test_fastpath.py`` and
``tests/unit/roguenerf/native/test_native.py``.

====================  ============================================  ==============================
operation             function                                      bodies
====================  ============================================  ==============================
reprojection          :func:`reproject`                             native, fast, reference
sampling              :func:`sample`                                fast, reference
window attention      :func:`window_attention`                      native, fast, torch, reference
LeWin block           :func:`lewin_block`                           native, torch / reference
LeFF                  :func:`leff`                                  native, fast, reference
pixel attention tail  :func:`attend_pool`, :func:`pool_neighbours`  native, fast
flow                  :func:`warp`, :func:`upsample_warp`,          native, fast, reference
                      :func:`pool_flow`, :func:`gru_gates`
3x3 convolution       :func:`conv3x3`                               native, torch
linear / conv + act   :func:`linear`, :func:`linear_add`,           fast (oneDNN), reference
                      :func:`conv2d`, :func:`conv_act`
concatenation         :func:`cat_channels`, :func:`pack_channels`   channels-last, plain
blur, image gradient  :func:`gaussian_blur`,                         torch, reference (kornia)
                      :func:`spatial_gradient`
pose fit step         ``gauss_newton.normal_equations``             native, reference
====================  ============================================  ==============================
"""

from roguenerf.ops import flow, gauss_newton
from roguenerf.ops.attention import attend_pool
from roguenerf.ops.attention import pool as pool_neighbours
from roguenerf.ops.backend import Body, pick
from roguenerf.ops.filters import box_sum3, gaussian_blur, spatial_gradient
from roguenerf.ops.flow import gru_gates, upsample_warp, warp
from roguenerf.ops.flow import pool as pool_flow
from roguenerf.ops.flow import upsample as upsample_flow
from roguenerf.ops.fused import (
    cat_channels,
    cat_channels_last,
    channels_last,
    conv2d,
    conv3x3,
    conv_act,
    linear,
    linear_add,
)
from roguenerf.ops.reproject import pack_channels, reproject, sample
from roguenerf.ops.uformer import leff, lewin_block, window_attention

__all__ = ["Body", "attend_pool", "box_sum3", "cat_channels", "cat_channels_last", "channels_last", "conv2d", "conv3x3",
           "conv_act", "flow", "gauss_newton", "gaussian_blur", "gru_gates", "leff", "lewin_block", "linear",
           "linear_add", "pack_channels", "pick", "pool_flow", "pool_neighbours", "reproject", "sample",
           "spatial_gradient", "upsample_flow", "upsample_warp", "warp", "window_attention"]
